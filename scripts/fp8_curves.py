#!/usr/bin/env python3
"""Compare the loss/accuracy curves of two FM-DPO runs on the same cache: the bf16 base and the FP8
frozen base (configs/fp8_curves.yaml, docs/training.md "FP8 frozen base").

    scripts/fp8_curves.py --bf16 runs/fp8_curves/bf16/metrics.jsonl --fp8 runs/fp8_curves/fp8/metrics.jsonl \
        --csv runs/fp8_curves/curves.csv [--png runs/fp8_curves/curves.png] [--window 50]

Writes one CSV row per step both runs logged (step, then loss, accuracy, margin, grad_norm of each run),
prints a summary (means over the last --window steps, the mean and max |difference| of the loss per step,
the Pearson correlation of the two loss curves and of their running means), and draws the PNG when
matplotlib can be imported (else says so; the CSV is enough to plot elsewhere). Outputs are written
atomically. Standard library only (plus optional matplotlib).
"""
import argparse
import csv
import io
import json
import math
import os
import sys

KEYS = ("loss", "accuracy", "margin", "grad_norm")


def read_metrics(path):
    """step -> {key: value} from a train_fmdpo metrics.jsonl; errors name the file and line."""
    out = {}
    with open(path, encoding="utf-8") as f:
        for n, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
                out[int(rec["step"])] = {k: rec.get(k) for k in KEYS}
            except (ValueError, KeyError, TypeError) as e:
                sys.exit(f"{path}:{n}: not a metrics record ({e})")
    if not out:
        sys.exit(f"{path}: no metrics records")
    return out


def atomic_write(path, data, mode="w"):
    tmp = f"{path}.tmp-{os.getpid()}"
    with open(tmp, mode) as f:
        f.write(data)
    os.replace(tmp, path)


def mean(v):
    v = [x for x in v if x is not None]
    return sum(v) / len(v) if v else float("nan")


def pearson(a, b):
    ma, mb = mean(a), mean(b)
    num = sum((x - ma) * (y - mb) for x, y in zip(a, b))
    den = math.sqrt(sum((x - ma) ** 2 for x in a) * sum((y - mb) ** 2 for y in b))
    return num / den if den > 0 else float("nan")


def running_mean(v, w):
    out, acc = [], 0.0
    for i, x in enumerate(v):
        acc += x
        if i >= w:
            acc -= v[i - w]
        out.append(acc / min(i + 1, w))
    return out


def plot(png, steps, runs, window):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"matplotlib not importable here: no {png} (plot the CSV elsewhere)")
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key in zip(axes, ("loss", "accuracy")):
        for name, m in runs.items():
            v = [m[s][key] for s in steps]
            (line,) = ax.plot(steps, running_mean(v, window), label=f"{name} (running mean {window})")
            ax.plot(steps, v, alpha=0.2, color=line.get_color())
        ax.set_xlabel("step")
        ax.set_ylabel(key)
        ax.legend()
    fig.suptitle("FM-DPO, bf16 base vs FP8 frozen base, same cache")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    atomic_write(png, buf.getvalue(), "wb")
    print(f"plot: {png}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bf16", required=True, help="metrics.jsonl of the bf16-base run")
    ap.add_argument("--fp8", required=True, help="metrics.jsonl of the FP8-base run")
    ap.add_argument("--csv", required=True, help="output CSV")
    ap.add_argument("--png", default="", help="output plot (needs matplotlib)")
    ap.add_argument("--window", type=int, default=50, help="steps of the final means and running means (default 50)")
    a = ap.parse_args()
    runs = {"bf16": read_metrics(a.bf16), "fp8": read_metrics(a.fp8)}
    steps = sorted(set(runs["bf16"]) & set(runs["fp8"]))
    if not steps:
        sys.exit(f"{a.bf16} and {a.fp8} have no step in common")
    text = io.StringIO()
    w = csv.writer(text)
    w.writerow(["step"] + [f"{k}_{r}" for r in runs for k in KEYS])
    for s in steps:
        w.writerow([s] + [runs[r][s][k] for r in runs for k in KEYS])
    atomic_write(a.csv, text.getvalue())
    last = steps[-a.window:]
    lb, lf = [runs["bf16"][s]["loss"] for s in steps], [runs["fp8"][s]["loss"] for s in steps]
    diff = [abs(x - y) for x, y in zip(lb, lf)]
    print(f"{len(steps)} common steps ({steps[0]}..{steps[-1]}); CSV: {a.csv}")
    for r in runs:
        print(f"{r:>5}: last {len(last)} steps mean loss {mean([runs[r][s]['loss'] for s in last]):.5f}, "
              f"accuracy {mean([runs[r][s]['accuracy'] for s in last]):.4f}, "
              f"margin {mean([runs[r][s]['margin'] for s in last]):.4f}")
    print(f"loss per step: mean |bf16 - fp8| {mean(diff):.3g}, max {max(diff):.3g}; "
          f"correlation {pearson(lb, lf):.4f} (running means: "
          f"{pearson(running_mean(lb, a.window), running_mean(lf, a.window)):.4f})")
    if a.png:
        plot(a.png, steps, runs, a.window)


if __name__ == "__main__":
    main()
