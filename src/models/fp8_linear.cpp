// FP8 (e4m3) frozen-weight linear products: row-wise quantisation, at::_scaled_mm, the CPU emulation,
// and the autograd function (input gradient only).
#include "models/fp8_linear.h"

#include <ATen/autocast_mode.h>
#include <ATen/cuda/CUDAContext.h>
#include <torch/autograd.h>

#include <limits>

#include "common/error.h"

namespace simu::models {

Fp8Backward parse_fp8_backward(const std::string& name, const std::string& what) {
  if (name == "fp8") return Fp8Backward::kFp8;
  if (name == "bf16") return Fp8Backward::kBf16;
  fail("{}: expected 'fp8' or 'bf16', got '{}'", what, name);
}

std::string fp8_backward_name(Fp8Backward b) { return b == Fp8Backward::kFp8 ? "fp8" : "bf16"; }

Fp8Rows quantize_rows(const torch::Tensor& v) {
  SIMU_CHECK(v.dim() == 2 && v.is_floating_point(), "quantize_rows: expected a 2-D float tensor, got {}-D {}", v.dim(),
             c10::toString(v.scalar_type()));
  // amax per row in fp32 (one reduction pass; NaN propagates, Inf gives an Inf scale).
  auto amax = torch::linalg_vector_norm(v, std::numeric_limits<double>::infinity(), {-1}, /*keepdim=*/true,
                                        torch::kFloat32);  // [rows, 1]
  // amax / 448 as amax * (1/448): CUDA divides by a scalar that way, so both devices compute it alike
  // (within one rounding of the quotient; the row's amax still lands on 448).
  auto scale = (amax * (1.0 / kE4m3Max)).masked_fill_(amax == 0, 1.0);  // [rows, 1]
  // q = e4m3(v / scale): the divide writes e4m3 directly (computed in fp32, rounded to nearest even).
  auto q = torch::empty(v.sizes(), v.options().dtype(torch::kFloat8_e4m3fn));  // [rows, cols]
  at::div_out(q, v, scale);
  return {q, scale};
}

torch::Tensor dequantize_rows(const Fp8Rows& r) { return r.q.to(torch::kFloat32) * r.scale; }

torch::Tensor fp8_matmul_reference(const Fp8Rows& a, const Fp8Rows& b, const torch::Tensor& bias) {
  auto y = torch::matmul(dequantize_rows(a), dequantize_rows(b).t());  // [M, N] fp32
  return bias.defined() ? y + bias.to(torch::kFloat32) : y;
}

torch::Tensor fp8_matmul(const Fp8Rows& a, const Fp8Rows& b, const torch::Tensor& bias, bool fast_accum) {
  SIMU_CHECK(a.q.size(1) == b.q.size(1), "fp8_matmul: inner sizes differ ({} vs {})", a.q.size(1), b.q.size(1));
  if (!a.q.is_cuda()) {
    // No FP8 GEMMs on the CPU: AMP-free IEEE fp32 emulation, rounded to the bf16 the GPU writes.
    at::NoTF32Guard no_tf32;
    return fp8_matmul_reference(a, b, bias).to(torch::kBFloat16);
  }
  // Row-wise scaled product: a row-major [M, K], b^T column-major [K, N], scales [M, 1] and [1, N]
  // (b's [N, 1] scale viewed as [1, N], still contiguous).
  std::optional<torch::Tensor> bias_opt;
  if (bias.defined()) bias_opt = bias;
  return at::_scaled_mm(a.q, b.q.t(), a.scale, b.scale.view({1, -1}), bias_opt, std::nullopt, torch::kBFloat16,
                        fast_accum);
}

std::shared_ptr<Fp8Weight> make_fp8_weight(const torch::Tensor& weight, const torch::Tensor& bias, Fp8Backward backward) {
  torch::NoGradGuard no_grad;
  SIMU_CHECK(weight.dim() == 2, "make_fp8_weight: expected a 2-D weight [out, in], got {}-D", weight.dim());
  auto w = std::make_shared<Fp8Weight>();
  w->out_features = weight.size(0);
  w->in_features = weight.size(1);
  w->backward = backward;
  w->fwd = quantize_rows(weight);  // per output channel
  if (backward == Fp8Backward::kFp8) w->bwd = quantize_rows(weight.t().contiguous());  // [in, out] per input channel
  else w->bwd_bf16 = weight.to(torch::kBFloat16).contiguous();
  if (bias.defined()) w->bias = bias.to(torch::kBFloat16).contiguous();
  return w;
}

namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

// y2 [M, out] bf16 = x2 [M, in] W^T + b through FP8; backward: dX only (W, b frozen).
class Fp8LinearFn : public torch::autograd::Function<Fp8LinearFn> {
 public:
  static torch::Tensor forward(AutogradContext* ctx, const torch::Tensor& x2, const Fp8Weight* w) {
    const bool fp8_bwd = w->backward == Fp8Backward::kFp8;
    if (fp8_bwd) ctx->save_for_backward({w->bwd.q, w->bwd.scale});
    else ctx->save_for_backward({w->bwd_bf16});
    ctx->saved_data["fp8_bwd"] = fp8_bwd;
    ctx->saved_data["dtype"] = x2.scalar_type();
    return fp8_matmul(quantize_rows(x2), w->fwd, w->bias, /*fast_accum=*/true);
  }

  static variable_list backward(AutogradContext* ctx, variable_list grads) {
    const auto saved = ctx->get_saved_variables();
    const auto dtype = ctx->saved_data["dtype"].toScalarType();
    auto dy = grads[0];  // [M, out]
    torch::Tensor dx;    // [M, in]
    if (ctx->saved_data["fp8_bwd"].toBool()) {
      dx = fp8_matmul(quantize_rows(dy), Fp8Rows{saved[0], saved[1]}, torch::Tensor(), /*fast_accum=*/false);
    } else {
      dx = torch::matmul(dy.to(torch::kBFloat16), saved[0]);
    }
    return {dx.to(dtype), torch::Tensor()};
  }
};

}  // namespace

torch::Tensor fp8_linear(const torch::Tensor& x, const Fp8Weight& w) {
  SIMU_CHECK(x.size(-1) == w.in_features, "fp8_linear: input has {} features, the weight {}", x.size(-1), w.in_features);
  auto out_shape = x.sizes().vec();
  out_shape.back() = w.out_features;
  auto x2 = x.reshape({-1, w.in_features});  // [M, in]
  auto y = Fp8LinearFn::apply(x2, &w).view(out_shape);  // [..., out] bf16
  // Autocast semantics: bf16 out under autocast; outside it the caller's dtype comes back.
  if (!at::autocast::is_autocast_enabled(x.device().type()) && x.scalar_type() != torch::kBFloat16)
    y = y.to(x.scalar_type());
  return y;
}

bool fp8_supported(const torch::Device& device) {
  if (!device.is_cuda() || !torch::cuda::is_available()) return false;
  const auto index = device.has_index() ? device.index() : at::cuda::current_device();
  const auto* prop = at::cuda::getDeviceProperties(index);
  return prop->major > 8 || (prop->major == 8 && prop->minor >= 9);
}

void require_fp8_device(const torch::Device& device, const std::string& what) {
  if (fp8_supported(device)) return;
  if (!device.is_cuda() || !torch::cuda::is_available())
    fail_hint("set it to false, or train on a CUDA GPU with compute capability >= 8.9 (Ada, Hopper)",
              "{}: the FP8 frozen base needs a CUDA device with FP8 tensor cores; this run is on {}", what,
              device.str());
  const auto* prop = at::cuda::getDeviceProperties(device.has_index() ? device.index() : at::cuda::current_device());
  fail_hint("set it to false: FP8 GEMMs need compute capability >= 8.9 (Ada, Hopper)",
            "{}: the FP8 frozen base needs FP8 tensor cores; {} has compute capability {}.{}", what, prop->name,
            prop->major, prop->minor);
}

}  // namespace simu::models
