#!/usr/bin/env python3
"""Compares an eval_lift summary with the values the shipped miniature's manifest records.

  shipped_eval_check.py MANIFEST SUMMARY [adapter]

manifest["ci_check"] = {"args": [...], "metrics": {"<depth>/<bucket>/<key>": value}, "tolerance": {key: t},
"tolerance_source": text}. Every recorded metric must reach value - tolerance[key] (higher is better for
each recorded key). Prints a table of recorded / measured / floor and exits 1 on any shortfall.
With "adapter": manifest["ci_check_adapter"] against the summary's paired deltas (check_adapter).
"""
import json
import sys


def check_adapter(manifest, summary) -> int:
    """manifest["ci_check_adapter"] = {"args", "deltas": {"<depth>/<bucket>/<key>": delta}, "tolerance": t,
    "tolerance_source"}: each paired delta (base + adapter - base) must reach its recorded value - t."""
    check = manifest["ci_check_adapter"]
    failed = 0
    print(f"{'adapter delta':<40} {'recorded':>9} {'measured':>9} {'floor':>9}")
    for path, recorded in sorted(check["deltas"].items()):
        depth, bucket, key = path.split("/")
        got = summary["deltas"][depth][bucket][key]["delta"]
        floor = recorded - check["tolerance"]
        ok = got is not None and got >= floor
        failed += not ok
        print(f"{path:<40} {recorded:+9.4f} {got if got is not None else float('nan'):+9.4f} {floor:+9.4f}"
              f"{'' if ok else '   FAIL'}")
    print(f"tolerance: {check['tolerance_source']}")
    return 1 if failed else 0


def main() -> int:
    manifest = json.load(open(sys.argv[1]))
    summary = json.load(open(sys.argv[2]))
    if len(sys.argv) > 3 and sys.argv[3] == "adapter":
        return check_adapter(manifest, summary)
    check = manifest["ci_check"]
    failed = 0
    print(f"{'metric':<40} {'recorded':>9} {'measured':>9} {'floor':>9}")
    for path, recorded in sorted(check["metrics"].items()):
        depth, bucket, key = path.split("/")
        got = summary["buckets"][depth]["base"][bucket][key]
        floor = recorded - check["tolerance"][key]
        ok = got is not None and got >= floor
        failed += not ok
        print(f"{path:<40} {recorded:9.4f} {got if got is not None else float('nan'):9.4f} {floor:9.4f}"
              f"{'' if ok else '   FAIL'}")
    print(f"tolerance: {check['tolerance_source']}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
