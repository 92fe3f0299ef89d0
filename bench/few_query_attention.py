#!/usr/bin/env python3
"""The pose stream's cross attention in sampling: 4 query tokens over the whole condition.

Times, for q [B, 16, 4, 64] over keys/values [B, 16, Lk, 64] (fp16, keys/values laid out as the flow
model's condition cache holds them: views of one [B, Lk, 2, 16, 64] projection), every
scaled_dot_product_attention backend and a split-key matrix-product formulation (scores, fp32 softmax,
P V over S key chunks summed). Method: each variant is captured N times in one CUDA graph and replayed
(so launch latency, absent from graph replays in sampling, is not counted); median of --iters replays,
time per call. Also prints the max abs difference of each variant to the math backend in fp32.
"""
import argparse

import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel


def split_kv(q, k, v, splits):
    # q [B,H,Lq,D], k/v [B,H,Lk,D] -> [B,H,Lq,D]
    B, H, Lq, D = q.shape
    Lk = k.shape[2]
    s = torch.matmul(q, k.transpose(-1, -2)) * D ** -0.5           # [B,H,Lq,Lk]
    p = torch.softmax(s.float(), -1).to(q.dtype)
    if splits == 1:
        return torch.matmul(p, v)
    c = Lk // splits
    pc = p.view(B, H, Lq, splits, c).transpose(2, 3)               # [B,H,S,Lq,c]
    vc = v.reshape(B, H, splits, c, D) if v.is_contiguous() else v.contiguous().view(B, H, splits, c, D)
    return torch.matmul(pc, vc).sum(2, dtype=torch.float32).to(q.dtype)


def timed(fn, n, iters):
    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s):
        for _ in range(3):
            fn()
    torch.cuda.current_stream().wait_stream(s)
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g):
        for _ in range(n):
            fn()
    ts = []
    for _ in range(iters):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record(); g.replay(); b.record(); torch.cuda.synchronize()
        ts.append(a.elapsed_time(b) * 1000 / n)
    ts.sort()
    return ts[len(ts) // 2]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cond-lens", type=int, nargs="+", default=[7528, 2800])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--n", type=int, default=50, help="calls per graph")
    ap.add_argument("--iters", type=int, default=7)
    a = ap.parse_args()
    torch.manual_seed(0)
    H, D, Lq = 16, 64, 4
    print(f"# {torch.cuda.get_device_name()}, torch {torch.__version__}; us per call (graph replay)")
    print("| B | Lk | variant | us | max abs diff vs math fp32 |")
    print("|---|---|---|---|---|")
    for Lk in a.cond_lens:
        for B in a.batches:
            kv = torch.randn(B, Lk, 2, H, D, device="cuda", dtype=torch.float16)
            k, v = kv[:, :, 0].permute(0, 2, 1, 3), kv[:, :, 1].permute(0, 2, 1, 3)
            q = torch.randn(B, Lq, H, D, device="cuda", dtype=torch.float16).permute(0, 2, 1, 3)
            ref = F.scaled_dot_product_attention(q.float(), k.float(), v.float())
            variants = {"sdpa default": lambda: F.scaled_dot_product_attention(q, k, v)}
            for name, be in [("cudnn", SDPBackend.CUDNN_ATTENTION), ("flash", SDPBackend.FLASH_ATTENTION),
                             ("efficient", SDPBackend.EFFICIENT_ATTENTION)]:
                variants[name] = (lambda be=be: (lambda: _with(be, q, k, v)))()
            vc = v.contiguous()
            for S in [1, 4, 8, 16]:
                if Lk % S == 0:
                    variants[f"matmul split {S}"] = (lambda S=S: (lambda: split_kv(q, k, vc, S)))()
            for name, fn in variants.items():
                try:
                    out = fn()
                    err = (out.float() - ref).abs().max().item()
                    us = timed(fn, a.n, a.iters)
                    print(f"| {B} | {Lk} | {name} | {us:.1f} | {err:.2e} |", flush=True)
                except Exception as e:  # a backend that refuses these shapes
                    print(f"| {B} | {Lk} | {name} | - | {type(e).__name__}: {str(e)[:60]} |", flush=True)


def _with(be, q, k, v):
    with sdpa_kernel(be):
        return F.scaled_dot_product_attention(q, k, v)


if __name__ == "__main__":
    main()
