// The flow model's fused kernels at tensor level, each next to the plain-ATen reference it must match
// (tests/models/fused_ops_gpu.cpp compares them, values and gradients). The fused versions run on CUDA
// only, on shapes the kernels support (see supports_*); callers check and otherwise take the reference.
//
// Gradients: layer_norm_affine_bf16, residual_layer_norm_affine_bf16 and split_qkv_rms_norm_autograd
// are differentiable with respect to their activations (x, h, qkv) through fused backward kernels; the
// forward kernel is the same with or without a graph. Their weights (w, b, gate, gammas) are the frozen
// base's and get no gradient: when one of them requires a gradient under grad mode, the function
// takes its ATen reference instead. split_qkv_rms_norm and linear_gelu_tanh_bf16 have no backward
// (inference only).
//
// 16-bit storage: the names say bf16 (the training recipe's autocast), but every kernel also stores
// fp16, the released inference precision (pipeline.yaml `dtype: float16`): the low-precision tensors
// (outputs, h, qkv, gradients) are bf16 or fp16 (is_low_precision), arithmetic stays fp32. The
// references take the same dtype, so fast and reference paths are compared in both.
#pragma once

#include <torch/torch.h>

namespace simu::models::fused {

// True when the library was compiled with the CUDA kernels (nvcc present at build time).
bool compiled();
// Number of fused kernel launches so far in this process (tests check that a fast path really ran).
int64_t launch_count();
// Launches of modulation_rows' kernel (one per block on the fused path), counted apart from launch_count.
int64_t modulation_launch_count();
// bf16 or fp16: the 16-bit types the kernels store.
bool is_low_precision(torch::ScalarType dtype);

// LayerNorm (no affine of its own, fp32 math) followed by a per-row-group affine, stored as `out`
// (bf16 by default, or fp16):
//   x: [B, L, C] float32 contiguous; w, b: [G, C] float32 with G = 1 or G = B (b may be undefined).
//   y[b, l] = LN(x[b, l]) * w[b or 0] + b[b or 0]  -> [B, L, C] out.
// This is norm1/norm3 + the adaLN modulation (w = 1 + scale, b = shift) and the affine norm2.
bool supports_layer_norm_affine(const torch::Tensor& x);
torch::Tensor layer_norm_affine_bf16(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b, double eps,
                                     torch::ScalarType out = torch::kBFloat16);
torch::Tensor layer_norm_affine_bf16_reference(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b,
                                               double eps, torch::ScalarType out = torch::kBFloat16);

// The residual update in front of a LayerNorm + affine, in one pass:
//   x_new = x + h * gate  (fp32; as torch::addcmul(x, h, gate); gate undefined: x + h)
//   y = layer_norm_affine_bf16(x_new, w, b, eps)
// x: [B, L, C] float32 contiguous; h: [B, L, C] bf16 or fp16 contiguous (a sublayer's output); gate: [G, C]
// (any float dtype, G = 1 or B) or undefined; w, b as for layer_norm_affine_bf16. Returns {x_new, y}, y in
// h's dtype (residual_output_dtype: the reference gives fp16 for an fp16 h, else bf16).
torch::ScalarType residual_output_dtype(const torch::Tensor& h);
bool supports_residual_layer_norm_affine(const torch::Tensor& x, const torch::Tensor& h);
std::pair<torch::Tensor, torch::Tensor> residual_layer_norm_affine_bf16(const torch::Tensor& x, const torch::Tensor& h,
                                                                         const torch::Tensor& gate, const torch::Tensor& w,
                                                                         const torch::Tensor& b, double eps);
// The same without autograd when h's rows from head.size(0) on are one broadcast row (CFG's
// zero-condition rows after a cross attention, CrossAttentionImpl::attend_parts):
//   residual_layer_norm_affine_bf16(x, cat(head, tail expanded to the other rows), gate, w, b, eps)
// without making that concatenation. head: [Bh <= B, L, C] bf16/fp16 contiguous; tail: C elements of
// head's dtype, contiguous, 16-byte aligned. CUDA kernels only (supports_..._tail); no gradient.
bool supports_residual_layer_norm_affine_tail(const torch::Tensor& x, const torch::Tensor& head, const torch::Tensor& tail);
std::pair<torch::Tensor, torch::Tensor> residual_layer_norm_affine_tail_bf16(const torch::Tensor& x, const torch::Tensor& head,
                                                                              const torch::Tensor& tail, const torch::Tensor& gate,
                                                                              const torch::Tensor& w, const torch::Tensor& b,
                                                                              double eps);
std::pair<torch::Tensor, torch::Tensor> residual_layer_norm_affine_bf16_reference(const torch::Tensor& x,
                                                                                   const torch::Tensor& h,
                                                                                   const torch::Tensor& gate,
                                                                                   const torch::Tensor& w,
                                                                                   const torch::Tensor& b, double eps);

// The official multi-head RMS norm in plain ATen, differentiable: x / max(|x|, 1e-12) * gamma * scale
// over the last dim in fp32, back to x's dtype. x: [..., H, D]; gamma: [H, D].
torch::Tensor multi_head_rms_norm_reference(const torch::Tensor& x, const torch::Tensor& gamma, double scale);

// Splits a fused projection qkv: [B, L, 3, H, D] bf16 or fp16 into q, k, v (qkv's dtype), with the official multi-head
// RMS norm on q and k (q / max(|q|, 1e-12) * gamma * scale in fp32, gamma: [H, D] float32).
// Writes into the given outputs ([B, L, H, D] views, last two dims contiguous, any even batch/token strides,
// 4-byte aligned), so that k and v can land directly in a larger key/value buffer.
// Two kernels, same per-element arithmetic (only the summation order of |q|, |k| differs): a 16-byte one
// (8 lanes per 64 channels of a head, 16 bytes per lane and access) when qkv, the fp32 gammas and every
// output are 16-byte aligned with strides a multiple of 8 elements, else the 4-byte one (one warp per
// token and head). The reference below stays the reference for both.
bool supports_split_qkv(const torch::Tensor& qkv);
void split_qkv_rms_norm(const torch::Tensor& qkv, const torch::Tensor& gamma_q, const torch::Tensor& gamma_k, double scale,
                        torch::Tensor q, torch::Tensor k, torch::Tensor v);
// The backward kernel of split_qkv_rms_norm_autograd at tensor level: the gradients of q, k, v ([B, L, H, D],
// any dtype, any layout; undefined: zero; rows with contiguous channels, 4-byte aligned and even strides are
// read in place, others copied) -> dqkv [B, L, 3, H, D] in qkv's dtype, contiguous:
//   dq_in = u / n - q * (u . q) / n^3 with u = dq * gamma_q * scale, n = |q| (n <= 1e-12: u / 1e-12); k alike;
//   dv_in = dv. Wide (16-byte) kernel when qkv, gammas, dqkv and the gradients are 16-byte aligned with strides
// a multiple of 8 elements. CUDA kernels only (supports_split_qkv).
torch::Tensor split_qkv_rms_norm_backward(const torch::Tensor& qkv, const torch::Tensor& gamma_q, const torch::Tensor& gamma_k,
                                          double scale, const torch::Tensor& dq, const torch::Tensor& dk,
                                          const torch::Tensor& dv);
// Switches the 16-byte split kernels on (default) or off (the 4-byte ones always: benchmarks and tests of
// the fallback), process-wide; split_qkv_wide_launch_count counts 16-byte launches, forward and backward.
void set_split_qkv_wide(bool on);
bool split_qkv_wide();
int64_t split_qkv_wide_launch_count();
void split_qkv_rms_norm_reference(const torch::Tensor& qkv, const torch::Tensor& gamma_q, const torch::Tensor& gamma_k,
                                  double scale, torch::Tensor q, torch::Tensor k, torch::Tensor v);

// y = gelu_tanh(x @ w^T + b) with the GELU in the matrix product's epilogue (cuBLASLt), in
// linear_gelu_dtype(x): the CUDA autocast dtype when autocast is on in bf16 or fp16, else fp16 for an
// fp16 x, else bf16:
//   x: [..., K] (cast to that dtype), w: [N, K], b: [N] (the fp32 parameters; 16-bit copies from the
//   autocast cache when autocast is on) -> [..., N]. Reference: linear, then gelu(approximate="tanh").
// split_qkv_rms_norm into new contiguous q, k, v [B, L, H, D] (same kernel), differentiable with respect to
// qkv: the backward kernel takes the three gradients (any token/head strides) and writes dqkv in one pass.
// qkv: [B, L, 3, H, D] bf16 contiguous (supports_split_qkv). Without kernels: the reference, unbound.
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> split_qkv_rms_norm_autograd(const torch::Tensor& qkv,
                                                                                   const torch::Tensor& gamma_q,
                                                                                   const torch::Tensor& gamma_k,
                                                                                   double scale);

// A block's adaLN modulation as the fp32 rows its fused kernels read, in one kernel:
//   m: [G, 6C] bf16, fp16 or float32 (G = 1 or B; the chunks shift_msa, scale_msa, gate_msa, shift_mlp,
//   scale_mlp, gate_mlp) -> [6, G, C] float32, row k = chunk k widened to fp32, except the scales (k = 1, 4):
//   1 + scale computed as ATen's (1 + scale) on m's dtype (one rounding to that dtype), then widened.
// Rows 1/0 and 4/3 are norm1's and norm3's LayerNorm weight/bias, rows 2 and 5 the gates (exact fp32
// copies of the 16-bit gates, which the residual kernels and addcmul widen anyway). No backward: when
// grad mode records through m (it requires a gradient), or without kernel support, the reference
// (the same ATen ops per chunk, differentiable).
bool supports_modulation_rows(const torch::Tensor& m);
torch::Tensor modulation_rows(const torch::Tensor& m);
torch::Tensor modulation_rows_reference(const torch::Tensor& m);

bool supports_linear_gelu(const torch::Tensor& x);
torch::ScalarType linear_gelu_dtype(const torch::Tensor& x);
torch::Tensor linear_gelu_tanh_bf16(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b);
torch::Tensor linear_gelu_tanh_bf16_reference(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b);

}  // namespace simu::models::fused
