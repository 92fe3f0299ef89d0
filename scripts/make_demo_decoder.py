#!/usr/bin/env python3
"""Writes the DEMO decoder weights used by scripts/demo.sh.

The small fixture decoder (fixtures/ss_decoder_small.safetensors) has random weights: its occupancy
logits are all <= 0 for the demo's latents, so nothing would be meshed and the resampled object would
only be flagged. This derives a demo decoder from it: every weight is kept, except that the output
convolution (out_layer.2) has its weights multiplied by --weight-scale and --bias added to its bias.
The logits become bias + (a damped random field of the latent): most voxels are occupied, the random
field dents the block, so the decoded shape is a lumpy blob that still depends on the sampled latent.

These are RANDOM-WEIGHT DEMO WEIGHTS, not a trained model; the file's metadata says so.

usage: make_demo_decoder.py FIXTURE_DECODER.safetensors OUT.safetensors [--weight-scale S] [--bias B]
"""
import argparse

import torch
from safetensors.torch import load_file, save_file


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("fixture", help="fixture decoder safetensors (ss_decoder_small.safetensors)")
    ap.add_argument("out", help="output safetensors")
    ap.add_argument("--weight-scale", type=float, default=0.25, help="factor on out_layer.2.weight")
    ap.add_argument("--bias", type=float, default=1.0, help="added to out_layer.2.bias")
    args = ap.parse_args()

    tensors = load_file(args.fixture)
    # Only the decoder's own weights (the fixture file also holds its io.* test tensors).
    tensors = {k: v for k, v in tensors.items() if not k.startswith("io.")}
    for key in ("out_layer.2.weight", "out_layer.2.bias"):
        if key not in tensors:
            raise SystemExit(f"error: {args.fixture}: key {key} missing (expected the small sparse-structure decoder)")
    # Output head: damped random field plus a positive bias.
    tensors["out_layer.2.weight"] = tensors["out_layer.2.weight"] * args.weight_scale
    tensors["out_layer.2.bias"] = tensors["out_layer.2.bias"] + args.bias
    note = (f"DEMO ONLY, random weights: derived from {args.fixture} (random-weight fixture decoder) with "
            f"out_layer.2.weight x {args.weight_scale} and out_layer.2.bias + {args.bias} so that voxels are "
            "occupied; not a trained model")
    save_file({k: v.contiguous() for k, v in tensors.items()}, args.out, metadata={"note": note})
    print(f"wrote {args.out}: {note}")


if __name__ == "__main__":
    main()
