#!/usr/bin/env python3
"""Checks a `world pairs` folder, its `build_pairs --filter-gt --report` JSON and the pair cache
(tests/pipeline/resample/world_pairs_test.sh): invariants of the filter, no recorded values.

    world_pairs_check.py PAIRS_DIR REPORT_JSON CACHE_H5
"""
import json
import os
import sys

import h5py
import numpy as np

pairs_dir, report_path, cache = sys.argv[1:4]
fails = []
lines = [json.loads(l) for l in open(os.path.join(pairs_dir, "manifest.jsonl")) if l.strip()]
kinds = [l["kind"] for l in lines]
if kinds.count("occlusion_completion") != 3 or kinds.count("clean_preservation") != 3:
    fails.append(f"manifest kinds {kinds}: expected 3 of each")
summary = json.load(open(os.path.join(pairs_dir, "pairs.json")))
if summary["completion"] != 3 or summary["preservation"] != 3:
    fails.append(f"pairs.json counts {summary}")
for l in lines:
    keys = {"image", "mask", "pointmap", "gt_occupancy"} | (
        {"full_image", "full_mask", "full_pointmap"} if l["kind"] == "occlusion_completion" else {"corrupted_mask"})
    for k in keys:
        if not os.path.exists(os.path.join(pairs_dir, l[k])):
            fails.append(f"{l['id']}: {k} {l[k]} missing")
    occ = np.load(os.path.join(pairs_dir, l["gt_occupancy"]))
    if occ.dtype != np.uint8 or occ.shape != (summary["resolution"],) * 3 or not (0 < occ.sum() < occ.size):
        fails.append(f"{l['id']}: gt_occupancy {occ.dtype} {occ.shape} with {occ.sum()} set")
    pm = np.load(os.path.join(pairs_dir, l["pointmap"]))
    if pm.ndim != 3 or pm.shape[2] != 3:
        fails.append(f"{l['id']}: pointmap shape {pm.shape}")

report = json.load(open(report_path))
rows = report["filtered"]
if report["issues"]:
    fails.append(f"issues: {report['issues']}")
if sorted(r["id"] for r in rows) != sorted(l["id"] for l in lines):
    fails.append("the filter did not judge every pair")
for r in rows:
    if not (0 <= r["iou_pos"] <= 1 and 0 <= r["iou_neg"] <= 1):
        fails.append(f"{r['id']}: IoU out of [0, 1]: {r}")
    if r["kept"] != (r["iou_pos"] > r["iou_neg"]):
        fails.append(f"{r['id']}: kept {r['kept']} but IoU x+ {r['iou_pos']:.4f}, x- {r['iou_neg']:.4f}")
kept = sorted(r["id"] for r in rows if r["kept"])
ids = []
if os.path.exists(cache):  # no cache when the filter dropped every pair
    with h5py.File(cache, "r") as f:
        ids = sorted(x.decode() if isinstance(x, bytes) else x for x in f["id"][:])
if ids != kept:
    fails.append(f"cache ids {ids} != kept {kept}")
if report["cache_size"] != len(kept) or report["written"] != len(kept):
    fails.append(f"report cache_size {report['cache_size']} / written {report['written']} != {len(kept)} kept")
print(f"{len(lines)} pairs, {len(kept)} kept by the filter: " +
      ", ".join(f"{r['id'].split('/')[-2]} {r['kind'][:5]} x+ {r['iou_pos']:.3f} x- {r['iou_neg']:.3f}" for r in rows))
if fails:
    print("FAIL:\n  " + "\n  ".join(fails))
    sys.exit(1)
print("ok")
