"""simuscene in a Python pipeline: a photo's arrays as a segmenter and a depth model give them -> Stage-1 lift
-> physics probe -> MuJoCo on the result, stepped for 2 s.

    PYTHONPATH=build/python python examples/lift_probe_mujoco.py --out out/example          # small models
    python examples/lift_probe_mujoco.py --generator-weights ... --decoder-weights ... \\
        --embedder-weights ... --out out/example                                         # released weights

Without weights it runs the small test models of shared/fixtures with a RANDOM embedder, and a copy of the
fixture decoder whose last layer is set to occupy every voxel, so each object meshes to its bounding cube
(CI runs it that way to show every step connects; the shapes mean nothing). The photo is synthetic.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Tuple

import mujoco
import numpy as np

import simuscene as ss

ROOT = Path(__file__).resolve().parents[1]


def synthetic_photo(h: int = 120, w: int = 160, f: float = 150.0) -> Tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                       np.ndarray, ss.Plane, np.ndarray]:
    """What SAM (a label map) and MoGe (an OpenCV point map, inf where invalid) would give for a camera
    1 m above a floor looking down at 30 degrees, with a box standing on it."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(cols - w / 2) / f, (rows - h / 2) / f, np.ones_like(cols)], -1)
    tilt = np.deg2rad(30)
    # Camera frame (x right, y down, z forward); "down" in the world is +y rotated by the tilt.
    down = np.array([0, np.cos(tilt), np.sin(tilt)])
    depth_floor = 1.0 / np.maximum(rays @ down, 1e-6)
    points = rays * depth_floor[..., None]
    points[(rays @ down) <= 0.05] = np.inf  # sky: MoGe's invalid points
    labels = np.zeros((h, w), np.uint8)
    box = (cols > 65) & (cols < 95) & (rows > 55) & (rows < 85)
    labels[box] = 1
    points[box] *= 0.92  # the box stands out of the floor
    rgb = np.clip(np.stack([90 + 0 * cols, 60 + rows, 40 + cols], -1), 0, 255).astype(np.uint8)
    rgb[box] = (200, 60, 40)
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    floor = ss.Plane("floor", point=down * 1.0, normal=-down)  # 1 m below the camera, normal up
    return rgb, labels, points.astype(np.float32), K, floor, down


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/example")
    shared = Path(os.environ.get("SIMU_SHARED_DIR", ROOT.parent / "shared")) / "fixtures"
    ap.add_argument("--generator-config", default=str(shared / "ss_generator_small.json"))
    ap.add_argument("--generator-weights", default=str(shared / "ss_generator_small.safetensors"))
    ap.add_argument("--decoder-config", default=str(shared / "ss_decoder_small.json"))
    ap.add_argument("--decoder-weights", default=None, help="default: the fixture decoder made to occupy every voxel")
    ap.add_argument("--embedder-config", default=str(ROOT / "configs" / "demo_embedder_small.json"))
    ap.add_argument("--embedder-weights", default=None)
    ap.add_argument("--steps", type=int, default=4)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(name)s %(levelname)s %(message)s")

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.decoder_weights is None:
        from safetensors.torch import load_file, save_file
        import torch

        w = load_file(str(shared / "ss_decoder_small.safetensors"))
        w["out_layer.2.weight"] = torch.zeros_like(w["out_layer.2.weight"])
        w["out_layer.2.bias"] = torch.full_like(w["out_layer.2.bias"], 2.0)  # logit 2 everywhere: all occupied
        args.decoder_weights = str(out / "ss_decoder_cube.safetensors")
        save_file(w, args.decoder_weights)
    rgb, labels, points, K, floor, gravity = synthetic_photo()
    stage1 = ss.Stage1(args.generator_config, args.generator_weights, args.decoder_config, args.decoder_weights,
                       args.embedder_config, args.embedder_weights, random_weights=args.embedder_weights is None,
                       device="auto", steps=args.steps)
    if stage1.random_weights_banner:
        print(f"*** {stage1.random_weights_banner} ***")
    lifted = stage1.lift(rgb, labels, pointmap=points, K=K)
    for o in lifted:
        print(f"{o.id}: {'ok' if o.ok else 'FAILED: ' + o.error}")
    scene = lifted.to_scene(out / "lift", overwrite=True)
    scene.gravity = gravity
    scene.floor = floor
    # A pipeline step of your own on the Scene: place each object on its observed points (centre and
    # extent of the point map under its mask; the random-weights pose alone would put it anywhere).
    for obj in scene.objects:
        k = int(obj.id.split("_")[-1])
        pts = points[(labels == k) & np.isfinite(points).all(-1)]
        obj.t = 0.5 * (pts.min(0) + pts.max(0)) - 0.05 * gravity
        obj.scale = float(np.ptp(pts, axis=0).max())
    result = ss.probe(scene, config=ROOT / "configs" / "probe.yaml", overrides={"collision.use_coacd": False},
                      out=out / "probe", overwrite=True, resampler=stage1)
    print(result.summary)
    print(result.metrics_table)
    print("pictures:", {k: v.shape for k, v in result.pictures.items()})
    assert result.mjcf_path is not None
    model = mujoco.MjModel.from_xml_path(result.mjcf_path)
    data = mujoco.MjData(model)
    steps = int(round(2.0 / model.opt.timestep))
    for _ in range(steps):
        mujoco.mj_step(model, data)
    print(f"MuJoCo {mujoco.__version__}: {result.mjcf_path} stepped {steps} x {model.opt.timestep:.5f} s = "
          f"{data.time:.2f} s; {model.nbody} bodies, max |qvel| {np.abs(data.qvel).max(initial=0):.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
