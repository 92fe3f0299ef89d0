"""Shared fixtures of the Python suite: the built package, the small fixture models, a synthetic photo.

The package comes from <build>/python (SIMU_BUILD_DIR, default ./build), unless SIMUSCENE_INSTALLED=1
(then the installed one is tested). Models: the Stage-1 fixtures of shared/fixtures (SIMU_SHARED_DIR),
the demo-size embedder on random weights, and a copy of the fixture decoder whose output layer is
0 * x + 2, so every voxel is occupied and every lifted shape meshes to the canonical cube (poses still
come from the sampled latents), as tests/pipeline/resample/lift_test.cpp does.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
BUILD = Path(os.environ.get("SIMU_BUILD_DIR", ROOT / "build"))
if os.environ.get("SIMUSCENE_INSTALLED") != "1":
    sys.path.insert(0, str(BUILD / "python"))

import simuscene as ss  # noqa: E402

SHARED = Path(os.environ.get("SIMU_SHARED_DIR", ROOT.parent / "shared"))
FIX = SHARED / "fixtures"
STEPS = 4  # sampling steps of every test lift (the CLI runs get --steps 4 too)
W, H = 160, 120
F, CX, CY = 150.0, 80.0, 60.0


def fixture(name: str) -> str:
    p = FIX / name
    if not p.exists():
        pytest.skip(f"fixture {p} missing (set SIMU_SHARED_DIR)")
    return str(p)


def program(name: str) -> str:
    p = BUILD / name
    if not p.exists():
        pytest.skip(f"program {p} not built")
    return str(p)


def run_cli(args: List[str], cwd: Path = ROOT) -> subprocess.CompletedProcess:
    r = subprocess.run(args, cwd=cwd, capture_output=True, text=True)
    assert r.returncode == 0, f"{' '.join(args)}\n{r.stdout}\n{r.stderr}"
    return r


@pytest.fixture(scope="session")
def full_decoder(tmp_path_factory: pytest.TempPathFactory) -> str:
    from safetensors.torch import load_file, save_file
    import torch

    w = load_file(fixture("ss_decoder_small.safetensors"))
    w["out_layer.2.weight"] = torch.zeros_like(w["out_layer.2.weight"])
    w["out_layer.2.bias"] = torch.full_like(w["out_layer.2.bias"], 2.0)
    path = tmp_path_factory.mktemp("models") / "ss_decoder_full.safetensors"
    save_file(w, str(path))
    return str(path)


@pytest.fixture(scope="session")
def model_files(full_decoder: str) -> Dict[str, Any]:
    return {
        "generator_config": fixture("ss_generator_small.json"),
        "generator_weights": fixture("ss_generator_small.safetensors"),
        "decoder_config": fixture("ss_decoder_small.json"),
        "decoder_weights": full_decoder,
        "embedder_config": str(ROOT / "configs" / "demo_embedder_small.json"),
    }


def model_flags(files: Dict[str, Any]) -> List[str]:
    """The same models as command-line flags (random embedder weights, CPU, STEPS steps)."""
    out = ["--device", "cpu", "--steps", str(STEPS), "--random-weights"]
    for key, value in files.items():
        out += ["--" + key.replace("_", "-"), value]
    return out


@pytest.fixture(scope="session")
def stage1(model_files: Dict[str, Any]) -> ss.Stage1:
    return ss.Stage1(**model_files, random_weights=True, device="cpu", steps=STEPS)


class Photo:
    """A wall at 2 m, a box at 1.2 m and an object cut by the left border (lift_test.cpp's photo), as
    arrays (a segmenter's label map and masks, MoGe's point map with +inf holes) and as files."""

    def __init__(self, folder: Path) -> None:
        r, c = np.mgrid[0:H, 0:W]
        self.rgb = np.stack([np.full((H, W), 120), 40 + c, 60 + r], axis=-1).astype(np.uint8)
        depth = np.full((H, W), 2.0, np.float32)
        self.labels = np.zeros((H, W), np.uint8)
        box = (c >= 60) & (c < 100) & (r >= 40) & (r < 80)
        cut = (c < 30) & (r >= 60) & (r < 110)
        self.labels[box], self.labels[cut] = 1, 2
        depth[box], depth[cut] = 1.2, 1.5
        self.rgb[box] = np.stack([np.full(box.sum(), 30), np.full(box.sum(), 200), 2 * c[box]], -1).astype(np.uint8)
        self.K = np.array([[F, 0, CX], [0, F, CY], [0, 0, 1]])
        x = (c - CX) / F * depth
        y = (r - CY) / F * depth
        self.pointmap = np.stack([x, y, depth], axis=-1).astype(np.float32)
        self.pointmap[10:30, 120:150] = np.inf
        self.depth = depth
        folder.mkdir(parents=True, exist_ok=True)
        self.rgb_path = str(folder / "rgb.png")
        self.labels_path = str(folder / "labels.png")
        self.pointmap_path = str(folder / "points.npy")
        ss.write_image(self.rgb_path, self.rgb)
        ss.write_image(self.labels_path, self.labels)
        np.save(self.pointmap_path, self.pointmap)


@pytest.fixture(scope="session")
def photo(tmp_path_factory: pytest.TempPathFactory) -> Photo:
    return Photo(tmp_path_factory.mktemp("photo"))
