"""reconstruct and build_pairs from Python with one loaded Stage1: the programs' outputs on disk, the
returned report, bad records listed (not raised), and a re-run resuming the cache."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import simuscene as ss
from conftest import Photo


def test_reconstruct_with_loaded_models(stage1: ss.Stage1, photo: Photo, tmp_path: Path) -> None:
    res = ss.reconstruct(photo.rgb, photo.labels, pointmap=photo.pointmap, K=photo.K, stage1=stage1,
                         out=tmp_path / "rec", run_probe=False)
    assert (tmp_path / "rec" / "input" / "scene.json").exists()
    assert (tmp_path / "rec" / "reconstruct_report.json").exists()
    ids = [o["id"] for o in res["objects"]]
    assert ids == ["label_1", "label_2"]
    assert {o.id for o in res["scene"].objects} <= set(ids) and len(res["scene"].objects) > 0
    assert res["probe_report"] is None
    # The first lift drew 4 shapes per lifted object and kept the one the depth and mask agree with most.
    several = [o for o in res["objects"] if any(st.startswith("lifted (") and "usable samples of 4)" in st
                                                for st in o["steps"])]
    assert several, [o["steps"] for o in res["objects"]]
    assert all(any(st.startswith("kept sample ") for st in o["steps"]) for o in several), [o["steps"] for o in several]


def test_reconstruct_refuses_negative_lift_samples(stage1: ss.Stage1, photo: Photo, tmp_path: Path) -> None:
    with pytest.raises(ss.InputError, match="lift_samples"):
        ss.reconstruct(photo.rgb, photo.labels, pointmap=photo.pointmap, K=photo.K, stage1=stage1,
                       out=tmp_path / "rec", run_probe=False, lift_samples=-1)


def test_build_pairs_with_loaded_models(stage1: ss.Stage1, photo: Photo, tmp_path: Path) -> None:
    d = tmp_path / "pairs"
    d.mkdir()
    box = (photo.labels == 1).astype(np.uint8) * 255
    part = box.copy()
    part[60:, :] = 0  # the occluded (modal) mask: the box's upper half
    ss.write_image(d / "img.png", photo.rgb)
    ss.write_image(d / "full.png", box)
    ss.write_image(d / "modal.png", part)
    lines = [{"id": "occ", "kind": "occlusion_completion", "image": "img.png", "mask": "modal.png",
              "full_image": "img.png", "full_mask": "full.png"},
             {"id": "clean", "kind": "clean_preservation", "image": "img.png", "mask": "full.png",
              "corrupted_mask": "modal.png"},
             {"id": "bad", "kind": "clean_preservation", "image": "missing.png", "mask": "full.png",
              "corrupted_mask": "modal.png"}]
    (d / "manifest.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    rep = ss.build_pairs(d / "manifest.jsonl", d / "pairs.h5", stage1=stage1, batch=2)
    assert rep["written"] == 2 and rep["cache_size"] == 2
    assert [i["id"] for i in rep["issues"]] == ["bad"] and "missing.png" in rep["issues"][0]["message"]
    r = ss.PairCacheReader(d / "pairs.h5")
    assert sorted(r.ids()) == ["clean", "occ"] and r.info["cond_mode"] == "tokens"
    again = ss.build_pairs(d / "manifest.jsonl", d / "pairs.h5", stage1=stage1, batch=2)
    assert again["written"] == 0 and again["skipped_existing"] == 2
