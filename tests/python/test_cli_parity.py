"""The same inputs through Python and through the command-line programs give identical outputs, bit for
bit: the lift's files (meshes, occupancy, poses, scene.json) and arrays, the probe's report, scene.json
and MJCF, with and without in-process resampling. Timings (report "seconds") are the only keys left out.
"""

from __future__ import annotations

import filecmp
import json
import os
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import pytest

import simuscene as ss
from conftest import ROOT, Photo, model_flags, program, run_cli


def without_timings(x: Any) -> Any:
    """A report with its wall-clock keys removed (they differ between any two runs)."""
    if isinstance(x, dict):
        return {k: without_timings(v) for k, v in x.items() if k not in ("seconds", "seconds_total")}
    if isinstance(x, list):
        return [without_timings(v) for v in x]
    return x


def tree(folder: Path) -> List[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_lift_matches_the_lift_program(stage1: ss.Stage1, model_files: Dict[str, Any], photo: Photo,
                                       tmp_path: Path) -> None:
    cli_out, py_out = tmp_path / "cli", tmp_path / "py"
    run_cli([program("lift"), "--image", photo.rgb_path, "--masks", photo.labels_path, "--pointmap",
             photo.pointmap_path, "--seed", "3", "--out", str(cli_out)] + model_flags(model_files))
    res = stage1.lift(photo.rgb, photo.labels, pointmap=photo.pointmap, seed=3)
    assert [o.id for o in res] == ["label_1", "label_2"] and res.failed == 0
    res.write(py_out, image_path=photo.rgb_path, depth_path=photo.pointmap_path)
    # Every file the program wrote, written the same from Python.
    assert tree(cli_out) == tree(py_out)
    for name in tree(cli_out):
        if name == "report.json":
            a = json.loads((cli_out / name).read_text())
            b = json.loads((py_out / name).read_text())
            assert without_timings(a) == without_timings(b)
        else:
            assert filecmp.cmp(cli_out / name, py_out / name, shallow=False), name
    # The arrays Python holds are the numbers in the program's files, exactly.
    for obj in res:
        sdir = cli_out / "objects" / obj.id / "sample_0"
        shape = obj.samples[0]
        occ = np.load(sdir / "occupancy.npy")
        assert occ.dtype == np.uint8 and np.array_equal(occ, shape.occupancy.numpy())
        pose = json.loads((sdir / "pose.json").read_text())
        assert np.array_equal(np.array(pose["sam3d"]["rotation_wxyz"]), shape.sam3d_pose["rotation_wxyz"])
        assert np.array_equal(np.array(pose["sam3d"]["translation"]), shape.sam3d_pose["translation"])
        assert np.array_equal(np.array(pose["sam3d"]["scale"]), shape.sam3d_pose["scale"])
        assert shape.pose is not None
        assert np.array_equal(np.array(pose["scene"]["R"]), shape.pose["R"])
        assert np.array_equal(np.array(pose["scene"]["t"]), shape.pose["t"])
        assert np.array_equal(np.array(pose["scene"]["scale"]), shape.pose["scale"])
        # The GLB stores float32 vertices: the float64 arrays rounded to float32 are those numbers.
        v, f = ss.read_mesh(sdir / "mesh.glb")
        assert np.array_equal(v, shape.vertices.astype(np.float32).astype(np.float64))
        assert np.array_equal(f, shape.faces)


SCENE = ROOT / "tests" / "testdata" / "scenes" / "synth_0000" / "scene.json"
# Shorter settles than configs/probe.yaml's (the same code paths; seconds instead of tens of seconds).
FAST = {"final.settle_time": 0.5, "evaluation.settle_time": 0.5, "final.candidate_settle_time": 0.3,
        "collision.use_coacd": False}


def sets(overrides: Dict[str, Any]) -> List[str]:
    out = []
    for k, v in overrides.items():
        out += ["--set", f"{k}={'true' if v is True else 'false' if v is False else v}"]
    return out


def compare_probe_outputs(cli_out: Path, res: ss.ProbeResult) -> None:
    assert res.out_dir is not None
    py_out = Path(res.out_dir)
    assert tree(cli_out) == tree(py_out)
    a = json.loads((cli_out / "report.json").read_text())
    b = json.loads((py_out / "report.json").read_text())
    assert without_timings(a) == without_timings(b)
    assert without_timings(a) == without_timings(res.report)
    assert (cli_out / "scene.xml").read_text() == (py_out / "scene.xml").read_text() == res.mjcf
    # scene.json and the meshes: the same bytes except the output folder's own path inside scene.json.
    sa = json.loads((cli_out / "scene.json").read_text())
    sb = json.loads((py_out / "scene.json").read_text())
    assert json.dumps(sa).replace(str(cli_out), "OUT") == json.dumps(sb).replace(str(py_out), "OUT")
    for name in tree(cli_out):
        if name.endswith((".obj", ".png")):
            assert filecmp.cmp(cli_out / name, py_out / name, shallow=False), name


def test_probe_matches_the_probe_program(tmp_path: Path) -> None:
    cli_out = tmp_path / "cli"
    run_cli([program("probe"), "--config", str(ROOT / "configs" / "probe.yaml"), "--scene", str(SCENE), "--out",
             str(cli_out), "--cache-dir", str(tmp_path / "hulls")] + sets(FAST))
    res = ss.probe(ss.Scene.load(SCENE), config=ROOT / "configs" / "probe.yaml",
                   overrides={**FAST, "collision.cache_dir": str(tmp_path / "hulls")}, out=tmp_path / "py")
    compare_probe_outputs(cli_out, res)
    assert [d.id for d in res.decisions] == [o.id for o in ss.Scene.load(SCENE).objects]
    assert {"before_after", "side_view", "overlay"} <= set(res.pictures)
    assert all(p.dtype == np.uint8 and p.ndim == 3 and p.shape[2] == 3 for p in res.pictures.values())


def test_probe_with_resampling_matches_the_program(stage1: ss.Stage1, model_files: Dict[str, Any],
                                                   tmp_path: Path) -> None:
    cli_out = tmp_path / "cli"
    flags = model_flags(model_files)  # --steps STEPS, as the stage1 fixture
    run_cli([program("probe"), "--config", str(ROOT / "configs" / "probe.yaml"), "--scene", str(SCENE), "--out",
             str(cli_out), "--cache-dir", str(tmp_path / "hulls"), "--resample", "--seed", "1", "--num-samples", "1"]
            + flags + sets(FAST))
    res = ss.probe(ss.Scene.load(SCENE), config=ROOT / "configs" / "probe.yaml",
                   overrides={**FAST, "collision.cache_dir": str(tmp_path / "hulls")}, out=tmp_path / "py",
                   resampler=stage1, seed=1)
    compare_probe_outputs(cli_out, res)
    assert any(d.branch == "resample" for d in res.decisions), "the scene exercises resampling"
