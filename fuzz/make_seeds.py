#!/usr/bin/env python3
"""Writes the committed seed corpora of the fuzz targets (fuzz/corpus/<target>/): small valid files
made with the reference tools users have (safetensors, h5py, json) plus the project's own configs.
Run from the repository root with the project's venv: .deps/venv/bin/python fuzz/make_seeds.py"""
import json
import os
import shutil
import struct
import sys

import h5py
import numpy as np
from safetensors.numpy import save as st_save

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CORPUS = os.path.join(ROOT, "fuzz", "corpus")


def out(target, name, data):
    d = os.path.join(CORPUS, target)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


def safetensors_seeds():
    rng = np.random.default_rng(0)
    out("fuzz_safetensors", "two_f32.safetensors",
        st_save({"a": rng.standard_normal((2, 3)).astype(np.float32), "b": np.arange(4, dtype=np.int64)},
                metadata={"format": "pt"}))
    out("fuzz_safetensors", "mixed.safetensors",
        st_save({"h": np.ones((1, 2, 2), np.float16), "u": np.zeros((3,), np.uint8), "e": np.zeros((0, 4), np.float32),
                 "s": np.array(1.5, np.float64), "t": np.array([True, False])}))
    out("fuzz_safetensors", "empty.safetensors", st_save({}))


def adapter_tensors(r=2, cin=4, cout=6):
    rng = np.random.default_rng(1)
    t = {}
    for p in ["reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape", "reverse_fn.backbone.blocks.0.cross_attn.shape.to_kv"]:
        t[f"base_model.model.{p}.lora_A.weight"] = rng.standard_normal((r, cin)).astype(np.float32)
        t[f"base_model.model.{p}.lora_B.weight"] = np.zeros((cout, r), np.float32)
    return t


def peft_seeds():
    base = {"alpha_pattern": {}, "bias": "none", "fan_in_fan_out": False, "inference_mode": True, "init_lora_weights": True,
            "lora_alpha": 4, "lora_dropout": 0.0, "modules_to_save": None, "peft_type": "LORA", "r": 2, "rank_pattern": {},
            "use_dora": False, "use_rslora": False}
    regex = r".*blocks\.\d+\.(self_attn\.(to_qkv|to_out)\.shape|cross_attn\.shape\.(to_q|to_kv|to_out))$"
    weights = st_save(adapter_tensors(), metadata={"format": "pt"})
    for name, tm in [("regex", regex), ("list", ["self_attn.to_qkv.shape", "cross_attn.shape.to_kv"])]:
        cfg = json.dumps(dict(base, target_modules=tm), indent=2).encode()
        out("fuzz_peft", f"{name}.bin", struct.pack("<I", len(cfg)) + cfg + weights)
    # The PEFT fixture of the shared test data, when present.
    fx = os.path.join(os.environ.get("SIMU_SHARED_DIR", os.path.join(ROOT, "..", "shared")), "fixtures", "lora_small")
    if os.path.isdir(fx):
        cfg = open(os.path.join(fx, "adapter_config.json"), "rb").read()
        w = open(os.path.join(fx, "adapter_model.safetensors"), "rb").read()
        if len(w) < 64 * 1024:
            out("fuzz_peft", "fixture_lora_small.bin", struct.pack("<I", len(cfg)) + cfg + w)
        else:
            out("fuzz_peft", "fixture_lora_small_config.bin", struct.pack("<I", len(cfg)) + cfg)


def config_seeds():
    for name in ["tiny.yaml", "lora64.yaml", "stage1_small.yaml", "demo_scene.yaml"]:
        p = os.path.join(ROOT, "configs", name)
        if os.path.exists(p):
            out("fuzz_config", name, open(p, "rb").read())
    tiny = open(os.path.join(ROOT, "configs", "tiny.yaml"), "rb").read()
    out("fuzz_config", "tiny_with_sets.yaml", tiny + b"\n#--set\noptim.lr=2e-5\nlora.target_modules=[to_q, to_kv]\ndata.cache=x.h5\n")
    out("fuzz_config", "anchors.yaml", b"base: &b {r: 4, alpha: 8}\nlora: *b\nlist: [1, 2.5, -3e4, .inf]\n")


def pair_cache_file(path, n=2, T=4, C=2, L=3, Cc=2, dtype=np.float16, vlen_attrs=True):
    rng = np.random.default_rng(2)
    with h5py.File(path, "w", libver="earliest") as f:
        if vlen_attrs:
            f.attrs["format"] = "simu.pair_cache"
            f.attrs["cond_mode"] = "tokens"
            f.attrs["created_by"] = "fuzz/make_seeds.py"
        else:
            f.attrs["format"] = np.bytes_(b"simu.pair_cache")
            f.attrs["cond_mode"] = np.bytes_(b"tokens")
            f.attrs["created_by"] = np.bytes_(b"fuzz/make_seeds.py")
        f.attrs["schema_version"] = np.int64(1)
        f.attrs["latent_shape"] = np.array([T, C], np.int64)
        f.attrs["cond_shape"] = np.array([L, Cc], np.int64)
        kw = dict(compression="gzip", compression_opts=4, shuffle=True)
        f.create_dataset("latent_pos", data=rng.standard_normal((n, T, C)).astype(dtype), chunks=(1, T, C), maxshape=(None, T, C), **kw)
        f.create_dataset("latent_neg", data=rng.standard_normal((n, T, C)).astype(dtype), chunks=(1, T, C), maxshape=(None, T, C), **kw)
        f.create_dataset("cond", data=rng.standard_normal((n, L, Cc)).astype(dtype), chunks=(1, L, Cc), maxshape=(None, L, Cc), **kw)
        f.create_dataset("cond_len", data=np.array([L, 1] * (n // 2) + [L] * (n % 2), np.int32), chunks=(1024,), maxshape=(None,), **kw)
        f.create_dataset("kind", data=np.array([0, 1] * (n // 2) + [0] * (n % 2), np.uint8), chunks=(1024,), maxshape=(None,), **kw)
        f.create_dataset("weight", data=np.array([1.0, 0.1] * (n // 2) + [1.0] * (n % 2), np.float32), chunks=(1024,), maxshape=(None,), **kw)
        f.create_dataset("id", data=[f"pair-{i}" for i in range(n)], dtype=h5py.string_dtype("utf-8"), chunks=(1024,), maxshape=(None,))


def pair_cache_seeds():
    tmp = os.path.join(CORPUS, "..", "tmp_seed.h5")
    for name, kw in [("f16_vlen.h5", {}), ("f32_fixed_attrs.h5", dict(dtype=np.float32, vlen_attrs=False, n=3))]:
        pair_cache_file(tmp, **kw)
        out("fuzz_pair_cache", name, open(tmp, "rb").read())
    os.remove(tmp)


def scene_seeds():
    d = os.path.join(ROOT, "tests", "data", "scenes")
    for n in sorted(os.listdir(d)) if os.path.isdir(d) else []:
        p = os.path.join(d, n, "scene.json")
        if os.path.exists(p):
            # compact JSON: the same content in fewer bytes for the mutator
            out("fuzz_scene", f"{n}.json", b"\x00" + json.dumps(json.load(open(p))).encode())
        m = os.path.join(d, n, "meshes")
        for mesh in sorted(os.listdir(m))[:1] if n.endswith("0000") and os.path.isdir(m) else []:
            if mesh.endswith(".obj") and os.path.getsize(os.path.join(m, mesh)) < 32 * 1024:
                out("fuzz_scene", f"{n}_{mesh}", b"\x80" + open(os.path.join(m, mesh), "rb").read())
    cube_v = [(x, y, z) for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)]
    faces = [(1, 3, 2), (2, 3, 4), (5, 6, 7), (6, 8, 7), (1, 2, 5), (2, 6, 5), (3, 7, 4), (4, 7, 8), (1, 5, 3), (3, 5, 7),
             (2, 4, 6), (4, 8, 6)]
    obj = "".join(f"v {x} {y} {z}\n" for x, y, z in cube_v) + "".join(f"f {a} {b} {c}\n" for a, b, c in faces)
    out("fuzz_scene", "cube.obj", b"\x80" + obj.encode())
    ply = ("ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\nproperty float z\n"
           "element face 12\nproperty list uchar int vertex_indices\nend_header\n" +
           "".join(f"{x} {y} {z}\n" for x, y, z in cube_v) + "".join(f"3 {a-1} {b-1} {c-1}\n" for a, b, c in faces))
    out("fuzz_scene", "cube.ply", b"\xc0" + ply.encode())


if __name__ == "__main__":
    for t in ["fuzz_safetensors", "fuzz_peft", "fuzz_config", "fuzz_pair_cache", "fuzz_scene"]:
        shutil.rmtree(os.path.join(CORPUS, t), ignore_errors=True)
    safetensors_seeds()
    peft_seeds()
    config_seeds()
    pair_cache_seeds()
    scene_seeds()
    for t in sorted(os.listdir(CORPUS)):
        print(t, len(os.listdir(os.path.join(CORPUS, t))), "seeds")
