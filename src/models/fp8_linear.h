// FP8 (e4m3) frozen-weight linear products: the opt-in "FP8 frozen base" of FM-DPO training
// (train.fp8_base, docs/training.md "FP8 frozen base").
//
// What it does. A frozen weight W [out, in] is quantised once to e4m3 with one fp32 scale per output
// channel (row of W); each call quantises its input x [rows, in] with one scale per row (token), and
// the product runs on Hopper's FP8 tensor cores (at::_scaled_mm, row-wise scales, bf16 output):
//   y[i, j] = sx[i] * sw[j] * sum_k qx[i, k] qw[j, k]  (+ bias[j]),   q = e4m3(v / s),  s = amax / 448
// The input gradient dX = dY W (the base is frozen: no weight gradient) runs through FP8 too by
// default (dY quantised per row to e4m3, W^T quantised per input channel), or in bf16
// (Fp8Backward::kBf16, a bf16 copy of W). Why FP8 by default: an FM-DPO step computes each wrapped
// base product three times (policy and reference forwards, one input-gradient product), so a bf16
// backward caps the base products' speed-up at 1.5x instead of 2x; the LoRA gradients dA, dB of a
// layer use that layer's exact bf16 dY, and the FP8 error of dX enters only as the upstream gradient
// of earlier layers, an unbiased per-element rounding (row-wise scales, 3 mantissa bits) that
// averages over the product's in/out dimension like the forward's does. e4m3 (not e5m2) for dY: with
// one scale per row the range within a row is what matters (e4m3 spans 2^-9 .. 448, 18 binades), and
// e4m3's extra mantissa bit halves the rounding error; torch's row-wise _scaled_mm takes e4m3 only.
//
// What it costs in fidelity: e4m3 rounds each operand element to 3 mantissa bits (relative error
// <= 2^-4 for normal values, RMS about 2^-4/sqrt(3)); the measured cost on the FM-DPO gradients
// (cosine vs the bf16 step, d_theta - d_ref) is bench/fp8_fidelity's output, figures in docs/benchmarks.md.
// Opt-in only: nothing uses it unless train.fp8_base (or set_fp8_base) switches it on.
//
// Reference path: on a CPU tensor fp8_matmul emulates the product exactly as specified above
// (dequantised operands, fp32 matmul, rounded to bf16); tests compare the CUDA path against it.
// Non-finite inputs: a row with a NaN or Inf gives a NaN scale and an all-NaN output row (bf16
// gives NaN/Inf there too); an all-zero row has scale 1 and quantises to zeros.
#pragma once

#include <torch/torch.h>

#include <memory>
#include <string>

namespace simu::models {

// e4m3fn's largest finite value.
constexpr double kE4m3Max = 448.0;

// How the input gradient of an FP8 linear is computed.
enum class Fp8Backward { kFp8, kBf16 };
// "fp8" / "bf16" <-> enum; parse throws naming `what` and the accepted values.
Fp8Backward parse_fp8_backward(const std::string& name, const std::string& what);
std::string fp8_backward_name(Fp8Backward b);

// A matrix quantised per row: v[i, k] ~= q[i, k] * scale[i].
struct Fp8Rows {
  torch::Tensor q;      // [rows, cols] e4m3fn
  torch::Tensor scale;  // [rows, 1] float32 (amax of the row * (1/448); 1 for an all-zero row)
};

// Quantises v [rows, cols] (any float dtype, any device) per row. One reduction and one fused
// divide-and-convert pass over v.
Fp8Rows quantize_rows(const torch::Tensor& v);
// q * scale in float32: [rows, cols].
torch::Tensor dequantize_rows(const Fp8Rows& r);

// a [M, K] x b [N, K] -> a b^T [M, N] (+ bias [N]) in bf16. CUDA: at::_scaled_mm with row-wise
// scales (K and N multiples of 16; compute capability >= 8.9). CPU: the reference emulation
// (fp8_matmul_reference rounded to bf16).
torch::Tensor fp8_matmul(const Fp8Rows& a, const Fp8Rows& b, const torch::Tensor& bias, bool fast_accum);
// The emulation on any device: dequantise both, matmul in fp32 (+ bias) -> [M, N] float32.
torch::Tensor fp8_matmul_reference(const Fp8Rows& a, const Fp8Rows& b, const torch::Tensor& bias);

// A frozen Linear weight prepared for FP8 products.
struct Fp8Weight {
  Fp8Rows fwd;               // W [out, in] per output channel
  Fp8Rows bwd;               // W^T [in, out] per input channel (Fp8Backward::kFp8)
  torch::Tensor bwd_bf16;    // W [out, in] bf16 (Fp8Backward::kBf16)
  torch::Tensor bias;        // [out] bf16, or undefined
  Fp8Backward backward = Fp8Backward::kFp8;
  int64_t in_features = 0, out_features = 0;
};
// Quantises weight [out, in] (and converts bias [out]) on their device; no gradient is tracked.
std::shared_ptr<Fp8Weight> make_fp8_weight(const torch::Tensor& weight, const torch::Tensor& bias, Fp8Backward backward);

// y = x W^T + b through FP8: x [..., in] (any float dtype) -> [..., out] bf16 (in x's dtype when
// autocast is off and x is not bf16). Differentiable in x only (dX as w.backward says); no graph when
// x does not require a gradient. Forward products use fast accumulation, the backward's do not.
torch::Tensor fp8_linear(const torch::Tensor& x, const Fp8Weight& w);

// True when FP8 products run on device: CUDA with compute capability >= 8.9 (Ada, Hopper, later).
bool fp8_supported(const torch::Device& device);
// Throws simu::Error naming `what` when !fp8_supported(device): on CPU, or on a GPU without FP8.
void require_fp8_device(const torch::Device& device, const std::string& what);

}  // namespace simu::models
