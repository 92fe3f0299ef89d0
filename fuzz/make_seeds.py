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


def manifest_seeds():
    occ = {"id": "occ-0", "kind": "occlusion_completion", "image": "img/0.png", "mask": "mask/0.png",
           "full_image": "img/0_full.png", "full_mask": "mask/0_full.png", "pointmap": "pm/0.safetensors",
           "weight": 1.0}
    clean = {"id": "clean-0", "kind": "clean_preservation", "image": "/abs/img/1.png", "mask": "mask/1.png",
             "corrupted_mask": "mask/1_bad.png", "weight": 0.1}
    lines = ["# build_pairs manifest", json.dumps(occ), "", json.dumps(clean),
             json.dumps(dict(occ, id="occ-1", full_pointmap="pm/1.safetensors")), json.dumps(dict(clean, id="occ-0"))]
    out("fuzz_manifest", "pairs.jsonl", "\n".join(lines).encode() + b"\r\n")
    out("fuzz_manifest", "one_line.jsonl", json.dumps(occ).encode())


def npy_bytes(a, fortran=False):
    """A .npy file (format 1.0) as numpy.save writes it, without numpy's writer: descr, order, shape."""
    descr = a.dtype.str
    shape = repr(tuple(int(d) for d in a.shape))  # (), (5,), (5, 6)
    h = "{'descr': '%s', 'fortran_order': %s, 'shape': %s, }" % (descr, "True" if fortran else "False", shape)
    h += " " * ((64 - (10 + len(h) + 1) % 64) % 64) + "\n"
    data = np.asfortranarray(a).tobytes(order="F") if fortran else a.tobytes()
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(h)) + h.encode() + data


def exr_bytes(depth):
    """A single-channel ('Y', float32) uncompressed scanline OpenEXR file."""
    h, w = depth.shape
    def attr(name, typ, value):
        return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(value)) + value
    chlist = b"Y\0" + struct.pack("<iB3xii", 2, 0, 1, 1) + b"\0"
    box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    head = (b"\x76\x2f\x31\x01" + struct.pack("<i", 2) + attr("channels", "chlist", chlist) +
            attr("compression", "compression", b"\0") + attr("dataWindow", "box2i", box) +
            attr("displayWindow", "box2i", box) + attr("lineOrder", "lineOrder", b"\0") +
            attr("pixelAspectRatio", "float", struct.pack("<f", 1.0)) +
            attr("screenWindowCenter", "v2f", struct.pack("<ff", 0, 0)) +
            attr("screenWindowWidth", "float", struct.pack("<f", 1.0)) + b"\0")
    first = len(head) + 8 * h
    blocks, offsets = b"", []
    for y in range(h):
        offsets.append(first + len(blocks))
        row = depth[y].astype("<f4").tobytes()
        blocks += struct.pack("<ii", y, len(row)) + row
    return head + b"".join(struct.pack("<Q", o) for o in offsets) + blocks


def depth_seeds():
    import io
    from PIL import Image
    H, W = 5, 6
    z = (1.0 + 0.1 * np.arange(H * W, dtype=np.float32).reshape(H, W))
    z[0, 0] = 0  # invalid
    out("fuzz_depth", "depth_f4.npy", b"\x00" + npy_bytes(z))
    out("fuzz_depth", "depth_u2_mm.npy", b"\x00" + npy_bytes((z * 1000).astype("<u2")))
    out("fuzz_depth", "depth_f8_fortran_be.npy", b"\x00" + npy_bytes(z.astype(">f8"), fortran=True))
    # MoGe-style point map [H, W, 3] of a pinhole camera (fx = fy = 50, cx = 3, cy = 2), one invalid point.
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    pm = np.stack([(u - 3) / 50 * z, (v - 2) / 50 * z, z], -1).astype(np.float32)
    pm[1, 1] = np.inf
    out("fuzz_depth", "pointmap_f4.npy", b"\x00" + npy_bytes(pm))
    buf = io.BytesIO()
    Image.fromarray((z * 1000).astype(np.uint16)).save(buf, format="PNG")  # 16-bit grey, millimetres
    out("fuzz_depth", "depth_mm16.png", b"\x40" + buf.getvalue())
    buf = io.BytesIO()
    Image.fromarray(np.arange(H * W, dtype=np.uint8).reshape(H, W) % 3).save(buf, format="PNG")  # labels / 8-bit
    out("fuzz_depth", "labels_u8.png", b"\x40" + buf.getvalue())
    out("fuzz_depth", "depth_f32.exr", b"\x80" + exr_bytes(z))
    out("fuzz_depth", "K_keys.json", b"\xc0" + json.dumps({"fx": 500, "fy": 500, "cx": 320, "cy": 240, "width": 640}).encode())
    out("fuzz_depth", "K_matrix.json", b"\xc0" + json.dumps({"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]]}).encode())
    out("fuzz_depth", "K_flat.json", b"\xc0" + json.dumps([500, 0, 320, 0, 500, 240, 0, 0, 1]).encode())


if __name__ == "__main__":
    for t in ["fuzz_safetensors", "fuzz_peft", "fuzz_config", "fuzz_pair_cache", "fuzz_scene", "fuzz_manifest",
              "fuzz_depth"]:
        shutil.rmtree(os.path.join(CORPUS, t), ignore_errors=True)
    safetensors_seeds()
    peft_seeds()
    config_seeds()
    pair_cache_seeds()
    scene_seeds()
    manifest_seeds()
    depth_seeds()
    for t in sorted(os.listdir(CORPUS)):
        print(t, len(os.listdir(os.path.join(CORPUS, t))), "seeds")
