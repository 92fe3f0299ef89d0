#!/usr/bin/env python3
"""Test data maker: checkpoints in the layout of the released SAM 3D Objects Stage-1 files, at the
released dimensions, written with PyTorch's own torch.save as the release is:

  ss_generator.ckpt  a Lightning-style dict {"state_dict": {...}, "epoch", "global_step", ...} whose
                     state_dict holds every `_base_models.generator.*` key (ShortCut -> CFG ->
                     mot SparseStructureFlowTdfyWrapper: 1024 channels, 24 blocks, 16 heads, 16^3 shape
                     tokens of 8 channels, 4 pose latents sharing one transformer, 1024-channel condition)
                     and every `_base_models.condition_embedder.*` key (EmbedderFuser: two
                     dinov2_vitl14_reg at 518 px, PointPatchEmbed 256 px / patch 8 / 512 dims, SwiGLU
                     projections to 1024, learned idx_emb);
  ss_decoder.ckpt    a plain state dict of the sparse-structure decoder (channels 512/128/32, 2 res
                     blocks per level and in the middle, 8 latent channels, 1 output channel).

Names follow the official module trees (sam3d_objects/model/backbone/tdfy_dit/models/
mot_sparse_structure_flow.py, dit/embedder/{embedder_fuser,dino,pointmap}.py, dinov2's
vision_transformer.py, sparse_structure_vae.py): the shapes are written out here from those
definitions (not read from the C++ port). Small fixtures made by the official code
(../shared/fixtures/*_small.safetensors) carry the same names at small sizes; --check-against
compares the name sets after mapping sizes (every small key must exist here and vice versa, up to
the block count).

Storage: every tensor is a zero scalar expanded to its shape (stride 0), so the .ckpt files are a few
MB although the shapes and dtypes are the released ones; scripts/convert_checkpoint.py writes such
all-zero tensors as holes of a sparse safetensors file.

Usage: make_official_checkpoint.py OUT_DIR [--dtype float32|bfloat16|float16]
Prints one JSON line: tensor and element counts per component.
"""
import argparse
import json
import os
import sys

import torch

# Released dimensions (ss_generator.yaml / ss_decoder.yaml of the release).
GEN = dict(model_channels=1024, cond_channels=1024, num_blocks=24, num_heads=16, mlp_ratio=4, resolution=16,
           in_channels=8, freq_dim=256)
POSE_LATENTS = {"6drotation_normalized": 6, "scale": 3, "translation": 3, "translation_scale": 1}
VITL = dict(dim=1024, depth=24, heads=16, mlp_ratio=4, patch=14, registers=4, img=518)
POINT = dict(dim=512, input_size=256, patch=8, mlp_ratio=2.0)
FUSER_OUT = 1024
DEC = dict(channels=[512, 128, 32], num_res_blocks=2, num_res_blocks_middle=2, latent_channels=8, out_channels=1)


def swiglu_hidden(multiplier, out_dim, multiple_of=256):
    # llama3 FeedForward: int(2 * hidden / 3) rounded up to a multiple of 256.
    h = int(2 * int(multiplier * out_dim) / 3)
    return multiple_of * ((h + multiple_of - 1) // multiple_of)


def generator_shapes():
    C, Cc = GEN["model_channels"], GEN["cond_channels"]
    heads = GEN["num_heads"]
    hidden = int(C * GEN["mlp_ratio"])
    s = {}
    p = "_base_models.generator.reverse_fn.backbone."
    for emb in ("t_embedder", "d_embedder"):  # TimestepEmbedder: Linear(256, C), SiLU, Linear(C, C)
        s[p + f"{emb}.mlp.0.weight"] = [C, GEN["freq_dim"]]
        s[p + f"{emb}.mlp.0.bias"] = [C]
        s[p + f"{emb}.mlp.2.weight"] = [C, C]
        s[p + f"{emb}.mlp.2.bias"] = [C]
    tokens = {"shape": GEN["resolution"] ** 3}
    latents = {"shape": GEN["in_channels"], **POSE_LATENTS}
    for name, ch in latents.items():  # mm_latent.Latent: input_layer, out_layer, pos_emb
        q = p + f"latent_mapping.{name}."
        s[q + "input_layer.weight"] = [C, ch]
        s[q + "input_layer.bias"] = [C]
        s[q + "out_layer.weight"] = [ch, C]
        s[q + "out_layer.bias"] = [ch]
        s[q + "pos_emb"] = [tokens.get(name, 1), C]
    streams = ["shape", "6drotation_normalized"]  # the pose latents share the 6drotation transformer
    for b in range(GEN["num_blocks"]):
        q = p + f"blocks.{b}."
        s[q + "adaLN_modulation.1.weight"] = [6 * C, C]
        s[q + "adaLN_modulation.1.bias"] = [6 * C]
        for st in streams:
            s[q + f"self_attn.to_qkv.{st}.weight"] = [3 * C, C]
            s[q + f"self_attn.to_qkv.{st}.bias"] = [3 * C]
            s[q + f"self_attn.to_out.{st}.weight"] = [C, C]
            s[q + f"self_attn.to_out.{st}.bias"] = [C]
            s[q + f"self_attn.q_rms_norm.{st}.gamma"] = [heads, C // heads]
            s[q + f"self_attn.k_rms_norm.{st}.gamma"] = [heads, C // heads]
            s[q + f"norm2.{st}.weight"] = [C]
            s[q + f"norm2.{st}.bias"] = [C]
            s[q + f"cross_attn.{st}.to_q.weight"] = [C, C]
            s[q + f"cross_attn.{st}.to_q.bias"] = [C]
            s[q + f"cross_attn.{st}.to_kv.weight"] = [2 * C, Cc]
            s[q + f"cross_attn.{st}.to_kv.bias"] = [2 * C]
            s[q + f"cross_attn.{st}.to_out.weight"] = [C, C]
            s[q + f"cross_attn.{st}.to_out.bias"] = [C]
            s[q + f"mlp.{st}.mlp.0.weight"] = [hidden, C]
            s[q + f"mlp.{st}.mlp.0.bias"] = [hidden]
            s[q + f"mlp.{st}.mlp.2.weight"] = [C, hidden]
            s[q + f"mlp.{st}.mlp.2.bias"] = [C]
    return s


def dino_shapes(prefix):
    D, P = VITL["dim"], VITL["patch"]
    n = (VITL["img"] // P) ** 2
    hidden = D * VITL["mlp_ratio"]
    s = {
        prefix + "cls_token": [1, 1, D],
        prefix + "pos_embed": [1, n + 1, D],
        prefix + "register_tokens": [1, VITL["registers"], D],
        prefix + "mask_token": [1, D],
        prefix + "patch_embed.proj.weight": [D, 3, P, P],
        prefix + "patch_embed.proj.bias": [D],
        prefix + "norm.weight": [D],
        prefix + "norm.bias": [D],
    }
    for b in range(VITL["depth"]):
        q = prefix + f"blocks.{b}."
        s.update({
            q + "norm1.weight": [D], q + "norm1.bias": [D],
            q + "attn.qkv.weight": [3 * D, D], q + "attn.qkv.bias": [3 * D],
            q + "attn.proj.weight": [D, D], q + "attn.proj.bias": [D],
            q + "ls1.gamma": [D],
            q + "norm2.weight": [D], q + "norm2.bias": [D],
            q + "mlp.fc1.weight": [hidden, D], q + "mlp.fc1.bias": [hidden],
            q + "mlp.fc2.weight": [D, hidden], q + "mlp.fc2.bias": [D],
            q + "ls2.gamma": [D],
        })
    return s


def embedder_shapes():
    p = "_base_models.condition_embedder."
    s = {}
    s.update(dino_shapes(p + "module_list.0.backbone."))
    s.update(dino_shapes(p + "module_list.1.backbone."))
    D, ps = POINT["dim"], POINT["patch"]
    n = POINT["input_size"] // ps
    h = int(D * POINT["mlp_ratio"])
    q = p + "module_list.2."
    s.update({
        q + "point_proj.weight": [D, 3], q + "point_proj.bias": [D],
        q + "invalid_xyz_token": [D],
        q + "pos_embed": [1, D, n, n],
        q + "pos_embed_window": [1, 1 + ps * ps, D],
        q + "cls_token": [1, 1, D],
        q + "blocks.0.norm1.weight": [D], q + "blocks.0.norm1.bias": [D],
        q + "blocks.0.attn.qkv.weight": [3 * D, D], q + "blocks.0.attn.qkv.bias": [3 * D],
        q + "blocks.0.attn.proj.weight": [D, D], q + "blocks.0.attn.proj.bias": [D],
        q + "blocks.0.norm2.weight": [D], q + "blocks.0.norm2.bias": [D],
        q + "blocks.0.mlp.fc1.weight": [h, D], q + "blocks.0.mlp.fc1.bias": [h],
        q + "blocks.0.mlp.fc2.weight": [D, h], q + "blocks.0.mlp.fc2.bias": [D],
    })
    hid = swiglu_hidden(4.0, FUSER_OUT)
    for i, din in enumerate([VITL["dim"], VITL["dim"], POINT["dim"]]):
        q = p + f"projection_nets.{i}."
        s.update({
            q + "0.weight": [din], q + "0.bias": [din],  # pre-norm LayerNorm(input dim)
            q + "1.w1.weight": [hid, din], q + "1.w3.weight": [hid, din], q + "1.w2.weight": [FUSER_OUT, hid],
        })
    s[p + "idx_emb"] = [3, FUSER_OUT]  # groups cropped, full, + 1
    return s


def decoder_shapes():
    ch = DEC["channels"]
    s = {"input_layer.weight": [ch[0], DEC["latent_channels"], 3, 3, 3], "input_layer.bias": [ch[0]]}

    def res(q, c):
        s.update({q + "norm1.weight": [c], q + "norm1.bias": [c], q + "conv1.weight": [c, c, 3, 3, 3],
                  q + "conv1.bias": [c], q + "norm2.weight": [c], q + "norm2.bias": [c],
                  q + "conv2.weight": [c, c, 3, 3, 3], q + "conv2.bias": [c]})

    for i in range(DEC["num_res_blocks_middle"]):
        res(f"middle_block.{i}.", ch[0])
    k = 0
    for level, c in enumerate(ch):
        for _ in range(DEC["num_res_blocks"]):
            res(f"blocks.{k}.", c)
            k += 1
        if level + 1 < len(ch):  # 3-D pixel-shuffle upsampling: conv to next * 8 channels
            s[f"blocks.{k}.conv.weight"] = [ch[level + 1] * 8, c, 3, 3, 3]
            s[f"blocks.{k}.conv.bias"] = [ch[level + 1] * 8]
            k += 1
    s.update({"out_layer.0.weight": [ch[-1]], "out_layer.0.bias": [ch[-1]],
              "out_layer.2.weight": [DEC["out_channels"], ch[-1], 3, 3, 3], "out_layer.2.bias": [DEC["out_channels"]]})
    return s


def check_names(fixtures):
    """The names written here, restricted to blocks 0 and 1, must equal the names of the small models the
    official code wrote (2 flow blocks, 2 ViT blocks): same modules, same nesting, nothing extra."""
    import re
    import struct

    def names(path, prefix=""):
        # The safetensors header (8-byte little-endian length, then JSON): no extra package needed.
        with open(path, "rb") as f:
            (n,) = struct.unpack("<Q", f.read(8))
            header = json.loads(f.read(n))
        return {prefix + k for k in header if k != "__metadata__" and not k.startswith("io.")}

    def first_two_blocks(keys):
        return {k for k in keys if all(int(i) < 2 for i in re.findall(r"blocks\.(\d+)\.", k))}

    bad = []
    for ours, small, what in [
        (generator_shapes(), names(os.path.join(fixtures, "ss_generator_small.safetensors")), "generator"),
        (embedder_shapes(), names(os.path.join(fixtures, "cond_embedder_small.safetensors"),
                                  "_base_models.condition_embedder."), "condition embedder"),
    ]:
        mine = first_two_blocks(set(ours))
        if mine != small:
            bad.append(f"{what}: only here {sorted(mine - small)[:8]}, only in the fixture {sorted(small - mine)[:8]}")
    if bad:
        sys.exit("error: names differ from the official small fixtures: " + "; ".join(bad))
    print("names match the official small fixtures (blocks 0-1)", file=sys.stderr)


def zeros(shape, dtype):
    # A one-element storage viewed with stride 0: tiny on disk, the released shape and dtype.
    return torch.zeros((), dtype=dtype).expand(shape)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out_dir")
    ap.add_argument("--dtype", default="float32", choices=["float32", "bfloat16", "float16"])
    ap.add_argument("--check-against", default="", help="fixtures dir: compare names with the official small files")
    a = ap.parse_args()
    if a.check_against:
        check_names(a.check_against)
    dtype = getattr(torch, a.dtype)
    os.makedirs(a.out_dir, exist_ok=True)
    gen, emb, dec = generator_shapes(), embedder_shapes(), decoder_shapes()
    state = {k: zeros(v, dtype) for k, v in {**gen, **emb}.items()}
    ckpt = {"state_dict": state, "epoch": 0, "global_step": 0, "pytorch-lightning_version": "2.x (test data)",
            "hyper_parameters": {}}
    torch.save(ckpt, os.path.join(a.out_dir, "ss_generator.ckpt"))
    torch.save({k: zeros(v, dtype) for k, v in dec.items()}, os.path.join(a.out_dir, "ss_decoder.ckpt"))

    def count(d):
        n = 1
        tot = 0
        for v in d.values():
            n = 1
            for x in v:
                n *= x
            tot += n
        return tot

    print(json.dumps({"generator_tensors": len(gen), "generator_elements": count(gen),
                      "embedder_tensors": len(emb), "embedder_elements": count(emb),
                      "decoder_tensors": len(dec), "decoder_elements": count(dec), "dtype": a.dtype}))


if __name__ == "__main__":
    sys.exit(main())
