#!/usr/bin/env python3
"""Merges eval_lift shards (scripts/gpu_eval_shards.sh) into one table per model, and compares two models
on the same objects.

  merge_eval_shards.py --model LABEL GLOB [--model LABEL GLOB ...] [--compare A B] [--bootstrap N] [--seed S]

Each GLOB names summary.json files of one model (quote it); their "base" rows, or with GLOB@compare the
rows of the --compare-adapter model (so that base and adapter of the same shards pair up). Per model, depth and visibility bucket
(plus "all"): n, mean IoU, F@1cm, F@2cm, Chamfer (mm), median rotation (deg), translation (cm), scale
(%), mean shape IoU, recomputed from the per-object rows (failed lifts count as eval_lift counts them:
left out of the means, shown as n_failed). --compare A B adds B - A paired by object (scene, object,
depth), with 95% percentile bootstrap intervals.
"""
import argparse
import glob
import json
import random
import statistics
import sys

BUCKETS = ["unoccluded", "70-100%", "40-70%", "<40%"]


def rows_of(pattern):
    model = "base"
    if pattern.endswith("@compare"):
        pattern, model = pattern[: -len("@compare")], "compare"
    files = sorted(glob.glob(pattern))
    if not files:
        sys.exit(f"merge_eval_shards.py: no file matches {pattern}")
    rows, seen = [], set()
    for f in files:
        for r in json.load(open(f))["objects"]:
            if r.get("model", "base") != model:
                continue
            key = (r["object"], r["depth"])
            if key in seen:
                sys.exit(f"merge_eval_shards.py: {key} appears twice in {pattern} (overlapping shards)")
            seen.add(key)
            rows.append(r)
    return files, rows


def agg(rs):
    ok = [r for r in rs if r.get("ok")]
    if not ok:
        return None
    med = lambda k: statistics.median(r[k] for r in ok if r.get(k) is not None)
    mean = lambda k: statistics.fmean(r[k] for r in ok if r.get(k) is not None)
    return {"n": len(ok), "n_failed": len(rs) - len(ok), "iou": mean("iou"), "f1": mean("fscore_1cm"),
            "f2": mean("fscore_2cm"), "cd_mm": 1000 * mean("chamfer"), "rot": med("rot_err_deg"),
            "trans_cm": 100 * med("trans_err"), "scale": med("scale_err_pct"), "shape_iou": mean("shape_iou")}


def boot(xs, rng, b):
    n = len(xs)
    ms = sorted(sum(xs[rng.randrange(n)] for _ in range(n)) / n for _ in range(b))
    return ms[int(0.025 * b)], ms[int(0.975 * b) - 1]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", nargs=2, action="append", metavar=("LABEL", "GLOB"), required=True)
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"))
    ap.add_argument("--bootstrap", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    models = {}
    for label, pattern in a.model:
        files, rows = rows_of(pattern)
        models[label] = rows
        print(f"{label}: {len(files)} shard(s), {len(rows)} object rows ({pattern})")
    print()
    print("| model | depth | bucket | n | IoU | F@1cm | F@2cm | CD mm | rot deg | trans cm | scale % | shape IoU |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for label, rows in models.items():
        for depth in sorted({r["depth"] for r in rows}):
            rd = [r for r in rows if r["depth"] == depth]
            for b in BUCKETS + ["all"]:
                g = agg(rd if b == "all" else [r for r in rd if r["bucket"] == b])
                if g:
                    print(f"| {label} | {depth} | {b} | {g['n']} | {g['iou']:.3f} | {g['f1']:.3f} | {g['f2']:.3f} | "
                          f"{g['cd_mm']:.1f} | {g['rot']:.1f} | {g['trans_cm']:.1f} | {g['scale']:.1f} | {g['shape_iou']:.3f} |")
    if a.compare:
        A, B = a.compare
        rng = random.Random(a.seed)
        ia = {(r["object"], r["depth"]): r for r in models[A] if r.get("ok")}
        ib = {(r["object"], r["depth"]): r for r in models[B] if r.get("ok")}
        keys = sorted(set(ia) & set(ib))
        print(f"\n{B} - {A}, paired by object ({len(keys)} pairs; 95% bootstrap interval):\n")
        print("| depth | bucket | n | IoU delta | shape IoU delta | F@2cm delta |")
        print("|---|---|---:|---:|---:|---:|")
        for depth in sorted({k[1] for k in keys}):
            for b in BUCKETS + ["all"]:
                ks = [k for k in keys if k[1] == depth and (b == "all" or ia[k]["bucket"] == b)]
                if len(ks) < 2:
                    continue
                cells = []
                for m in ("iou", "shape_iou", "fscore_2cm"):
                    d = [ib[k][m] - ia[k][m] for k in ks]
                    lo, hi = boot(d, rng, a.bootstrap)
                    cells.append(f"{statistics.fmean(d):+.4f} [{lo:+.4f}, {hi:+.4f}]")
                print(f"| {depth} | {b} | {len(ks)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
