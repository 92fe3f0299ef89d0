#include "models/fused_ops.h"

#include <fmt/ranges.h>

#include <atomic>

#include "common/error.h"

#include <ATen/autocast_mode.h>

#ifdef SIMU_HAVE_CUDA_KERNELS
#include <c10/cuda/CUDAStream.h>

#include "models/fused_kernels.h"
#endif

namespace simu::models::fused {

namespace {

std::atomic<int64_t> g_launches{0};

#ifdef SIMU_HAVE_CUDA_KERNELS
void check_cuda(cudaError_t e, const char* what) {
  SIMU_CHECK(e == cudaSuccess, "fused kernel {}: {}", what, cudaGetErrorString(e));
}
#endif

// [B, L, H, D] output view with the last two dims contiguous: (batch stride, token stride) in elements.
void check_out(const torch::Tensor& o, const torch::Tensor& qkv, const char* name) {
  SIMU_CHECK(o.dim() == 4 && o.size(0) == qkv.size(0) && o.size(1) == qkv.size(1) && o.size(2) == qkv.size(3) &&
                 o.size(3) == qkv.size(4),
             "split_qkv_rms_norm: {} must be [{}, {}, {}, {}], got [{}]", name, qkv.size(0), qkv.size(1), qkv.size(3),
             qkv.size(4), fmt::join(o.sizes(), ", "));
  SIMU_CHECK(o.scalar_type() == torch::kBFloat16 && o.stride(3) == 1 && o.stride(2) == o.size(3) && o.device() == qkv.device(),
             "split_qkv_rms_norm: {} must be a bfloat16 view on {} with contiguous heads", name, qkv.device().str());
}

}  // namespace

int64_t launch_count() { return g_launches.load(); }

bool compiled() {
#ifdef SIMU_HAVE_CUDA_KERNELS
  return true;
#else
  return false;
#endif
}

bool supports_layer_norm_affine(const torch::Tensor& x) {
  const int64_t C = x.size(-1);
  return compiled() && x.is_cuda() && x.dim() == 3 && x.scalar_type() == torch::kFloat32 && x.is_contiguous() &&
         (C == 128 || C == 256 || C == 512 || C == 768 || C == 1024);
}

torch::Tensor layer_norm_affine_bf16_reference(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b,
                                               double eps) {
  auto n = at::layer_norm(x.to(torch::kFloat32), {x.size(-1)}, {}, {}, eps);  // [B, L, C]
  auto y = n * w.to(torch::kFloat32).unsqueeze(1);
  if (b.defined()) y = y + b.to(torch::kFloat32).unsqueeze(1);
  return y.to(torch::kBFloat16);
}

torch::Tensor layer_norm_affine_bf16(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b, double eps) {
  const int64_t B = x.size(0), L = x.size(1), C = x.size(2);
  SIMU_CHECK(w.dim() == 2 && w.size(1) == C && (w.size(0) == 1 || w.size(0) == B) && w.scalar_type() == torch::kFloat32,
             "layer_norm_affine_bf16: weight must be [1 or {}, {}] float32, got [{}] {}", B, C, fmt::join(w.sizes(), ", "),
             c10::toString(w.scalar_type()));
  SIMU_CHECK(!b.defined() || b.sizes() == w.sizes(), "layer_norm_affine_bf16: bias must be shaped like the weight");
#ifdef SIMU_HAVE_CUDA_KERNELS
  SIMU_CHECK(supports_layer_norm_affine(x), "layer_norm_affine_bf16: unsupported input [{}] {} on {}",
             fmt::join(x.sizes(), ", "), c10::toString(x.scalar_type()), x.device().str());
  auto wc = w.contiguous();
  auto bc = b.defined() ? b.contiguous() : b;
  auto y = torch::empty({B, L, C}, x.options().dtype(torch::kBFloat16));
  const int64_t rows_per_w = w.size(0) == 1 ? B * L : L;
  ++g_launches;
  check_cuda(kernels::layer_norm_affine_bf16(x.data_ptr<float>(), wc.data_ptr<float>(),
                                             bc.defined() ? bc.data_ptr<float>() : nullptr,
                                             reinterpret_cast<__nv_bfloat16*>(y.data_ptr<at::BFloat16>()), B * L,
                                             std::max<int64_t>(rows_per_w, 1), static_cast<int>(C), static_cast<float>(eps),
                                             c10::cuda::getCurrentCUDAStream(x.device().index()).stream()),
             "layer_norm_affine_bf16");
  return y;
#else
  return layer_norm_affine_bf16_reference(x, w, b, eps);
#endif
}

bool supports_residual_layer_norm_affine(const torch::Tensor& x, const torch::Tensor& h) {
  return supports_layer_norm_affine(x) && h.is_cuda() && h.scalar_type() == torch::kBFloat16 && h.is_contiguous() &&
         h.sizes() == x.sizes();
}

std::pair<torch::Tensor, torch::Tensor> residual_layer_norm_affine_bf16_reference(const torch::Tensor& x,
                                                                                   const torch::Tensor& h,
                                                                                   const torch::Tensor& gate,
                                                                                   const torch::Tensor& w,
                                                                                   const torch::Tensor& b, double eps) {
  auto x_new = gate.defined() ? torch::addcmul(x, h, gate.unsqueeze(1)) : x + h;  // [B, L, C] float32
  return {x_new, layer_norm_affine_bf16_reference(x_new, w, b, eps)};
}

std::pair<torch::Tensor, torch::Tensor> residual_layer_norm_affine_bf16(const torch::Tensor& x, const torch::Tensor& h,
                                                                         const torch::Tensor& gate, const torch::Tensor& w,
                                                                         const torch::Tensor& b, double eps) {
  const int64_t B = x.size(0), L = x.size(1), C = x.size(2);
  SIMU_CHECK(w.dim() == 2 && w.size(1) == C && (w.size(0) == 1 || w.size(0) == B) && w.scalar_type() == torch::kFloat32,
             "residual_layer_norm_affine_bf16: weight must be [1 or {}, {}] float32, got [{}] {}", B, C,
             fmt::join(w.sizes(), ", "), c10::toString(w.scalar_type()));
  SIMU_CHECK(!b.defined() || b.sizes() == w.sizes(), "residual_layer_norm_affine_bf16: bias must be shaped like the weight");
  SIMU_CHECK(!gate.defined() || (gate.dim() == 2 && gate.size(1) == C && (gate.size(0) == 1 || gate.size(0) == B)),
             "residual_layer_norm_affine_bf16: gate must be [1 or {}, {}], got [{}]", B, C, fmt::join(gate.sizes(), ", "));
#ifdef SIMU_HAVE_CUDA_KERNELS
  SIMU_CHECK(supports_residual_layer_norm_affine(x, h),
             "residual_layer_norm_affine_bf16: unsupported inputs x [{}] {}, h [{}] {} on {}", fmt::join(x.sizes(), ", "),
             c10::toString(x.scalar_type()), fmt::join(h.sizes(), ", "), c10::toString(h.scalar_type()), x.device().str());
  auto wc = w.contiguous();
  auto bc = b.defined() ? b.contiguous() : b;
  auto gc = gate.defined() ? gate.to(torch::kFloat32).contiguous() : gate;
  auto x_new = torch::empty_like(x);
  auto y = torch::empty({B, L, C}, x.options().dtype(torch::kBFloat16));
  ++g_launches;
  check_cuda(kernels::residual_layer_norm_affine_bf16(
                 x.data_ptr<float>(), reinterpret_cast<const __nv_bfloat16*>(h.data_ptr<at::BFloat16>()),
                 gc.defined() ? gc.data_ptr<float>() : nullptr, gc.defined() && gc.size(0) == B ? L : B * L,
                 x_new.data_ptr<float>(), wc.data_ptr<float>(), bc.defined() ? bc.data_ptr<float>() : nullptr,
                 reinterpret_cast<__nv_bfloat16*>(y.data_ptr<at::BFloat16>()), B * L,
                 w.size(0) == 1 ? B * L : L, static_cast<int>(C), static_cast<float>(eps),
                 c10::cuda::getCurrentCUDAStream(x.device().index()).stream()),
             "residual_layer_norm_affine_bf16");
  return {x_new, y};
#else
  return residual_layer_norm_affine_bf16_reference(x, h, gate, w, b, eps);
#endif
}

bool supports_split_qkv(const torch::Tensor& qkv) {
  if (!(compiled() && qkv.is_cuda() && qkv.dim() == 5 && qkv.size(2) == 3 && qkv.scalar_type() == torch::kBFloat16 &&
        qkv.is_contiguous()))
    return false;
  const int64_t D = qkv.size(4);
  return D == 64 || D == 128 || D == 256;
}

void split_qkv_rms_norm_reference(const torch::Tensor& qkv, const torch::Tensor& gamma_q, const torch::Tensor& gamma_k,
                                  double scale, torch::Tensor q, torch::Tensor k, torch::Tensor v) {
  auto norm = [&](const torch::Tensor& x, const torch::Tensor& g) {
    auto inv = at::linalg_vector_norm(x, 2, {-1}, true, torch::kFloat32).clamp_min(1e-12).reciprocal();
    return (x * inv * (g.to(torch::kFloat32) * scale)).to(torch::kBFloat16);
  };
  q.copy_(norm(qkv.select(2, 0), gamma_q));
  k.copy_(norm(qkv.select(2, 1), gamma_k));
  v.copy_(qkv.select(2, 2));
}

void split_qkv_rms_norm(const torch::Tensor& qkv, const torch::Tensor& gamma_q, const torch::Tensor& gamma_k, double scale,
                        torch::Tensor q, torch::Tensor k, torch::Tensor v) {
  check_out(q, qkv, "q");
  check_out(k, qkv, "k");
  check_out(v, qkv, "v");
  const int64_t B = qkv.size(0), L = qkv.size(1), H = qkv.size(3), D = qkv.size(4);
  SIMU_CHECK(gamma_q.sizes() == torch::IntArrayRef({H, D}) && gamma_k.sizes() == gamma_q.sizes(),
             "split_qkv_rms_norm: gammas must be [{}, {}]", H, D);
#ifdef SIMU_HAVE_CUDA_KERNELS
  SIMU_CHECK(supports_split_qkv(qkv), "split_qkv_rms_norm: unsupported qkv [{}] {} on {}", fmt::join(qkv.sizes(), ", "),
             c10::toString(qkv.scalar_type()), qkv.device().str());
  auto gq = gamma_q.to(torch::kFloat32).contiguous(), gk = gamma_k.to(torch::kFloat32).contiguous();
  auto out = [](torch::Tensor& t) {
    return kernels::QkvOut{reinterpret_cast<__nv_bfloat16*>(t.data_ptr<at::BFloat16>()), t.stride(0), t.stride(1)};
  };
  ++g_launches;
  check_cuda(kernels::split_qkv_rms_norm(reinterpret_cast<const __nv_bfloat16*>(qkv.data_ptr<at::BFloat16>()),
                                         gq.data_ptr<float>(), gk.data_ptr<float>(), static_cast<float>(scale), out(q),
                                         out(k), out(v), static_cast<int>(B), static_cast<int>(L), static_cast<int>(H),
                                         static_cast<int>(D), c10::cuda::getCurrentCUDAStream(qkv.device().index()).stream()),
             "split_qkv_rms_norm");
#else
  split_qkv_rms_norm_reference(qkv, gamma_q, gamma_k, scale, q, k, v);
#endif
}

bool supports_linear_gelu(const torch::Tensor& x) { return compiled() && x.is_cuda() && x.dim() >= 2; }

torch::Tensor linear_gelu_tanh_bf16_reference(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b) {
  auto y = torch::linear(x.to(torch::kBFloat16), w.to(torch::kBFloat16), b.to(torch::kBFloat16));
  return torch::gelu(y, "tanh");
}

torch::Tensor linear_gelu_tanh_bf16(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b) {
  SIMU_CHECK(supports_linear_gelu(x), "linear_gelu_tanh_bf16: needs a CUDA input of rank >= 2, got [{}] on {}",
             fmt::join(x.sizes(), ", "), x.device().str());
  SIMU_CHECK(w.dim() == 2 && w.size(1) == x.size(-1) && b.dim() == 1 && b.size(0) == w.size(0),
             "linear_gelu_tanh_bf16: weight [{}] / bias [{}] do not fit an input of {} features", fmt::join(w.sizes(), ", "),
             fmt::join(b.sizes(), ", "), x.size(-1));
  // The autocast cache holds the bf16 weight copies for the whole autocast region (as for linear).
  const bool ac = at::autocast::is_autocast_enabled(at::kCUDA);
  auto wb = ac ? at::autocast::cached_cast(at::kBFloat16, w, c10::DeviceType::CUDA) : w.to(torch::kBFloat16);
  auto bb = ac ? at::autocast::cached_cast(at::kBFloat16, b, c10::DeviceType::CUDA) : b.to(torch::kBFloat16);
  auto x2 = x.to(torch::kBFloat16).reshape({-1, x.size(-1)});
  ++g_launches;
  auto y = at::_addmm_activation(bb, x2, wb.t(), 1, 1, /*use_gelu=*/true);  // [rows, N]
  auto shape = x.sizes().vec();
  shape.back() = w.size(0);
  return y.view(shape);
}

}  // namespace simu::models::fused
