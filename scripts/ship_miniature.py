#!/usr/bin/env python3
"""Assembles a shipped model folder (weights/miniature_cpu, docs/miniature.md) from a training run.

  ship_miniature.py --vae runs/ss_vae_cpu --stage1 runs/stage1_cpu --out weights/miniature_cpu
      copies the configs, writes the weights as fp16 safetensors and manifest.json (name, description,
      files, the git commit, the commands and seeds of the runs, sizes);
  ship_miniature.py --out weights/miniature_cpu --eval runs/eval_test/summary.json [--eval ...]
      adds evaluation summaries (eval_lift's summary.json) to the manifest.
Every write goes to a temporary file renamed into place.
"""
from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

ROOT = Path(__file__).resolve().parent.parent


def atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + f".tmp-{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def to_fp16(src: Path, dst: Path) -> None:
    """Floating tensors as float16 (integers kept); metadata says so."""
    tensors = load_file(str(src))
    out = {k: (v.to(torch.float16) if v.is_floating_point() else v).contiguous() for k, v in tensors.items()}
    for k, v in out.items():
        if v.is_floating_point() and not torch.isfinite(v).all():
            sys.exit(f"{src}: tensor {k} is not finite in float16")
    tmp = dst.with_name(dst.name + f".tmp-{os.getpid()}")
    save_file(out, str(tmp), metadata={"format": "pt", "written_by": "scripts/ship_miniature.py", "source": src.name})
    os.replace(tmp, dst)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def git_commit() -> str:
    try:
        return subprocess.check_output(["git", "-C", str(ROOT), "rev-parse", "HEAD"], text=True).strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def run_info(run: Path) -> dict:
    """The run's config as it ran (config.yaml / run_config), the last logged metrics, steps."""
    info: dict = {"dir": os.path.relpath(run, ROOT)}
    for name in ("config.yaml", "run_config.yaml", "train_config.yaml"):
        if (run / name).exists():
            info["config"] = (run / name).read_text()
            break
    metrics = run / "metrics.jsonl"
    if metrics.exists():
        lines = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
        steps = [m for m in lines if "loss" in m]
        if steps:
            info["last_step"] = steps[-1]
        evals = [m for m in lines if any(k.startswith(("test/", "val/")) for k in m)]
        if evals:
            info["last_eval"] = evals[-1]
    if (run / "eval.json").exists():
        info["eval"] = json.loads((run / "eval.json").read_text())
    return info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vae", type=Path, help="train_ss_vae run folder (weights/ss_decoder.*)")
    ap.add_argument("--stage1", type=Path, help="train_stage1 run folder (model/ss_generator.safetensors)")
    ap.add_argument("--preprocess", type=Path, default=ROOT / "configs/miniature_cpu/preprocess.yaml")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--eval", type=Path, action="append", default=[], help="eval_lift summary.json to record")
    ap.add_argument("--commands", type=Path, default=ROOT / "scripts/make_miniature.sh",
                    help="the script whose commands made the weights (recorded in the manifest)")
    ap.add_argument("--note", default="", help="free text recorded in the manifest (how this run differed)")
    ap.add_argument("--name", default="SimuScene CPU miniature", help="the model's name (programs print it)")
    ap.add_argument("--description", default="a small SAM 3D Stage-1 model (MoT flow model 96 ch x 3 blocks, "
                    "DINOv2-architecture embedder, 16^3 sparse-structure VAE) trained from scratch on the procedural "
                    "shape world", help="one line on what the model is (programs print it)")
    a = ap.parse_args()
    out: Path = a.out
    manifest_path = out / "manifest.json"
    if a.vae or a.stage1:
        if not (a.vae and a.stage1):
            sys.exit("--vae and --stage1 go together")
        out.mkdir(parents=True, exist_ok=True)
        dec = a.vae / "weights"
        gen = a.stage1 / "model"
        for need in (dec / "ss_decoder.json", dec / "ss_decoder.safetensors", gen / "ss_generator.safetensors",
                     gen / "generator.yaml", gen / "embedder.json", a.preprocess):
            if not need.exists():
                sys.exit(f"{need}: not found")
        shutil.copyfile(gen / "generator.yaml", out / "generator.yaml")
        shutil.copyfile(gen / "embedder.json", out / "embedder.json")
        shutil.copyfile(dec / "ss_decoder.json", out / "ss_decoder.json")
        shutil.copyfile(a.preprocess, out / "preprocess.yaml")
        to_fp16(gen / "ss_generator.safetensors", out / "ss_generator.safetensors")
        to_fp16(dec / "ss_decoder.safetensors", out / "ss_decoder.safetensors")
        files = {"generator_config": "generator.yaml", "generator_weights": "ss_generator.safetensors",
                 "embedder_config": "embedder.json", "embedder_weights": "ss_generator.safetensors",
                 "decoder_config": "ss_decoder.json", "decoder_weights": "ss_decoder.safetensors",
                 "preprocess": "preprocess.yaml"}
        manifest = {
            "name": a.name,
            "description": a.description,
            "files": files,
            "sha256": {f: sha256(out / f) for f in sorted(set(files.values()))},
            "bytes": sum((out / f).stat().st_size for f in set(files.values())),
            "commit": git_commit(),
            "made": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
            "commands": a.commands.read_text() if a.commands.exists() else "",
            "note": a.note,
            "runs": {"ss_vae": run_info(a.vae), "stage1": run_info(a.stage1)},
            "evaluation": {},
        }
    else:
        if not manifest_path.exists():
            sys.exit(f"{manifest_path}: not found (make the folder first with --vae and --stage1)")
        manifest = json.loads(manifest_path.read_text())
    for summary in a.eval:
        manifest.setdefault("evaluation", {})[str(os.path.relpath(summary.parent, ROOT))] = {k: v for k, v in json.loads(summary.read_text()).items() if k != "objects"}
    atomic_write(manifest_path, (json.dumps(manifest, indent=1) + "\n").encode())
    print(f"wrote {manifest_path} ({manifest.get('bytes', 0) / 1e6:.2f} MB of weights)")


if __name__ == "__main__":
    main()
