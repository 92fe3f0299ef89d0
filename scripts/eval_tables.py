#!/usr/bin/env python3
"""Markdown tables from eval_lift summaries (docs/results.md, docs/miniature.md).

  eval_tables.py buckets SUMMARY [LABEL]           the per-bucket table of a run (every depth, model)
  eval_tables.py deltas ROW_LABEL:BUCKET:SUMMARY ...  one row per argument: base / tuned / delta (95% CI)
                                                   of iou_mean, shape_iou_mean and fscore_2cm
"""
import json
import sys

COLS = [("n", "n", "{:d}"), ("iou_mean", "IoU", "{:.3f}"), ("fscore_1cm", "F@1cm", "{:.3f}"),
        ("fscore_2cm", "F@2cm", "{:.3f}"), ("chamfer_mean", "CD mm", "mm"), ("rot_err_deg_median", "rot deg", "{:.1f}"),
        ("trans_err_median", "trans cm", "cm"), ("scale_err_pct_median", "scale %", "{:.1f}"),
        ("shape_iou_mean", "shape IoU", "{:.3f}")]


def fmt(v, f):
    if v is None:
        return "-"
    if f == "mm":
        return f"{1000 * v:.1f}"
    if f == "cm":
        return f"{100 * v:.1f}"
    return f.format(v)


def buckets(path, label=""):
    s = json.load(open(path))
    print("| " + " | ".join(["run", "point map", "model", "bucket"] + [c[1] for c in COLS]) + " |")
    print("|" + "---|" * 4 + "---:|" * len(COLS))
    for depth, models in s["buckets"].items():
        for model, bs in models.items():
            for b, agg in bs.items():
                if agg["n"] == 0:
                    continue
                print("| " + " | ".join([label, depth, model, b] + [fmt(agg[k], f) for k, _, f in COLS]) + " |")


def deltas(items):
    print("| row | n | IoU base / tuned | IoU delta (95% CI) | shape IoU base / tuned | shape IoU delta (95% CI) | F@2cm delta (95% CI) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for it in items:
        label, bucket, path = it.split(":", 2)
        d = json.load(open(path))["deltas"]["clean"][bucket]
        cells = [label, str(d["n"])]
        for k in ("iou_mean", "shape_iou_mean", "fscore_2cm"):
            x = d[k]
            ci = f"{x['delta']:+.4f} [{x['ci95'][0]:+.4f}, {x['ci95'][1]:+.4f}]"
            if k == "fscore_2cm":
                cells.append(ci)
            else:
                cells += [f"{x['base']:.3f} / {x['compare']:.3f}", ci]
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "buckets":
        buckets(sys.argv[2], sys.argv[3] if len(sys.argv) > 3 else "")
    elif len(sys.argv) >= 3 and sys.argv[1] == "deltas":
        deltas(sys.argv[2:])
    else:
        print(__doc__)
        sys.exit(2)
