#!/usr/bin/env python3
"""Compares an eval_lift summary with the values the shipped miniature's manifest records.

  shipped_eval_check.py MANIFEST SUMMARY [adapter]

manifest["ci_check"] = {"args": [...], "metrics": {"<depth>/<bucket>/<key>": value}, "tolerance": {key: t},
"tolerance_source": text}. Every recorded metric must reach value - tolerance[key] (higher is better for
each recorded key). Prints a table of recorded / measured / floor and exits 1 on any shortfall.
With "adapter": manifest["ci_check_adapter"] = {"args", "deltas": {"<depth>/<bucket>/<key>": delta},
"tolerance": t, "tolerance_source"}: each paired delta (base + adapter - base) of the summary must reach
its recorded value - t.
"""
import json
import sys


def check(title, recorded_values, measured, tolerance, source, sign="") -> int:
    """Prints recorded / measured / floor per "<depth>/<bucket>/<key>" path; returns 1 on any shortfall.
    measured(depth, bucket, key) reads the summary; tolerance(key) gives the allowed drop."""
    failed = 0
    print(f"{title:<40} {'recorded':>9} {'measured':>9} {'floor':>9}")
    for path, recorded in sorted(recorded_values.items()):
        depth, bucket, key = path.split("/")
        got = measured(depth, bucket, key)
        floor = recorded - tolerance(key)
        ok = got is not None and got >= floor
        failed += not ok
        shown = got if got is not None else float("nan")
        print(f"{path:<40} {recorded:{sign}9.4f} {shown:{sign}9.4f} {floor:{sign}9.4f}{'' if ok else '   FAIL'}")
    print(f"tolerance: {source}")
    return 1 if failed else 0


def main() -> int:
    manifest = json.load(open(sys.argv[1]))
    summary = json.load(open(sys.argv[2]))
    if len(sys.argv) > 3 and sys.argv[3] == "adapter":
        c = manifest["ci_check_adapter"]
        return check("adapter delta", c["deltas"], lambda d, b, k: summary["deltas"][d][b][k]["delta"],
                     lambda k: c["tolerance"], c["tolerance_source"], sign="+")
    c = manifest["ci_check"]
    return check("metric", c["metrics"], lambda d, b, k: summary["buckets"][d]["base"][b][k],
                 lambda k: c["tolerance"][k], c["tolerance_source"])


if __name__ == "__main__":
    sys.exit(main())
