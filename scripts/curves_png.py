#!/usr/bin/env python3
"""Training curves of one or more runs as a PNG, drawn with Pillow (no matplotlib needed).

    scripts/curves_png.py --run "H200 miniature=runs/gpu_mini/stage1/metrics.jsonl" \
        --run "CPU miniature=runs/stage1_cpu/metrics.jsonl" \
        --keys loss loss/6drotation_normalized loss/shape loss/translation --x samples --window 50 \
        --out docs/img/miniature_curves.png

One panel per key (a logarithmic y axis when --log), one line per run: the running mean over --window
logged records. --x step plots against the step, --x samples against step x the run's global batch
(the metrics' samples_per_s does not say it; --batch NAME=N does, default 256). Errors name the file
and line. The PNG is written atomically.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys

from PIL import Image, ImageDraw

COLORS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14)]


def read(path: str, keys: list[str]) -> list[dict]:
    rows = []
    with open(path, encoding="utf-8") as f:
        for n, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except ValueError as e:
                sys.exit(f"{path}:{n}: not JSON ({e})")
            if "step" in rec and any(k in rec for k in keys):
                rows.append(rec)
    if not rows:
        sys.exit(f"{path}: no records with a step and one of {keys}")
    return rows


def smooth(xs: list[float], ys: list[float], window: int) -> tuple[list[float], list[float]]:
    out_x, out_y, acc = [], [], []
    for x, y in zip(xs, ys):
        acc.append(y)
        if len(acc) > window:
            acc.pop(0)
        out_x.append(x)
        out_y.append(sum(acc) / len(acc))
    return out_x, out_y


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", action="append", required=True, help="NAME=metrics.jsonl (repeatable)")
    ap.add_argument("--batch", action="append", default=[], help="NAME=global batch, for --x samples (default 256)")
    ap.add_argument("--keys", nargs="+", default=["loss"])
    ap.add_argument("--x", choices=["step", "samples"], default="step")
    ap.add_argument("--window", type=int, default=50)
    ap.add_argument("--log", action="store_true", help="logarithmic y axes")
    ap.add_argument("--title", default="")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    batches = {}
    for b in a.batch:
        name, _, n = b.partition("=")
        batches[name] = int(n)
    runs = []
    for r in a.run:
        name, sep, path = r.partition("=")
        if not sep:
            sys.exit(f"--run {r}: expected NAME=metrics.jsonl")
        rows = read(path, a.keys)
        scale = batches.get(name, 256) if a.x == "samples" else 1
        runs.append((name, rows, scale))

    pw, ph, margin = 460, 300, 60
    cols = 2
    nrows = math.ceil(len(a.keys) / cols)
    top = 40
    img = Image.new("RGB", (cols * (pw + margin) + margin, top + nrows * (ph + margin) + 40), "white")
    d = ImageDraw.Draw(img)
    d.text((margin, 12), a.title, fill="black")
    for i, key in enumerate(a.keys):
        ox, oy = margin + (i % cols) * (pw + margin), top + (i // cols) * (ph + margin)
        lines = []
        for name, rows, scale in runs:
            pts = [(r["step"] * scale, r[key]) for r in rows if isinstance(r.get(key), (int, float)) and math.isfinite(r[key])]
            if a.log:
                pts = [(x, y) for x, y in pts if y > 0]
            if pts:
                lines.append((name, *smooth([p[0] for p in pts], [p[1] for p in pts], a.window)))
        if not lines:
            sys.exit(f"no run logs '{key}'")
        f = (lambda y: math.log10(y)) if a.log else (lambda y: y)
        x0, x1 = 0.0, max(max(xs) for _, xs, _ in lines)
        # The y range: the smoothed curves after their first 2% (the first steps' loss dwarfs the rest).
        tail = [f(y) for _, xs, ys in lines for x, y in zip(xs, ys) if x >= 0.02 * x1]
        y0, y1 = min(tail), max(tail)
        if y1 - y0 < 1e-12:
            y1 = y0 + 1
        d.rectangle([ox, oy, ox + pw, oy + ph], outline="black")
        d.text((ox, oy - 14), key + (" (log10)" if a.log else ""), fill="black")
        for t in range(5):
            yv = y0 + (y1 - y0) * t / 4
            yy = oy + ph - (yv - y0) / (y1 - y0) * ph
            d.line([ox - 4, yy, ox, yy], fill="black")
            d.text((ox - 56, yy - 6), f"{(10 ** yv if a.log else yv):.3g}", fill="black")
            xv = x0 + (x1 - x0) * t / 4
            xx = ox + (xv - x0) / (x1 - x0) * pw
            d.line([xx, oy + ph, xx, oy + ph + 4], fill="black")
            d.text((xx - 14, oy + ph + 6), f"{xv:.3g}", fill="black")
        d.text((ox + pw - 60, oy + ph + 20), a.x, fill="black")
        for j, (name, xs, ys) in enumerate(lines):
            pts = [(ox + (x - x0) / (x1 - x0) * pw, oy + ph - (min(max(f(y), y0), y1) - y0) / (y1 - y0) * ph)
                   for x, y in zip(xs, ys)]
            d.line(pts, fill=COLORS[j % len(COLORS)], width=2)
            d.text((ox + 8, oy + 6 + 14 * j), f"{name}: {ys[-1]:.3g} at {xs[-1]:.3g}", fill=COLORS[j % len(COLORS)])
    tmp = a.out + f".tmp-{os.getpid()}.png"
    img.save(tmp)
    os.replace(tmp, a.out)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
