#!/usr/bin/env python3
"""The scene picture of docs/world.md from folders written by `world scenes --corrupt --edited`.

One row per scene: the RGB image, the label image (one colour per label), the clean and the corrupted
point map's depth (z, same colour scale, invalid pixels black) and the edited image (the first target
with its occluders removed). Saved as a 256-colour PNG.
  python3 scripts/world_figure.py OUT.png SCENE_DIR [SCENE_DIR ...]
"""
import glob
import sys

import numpy as np
from PIL import Image


def depth_rgb(z, lo, hi):
    ok = np.isfinite(z)
    t = np.clip((np.where(ok, z, lo) - lo) / max(hi - lo, 1e-9), 0, 1)
    rgb = np.stack([255 * (1 - t), 255 * (0.3 + 0.7 * np.sin(np.pi * t)), 255 * t], -1).astype(np.uint8)
    rgb[~ok] = 0
    return rgb


def main():
    out, dirs = sys.argv[1], sys.argv[2:]
    rows = []
    for d in dirs:
        rgb = np.array(Image.open(f"{d}/image.png").convert("RGB"))
        labels = np.array(Image.open(f"{d}/labels.png")).astype(np.int64)
        palette = np.random.default_rng(3).integers(40, 255, (labels.max() + 1, 3)).astype(np.uint8)
        palette[0] = 0
        clean = np.load(f"{d}/pointmap_clean.npy")[..., 2]
        noisy = np.load(f"{d}/pointmap.npy")[..., 2]
        lo, hi = np.nanpercentile(clean, 1), np.nanpercentile(clean, 99)
        edited = sorted(glob.glob(f"{d}/edited/*/image.png"))
        ed = np.array(Image.open(edited[0]).convert("RGB")) if edited else np.zeros_like(rgb)
        rows.append(np.concatenate([rgb, palette[labels], depth_rgb(clean, lo, hi), depth_rgb(noisy, lo, hi), ed], 1))
    Image.fromarray(np.concatenate(rows, 0)).quantize(256).save(out, optimize=True)


if __name__ == "__main__":
    main()
