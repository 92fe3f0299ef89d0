// Launchers of the flow model's fused CUDA kernels (src/models/fused_kernels.cu). Plain pointers and a
// stream so that the .cu file needs no torch headers; the checked, tensor-level API is fused_ops.h.
// T, the 16-bit storage type, is __nv_bfloat16 (bf16 autocast, training) or __half (fp16 autocast, the
// released inference precision); both are instantiated. Arithmetic is fp32 either way.
#pragma once

#include <cstdint>

#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <cuda_runtime_api.h>

namespace simu::models::kernels {

// y[r, :] = (x[r, :] - mean) * rstd * w[r / rows_per_w, :] + b[r / rows_per_w, :] in fp32, stored as T.
// x: [rows, C] fp32 contiguous; w, b: [rows / rows_per_w, C] fp32 (b may be null); C % 128 == 0, C <= 1024.
template <typename T>
cudaError_t layer_norm_affine(const float* x, const float* w, const float* b, T* y, int64_t rows, int64_t rows_per_w,
                              int C, float eps, cudaStream_t stream);

// x_out[r, :] = x[r, :] + h[r, :] * gate[r / rows_per_gate, :] (gate null: + h) in fp32, then
// y = layer_norm_affine(x_out, w, b). h: [h_rows, C] T contiguous; rows r >= h_rows read h_tail [C]
// instead (one row broadcast; null when h_rows = rows); gate: [rows / rows_per_gate, C] fp32.
template <typename T>
cudaError_t residual_layer_norm_affine(const float* x, const T* h, int64_t h_rows, const T* h_tail, const float* gate,
                                       int64_t rows_per_gate, float* x_out, const float* w, const float* b, T* y,
                                       int64_t rows, int64_t rows_per_w, int C, float eps, cudaStream_t stream);

// From a fused projection qkv [B, L, 3, H, D] (T, contiguous) writes, per token and head,
//   q = T(q / max(|q|, 1e-12) * gq[h] * scale), k likewise with gk, v copied,
// into outputs (of type T) addressed as out + b*sb + l*sl + h*D + d (strides in elements). D in 64, 128, 256.
// Two kernels: wide = false, one warp per (token, head), 4 bytes per lane and access (needs 4-byte aligned
// outputs and even strides); wide = true, 8 lanes per 64 channels of a head (4 heads of 64 per warp, 2 of
// 128, 1 of 256), 16 bytes per lane and access: needs split_qkv_wide_ok (else cudaErrorMisalignedAddress).
// Same per-element arithmetic; only the summation order of |q|, |k| differs.
struct QkvOut {
  void* ptr;
  int64_t sb, sl;
};
template <typename T>
cudaError_t split_qkv_rms_norm(const T* qkv, const float* gq, const float* gk, float scale, QkvOut q, QkvOut k, QkvOut v,
                               int B, int L, int H, int D, bool wide, cudaStream_t stream);
// Whether the wide kernel may run: qkv, gq, gk and the outputs 16-byte aligned, output strides multiples of 8.
bool split_qkv_wide_ok(const void* qkv, const float* gq, const float* gk, QkvOut q, QkvOut k, QkvOut v);

// Backward of layer_norm_affine (and of residual_layer_norm_affine) with respect to x only:
//   dx = LN'(x)^T (gy * w[r / rows_per_w]) + gx_in   (fp32; gy null: LayerNorm term 0; gx_in null: 0)
//   dh = dx * gate[r / rows_per_gate] stored as T (gate null: dx; dh null: not written).
// x: the LayerNorm's fp32 input [rows, C]; gy: [rows, C] T; mean/rstd are recomputed from x.
template <typename T>
cudaError_t layer_norm_affine_backward(const float* x, const float* w, int64_t rows_per_w, const T* gy, const float* gx_in,
                                       const float* gate, int64_t rows_per_gate, float* dx, T* dh, int64_t rows, int C,
                                       float eps, cudaStream_t stream);

// Backward of split_qkv_rms_norm: the gradients of q, k, v ([B, L, H, D] T read at
// ptr + b*sb + l*sl + h*sh + d; ptr null: zero) -> dqkv [B, L, 3, H, D] T contiguous.
struct QkvGrad {
  const void* ptr;
  int64_t sb, sl, sh;
};
// wide: the 16-byte kernel (as split_qkv_rms_norm's), which needs split_qkv_backward_wide_ok.
template <typename T>
cudaError_t split_qkv_rms_norm_backward(const T* qkv, const float* gq, const float* gk, float scale, QkvGrad dq, QkvGrad dk,
                                        QkvGrad dv, T* dqkv, int B, int L, int H, int D, bool wide, cudaStream_t stream);
// Whether the wide backward may run: qkv, gammas, dqkv and the non-null gradients 16-byte aligned, gradient
// strides multiples of 8 elements.
bool split_qkv_backward_wide_ok(const void* qkv, const float* gq, const float* gk, QkvGrad dq, QkvGrad dk, QkvGrad dv,
                                const void* dqkv);

// The adaLN modulation of a block as fp32 rows: m [rows, 6C] (T contiguous: bf16, fp16 or float; six chunks
// of C channels) -> out [6, rows, C] float32 contiguous, out[k, r, c] = m[r, k*C + c] widened to fp32, except
// the scale chunks (k = 1, 4): float(T(float(m) + 1)), i.e. 1 + scale rounded once to T as ATen's
// (1 + scale) on a T tensor, then widened.
template <typename T>
cudaError_t modulation_rows(const T* m, float* out, int64_t rows, int64_t C, cudaStream_t stream);

}  // namespace simu::models::kernels
