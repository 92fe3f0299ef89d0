#!/usr/bin/env python3
"""Adds an FM-DPO resampling adapter to a shipped model folder (docs/results.md, issue 36 section 5).

  ship_adapter.py --model weights/miniature_cpu --adapter runs/gpu_fmdpo/runs/beta5_s0/adapter \
      --commands "..." --selection "..." [--evaluation NAME=SUMMARY.json ...] [--ci-args ... --ci-record SUMMARY]

Copies the PEFT folder (adapter_config.json, adapter_model.safetensors) to MODEL/adapter, and records in
MODEL/manifest.json: files.resample_adapter, the files' sha256 and the folder's bytes, and a
"resample_adapter" entry (source run, commands, the selection rule, the evaluations' deltas). With
--ci-args / --ci-record: "ci_check_adapter" (the eval_lift arguments CI reruns and the deltas it must
reach, tests/pipeline/resample/shipped_eval_test.sh). Writes the manifest atomically.
"""
import argparse
import datetime
import hashlib
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True, help="the model folder (its manifest.json is updated)")
    ap.add_argument("--adapter", required=True, help="the PEFT adapter folder to ship")
    ap.add_argument("--commands", required=True, help="the commands and seeds that made the adapter")
    ap.add_argument("--selection", required=True, help="how this adapter was chosen (on which split, by which rule)")
    ap.add_argument("--evaluation", action="append", default=[], metavar="NAME=SUMMARY",
                    help="an eval_lift --compare-adapter summary.json to record (its deltas)")
    ap.add_argument("--ci-args", default=None, help="eval_lift arguments of the CI check, one string (no --out)")
    ap.add_argument("--ci-record", help="the summary.json of those arguments, run here: its deltas are recorded")
    ap.add_argument("--ci-tolerance", type=float, default=0.02, help="allowed drop of each recorded delta")
    ap.add_argument("--ci-tolerance-source", default="", help="where the tolerance comes from")
    a = ap.parse_args()

    manifest_path = os.path.join(a.model, "manifest.json")
    m = json.load(open(manifest_path))
    for f in ("adapter_config.json", "adapter_model.safetensors"):
        if not os.path.isfile(os.path.join(a.adapter, f)):
            sys.exit(f"ship_adapter: {a.adapter}: {f} missing (not a PEFT adapter folder)")
    dst = os.path.join(a.model, "adapter")
    shutil.rmtree(dst, ignore_errors=True)
    os.makedirs(dst)
    for f in ("adapter_config.json", "adapter_model.safetensors"):
        shutil.copy2(os.path.join(a.adapter, f), os.path.join(dst, f))
        m["sha256"][f"adapter/{f}"] = sha256(os.path.join(dst, f))
    m["files"]["resample_adapter"] = "adapter"
    total = 0
    for root, _, files in os.walk(a.model):
        total += sum(os.path.getsize(os.path.join(root, f)) for f in files if f != "manifest.json")
    m["bytes"] = total

    evals = {}
    for item in a.evaluation:
        name, path = item.split("=", 1)
        s = json.load(open(path))
        evals[name] = {"summary": path, "settings": s["settings"], "deltas": s["deltas"]}
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    m["resample_adapter"] = {
        "folder": "adapter",
        "source": a.adapter,
        "use": "probe --resample, reconstruct and the demo resample with base + this adapter; the first lift runs the "
               "base model (--base-resampling: the base for both)",
        "commands": a.commands,
        "selection": a.selection,
        "commit": commit,
        "made": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "evaluation": evals,
    }
    if a.ci_args is not None:
        if not a.ci_record:
            sys.exit("ship_adapter: --ci-args needs --ci-record (the summary of those arguments)")
        d = json.load(open(a.ci_record))["deltas"]
        metrics = {}
        for depth, buckets in d.items():
            for bucket, keys in buckets.items():
                for key in ("iou_mean", "shape_iou_mean"):
                    if bucket != "all" or key not in keys or keys[key].get("delta") is None:
                        continue
                    metrics[f"{depth}/{bucket}/{key}"] = round(keys[key]["delta"], 4)
        m["ci_check_adapter"] = {"args": shlex.split(a.ci_args), "deltas": metrics,
                                 "tolerance": a.ci_tolerance, "tolerance_source": a.ci_tolerance_source}
    fd, tmp = tempfile.mkstemp(dir=a.model, suffix=".json")
    with os.fdopen(fd, "w") as f:
        json.dump(m, f, indent=1)
        f.write("\n")
    os.replace(tmp, manifest_path)
    print(f"ship_adapter: {a.adapter} -> {dst}; {manifest_path} updated ({total} bytes in the folder)")


if __name__ == "__main__":
    main()
