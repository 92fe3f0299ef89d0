#!/usr/bin/env python3
"""Convert an official SAM 3D Objects checkpoint (.ckpt / .pt: torch.save or PyTorch Lightning) to
safetensors, keeping the official tensor names (e.g. `_base_models.generator.reverse_fn.backbone...`).

Usage: python3 scripts/convert_checkpoint.py IN.ckpt OUT.safetensors [--prefix P] [--dtype keep|float32]

- Lightning checkpoints keep the weights under `state_dict`; a plain torch.save dict of tensors is
  used as is. Non-tensor entries are skipped (listed on stderr).
- --prefix keeps only keys starting with P (names unchanged), e.g. `_base_models.generator.`.
- The C++ loader strips `_base_models.generator.` itself; nothing is renamed here.
Needs only PyTorch (the safetensors file is written directly: 8-byte header length, JSON header,
raw little-endian data), atomically (temporary file + rename), one tensor at a time. Prints the tensor
and element counts per `_base_models.<component>.` prefix.
"""
import argparse
import json
import os
import struct
import sys

import torch

DTYPES = {
    torch.float32: "F32", torch.float16: "F16", torch.bfloat16: "BF16", torch.float64: "F64",
    torch.int64: "I64", torch.int32: "I32", torch.int16: "I16", torch.int8: "I8", torch.uint8: "U8",
    torch.bool: "BOOL",
}


def load_state(path):
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # older checkpoints may hold non-tensor objects (hyper-parameters)
        print(f"note: weights_only load failed ({type(e).__name__}); retrying with weights_only=False "
              f"(only do this for checkpoints you trust)", file=sys.stderr)
        obj = torch.load(path, map_location="cpu", weights_only=False)
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        sys.exit(f"error: {path}: expected a dict of tensors or a Lightning checkpoint with 'state_dict', "
                 f"got {type(obj).__name__}")
    return obj


def tensor_bytes(t):
    t = t.detach().cpu().contiguous()
    if t.dtype == torch.bfloat16:
        return t.view(torch.int16).numpy().tobytes()
    return t.numpy().tobytes()


def nbytes(t):
    return t.numel() * t.element_size()


def is_expanded_zero(t):
    """True for a tensor whose (smaller) storage is all zeros, e.g. torch.zeros(()).expand(shape): its
    bytes are written as a hole (sparse file) instead of materialising it. Never true for ordinary
    (full-storage) tensors, whose bytes are always written."""
    st = t.untyped_storage()
    if st.nbytes() >= nbytes(t) or t.numel() == 0:
        return False
    flat = torch.empty(0, dtype=torch.uint8).set_(st)
    return not bool(flat.any())


def save_safetensors(path, tensors):
    """Streams tensors one at a time (memory: the largest tensor, not the checkpoint)."""
    header, offset, names = {}, 0, sorted(tensors)
    for name in names:
        t = tensors[name]
        if t.dtype not in DTYPES:
            sys.exit(f"error: tensor {name}: unsupported dtype {t.dtype}")
        n = nbytes(t)
        header[name] = {"dtype": DTYPES[t.dtype], "shape": list(t.shape), "data_offsets": [offset, offset + n]}
        offset += n
    header["__metadata__"] = {"format": "pt", "source": "scripts/convert_checkpoint.py"}
    h = json.dumps(header, separators=(",", ":")).encode()
    h += b" " * ((8 - len(h) % 8) % 8)
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(struct.pack("<Q", len(h)))
        f.write(h)
        for name in names:
            t = tensors[name]
            if is_expanded_zero(t):
                f.seek(nbytes(t), os.SEEK_CUR)  # zeros: a hole
            else:
                f.write(tensor_bytes(t))
        f.truncate(8 + len(h) + offset)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("input", help="official .ckpt/.pt file")
    ap.add_argument("output", help="output .safetensors file")
    ap.add_argument("--prefix", default="", help="keep only keys starting with this prefix")
    ap.add_argument("--dtype", choices=["keep", "float32"], default="keep", help="convert floating tensors")
    a = ap.parse_args()
    state = load_state(a.input)
    out, skipped = {}, []
    for k, v in state.items():
        if not isinstance(v, torch.Tensor):
            skipped.append(k)
            continue
        if a.prefix and not k.startswith(a.prefix):
            continue
        if a.dtype == "float32" and v.is_floating_point():
            v = v.float()
        out[k] = v
    if skipped:
        print(f"skipped {len(skipped)} non-tensor entries: {skipped[:10]}", file=sys.stderr)
    if not out:
        sys.exit(f"error: {a.input}: no tensors to write (prefix '{a.prefix}')")
    save_safetensors(a.output, out)
    n = sum(v.numel() for v in out.values())
    prefixes = {}
    for k, v in out.items():
        p = ".".join(k.split(".")[:2]) + "." if k.startswith("_base_models.") else "(no _base_models prefix)"
        c = prefixes.setdefault(p, [0, 0])
        c[0] += 1
        c[1] += v.numel()
    print(f"wrote {a.output}: {len(out)} tensors, {n} elements")
    for p, (nt, ne) in sorted(prefixes.items()):
        print(f"  {p}: {nt} tensors, {ne} elements")


if __name__ == "__main__":
    main()
