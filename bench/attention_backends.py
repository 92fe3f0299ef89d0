#!/usr/bin/env python3
"""Ceilings for the Stage-1 flow model's building blocks on this GPU (bf16, PyTorch's own kernels).

Times, for the real model's shapes (1024 channels, 16 heads of 64, 4096 shape tokens, batch 2 = the
CFG pair), every scaled_dot_product_attention backend PyTorch offers here (flash, FA3 when it can be
activated, cuDNN, memory-efficient) forward and forward+backward, and the linear layers' matrix
products; prints TFLOP/s and the ratio to a plain 8192^3 bf16 matmul measured in the same run.
Method: CUDA events around each call, median of --iters after --warmup; FLOPs counted analytically
(attention 4*B*H*Lq*Lk*D forward, 2.5x that for forward+backward; GEMM 2*M*N*K).
"""
import argparse

import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel


def median_ms(fn, warmup, iters):
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(iters):
        s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        s.record()
        fn()
        e.record()
        torch.cuda.synchronize()
        times.append(s.elapsed_time(e))
    times.sort()
    return times[len(times) // 2]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--heads", type=int, default=16)
    ap.add_argument("--head-dim", type=int, default=64)
    ap.add_argument("--tokens", type=int, default=4096)
    ap.add_argument("--cond-lens", type=int, nargs="+", default=[2800, 7500])
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--iters", type=int, default=10)
    a = ap.parse_args()
    if not torch.cuda.is_available():
        print("attention_backends.py needs a CUDA device (none here)")
        return
    dev, bf = "cuda", torch.bfloat16
    x = torch.randn(8192, 8192, device=dev, dtype=bf)
    peak = 2 * 8192**3 / median_ms(lambda: x @ x, a.warmup, a.iters) / 1e9
    print(f"device: {torch.cuda.get_device_name()}  torch {torch.__version__}  bf16 matmul 8192^3: {peak:.1f} TFLOP/s")

    # FA3 (Hopper) is an optional flash implementation in recent PyTorch; try to activate it.
    fa3 = False
    try:
        from torch.nn.attention import activate_flash_attention_impl  # type: ignore

        activate_flash_attention_impl("FA3")
        fa3 = True
        from torch.nn.attention import restore_flash_attention_impl  # type: ignore

        restore_flash_attention_impl()
    except Exception as err:  # noqa: BLE001 - report any reason
        print(f"FA3 not available: {type(err).__name__}: {err}")

    B, H, D, L = a.batch, a.heads, a.head_dim, a.tokens
    cases = [("self shape", L, L)] + [(f"cross c{c}", L, c) for c in a.cond_lens]
    backends = [("flash", SDPBackend.FLASH_ATTENTION), ("cudnn", SDPBackend.CUDNN_ATTENTION),
                ("efficient", SDPBackend.EFFICIENT_ATTENTION)]
    print("| attention | backend | fwd ms | fwd TFLOP/s | % matmul | fwd+bwd ms | fwd+bwd TFLOP/s | % matmul |")
    print("|---|---|---|---|---|---|---|---|")
    for name, lq, lk in cases:
        q = torch.randn(B, H, lq, D, device=dev, dtype=bf, requires_grad=True)
        k = torch.randn(B, H, lk, D, device=dev, dtype=bf, requires_grad=True)
        v = torch.randn(B, H, lk, D, device=dev, dtype=bf, requires_grad=True)
        g = torch.randn(B, H, lq, D, device=dev, dtype=bf)
        flops = 4.0 * B * H * lq * lk * D
        runs = list(backends)
        if fa3:
            runs.insert(1, ("flash FA3", "FA3"))
        for bname, be in runs:
            try:
                if be == "FA3":
                    from torch.nn.attention import activate_flash_attention_impl, restore_flash_attention_impl  # type: ignore

                    activate_flash_attention_impl("FA3")
                    ctx_be = SDPBackend.FLASH_ATTENTION
                else:
                    ctx_be = be
                with sdpa_kernel([ctx_be]):
                    with torch.no_grad():
                        f_ms = median_ms(lambda: F.scaled_dot_product_attention(q, k, v), a.warmup, a.iters)
                    fb_ms = median_ms(lambda: F.scaled_dot_product_attention(q, k, v).backward(g), a.warmup, a.iters)
                if be == "FA3":
                    restore_flash_attention_impl()
                ft, fbt = flops / f_ms / 1e9, 2.5 * flops / fb_ms / 1e9
                print(f"| {name} | {bname} | {f_ms:.3f} | {ft:.1f} | {100 * ft / peak:.0f}% | {fb_ms:.3f} | {fbt:.1f} | {100 * fbt / peak:.0f}% |")
            except Exception as err:  # noqa: BLE001
                print(f"| {name} | {bname} | n/a: {type(err).__name__}: {str(err).splitlines()[0][:80]} |")

    print("\n| linear (M x K -> N) | ms | TFLOP/s | % matmul |")
    print("|---|---|---|---|")
    M = B * L
    for k_in, n_out, label in [(1024, 3072, "to_qkv"), (1024, 1024, "to_out / to_q"), (1024, 4096, "mlp.fc1"),
                               (4096, 1024, "mlp.fc2"), (1024, 2048, "to_kv (per cond token)")]:
        a_ = torch.randn(M, k_in, device=dev, dtype=bf)
        w = torch.randn(n_out, k_in, device=dev, dtype=bf)
        b = torch.randn(n_out, device=dev, dtype=bf)
        ms = median_ms(lambda: F.linear(a_, w, b), a.warmup, a.iters)
        t = 2.0 * M * k_in * n_out / ms / 1e9
        print(f"| {label} {M}x{k_in}->{n_out} | {ms:.3f} | {t:.1f} | {100 * t / peak:.0f}% |")


if __name__ == "__main__":
    main()
