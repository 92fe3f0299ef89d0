#include "models/fused_ops.h"

#include <fmt/ranges.h>

#include <atomic>

#include "common/error.h"

#include <ATen/autocast_mode.h>
#include <torch/autograd.h>

#ifdef SIMU_HAVE_CUDA_KERNELS
#include <c10/cuda/CUDAStream.h>

#include "models/fused_kernels.h"
#endif

namespace simu::models::fused {

namespace {

std::atomic<int64_t> g_launches{0};
std::atomic<int64_t> g_modulation_launches{0};
std::atomic<bool> g_split_wide{true};
std::atomic<int64_t> g_split_wide_launches{0};

#ifdef SIMU_HAVE_CUDA_KERNELS
void check_cuda(cudaError_t e, const char* what) {
  SIMU_CHECK(e == cudaSuccess, "fused kernel {}: {}", what, cudaGetErrorString(e));
}

// Calls f(T{}) with T the kernels' storage type of dtype (bf16 or fp16).
template <typename F>
void by_dtype(torch::ScalarType dtype, F&& f) {
  if (dtype == torch::kHalf) f(__half{});
  else f(__nv_bfloat16{});
}
template <typename T>
T* ptr(const torch::Tensor& t) {
  return reinterpret_cast<T*>(t.data_ptr());
}
#endif

void check_low(torch::ScalarType dtype, const char* what) {
  SIMU_CHECK(is_low_precision(dtype), "{}: the output dtype must be bfloat16 or float16, got {}", what, c10::toString(dtype));
}

// [B, L, H, D] output view with the last two dims contiguous: (batch stride, token stride) in elements.
void check_out(const torch::Tensor& o, const torch::Tensor& qkv, const char* name) {
  SIMU_CHECK(o.dim() == 4 && o.size(0) == qkv.size(0) && o.size(1) == qkv.size(1) && o.size(2) == qkv.size(3) &&
                 o.size(3) == qkv.size(4),
             "split_qkv_rms_norm: {} must be [{}, {}, {}, {}], got [{}]", name, qkv.size(0), qkv.size(1), qkv.size(3),
             qkv.size(4), fmt::join(o.sizes(), ", "));
  SIMU_CHECK(o.scalar_type() == qkv.scalar_type() && o.stride(3) == 1 && o.stride(2) == o.size(3) && o.device() == qkv.device(),
             "split_qkv_rms_norm: {} must be a {} view (qkv's dtype) on {} with contiguous heads", name,
             c10::toString(qkv.scalar_type()), qkv.device().str());
  // The 4-byte kernel stores pairs of values: 4-byte aligned rows (the 16-byte one wants more, else this one runs).
  SIMU_CHECK(reinterpret_cast<uintptr_t>(o.data_ptr()) % 4 == 0 && o.stride(0) % 2 == 0 && o.stride(1) % 2 == 0,
             "split_qkv_rms_norm: {} must start 4-byte aligned with even batch/token strides, got strides [{}]", name,
             fmt::join(o.strides(), ", "));
}

// A gamma as the split kernels read it: fp32, contiguous and 16-byte aligned (the 16-byte kernels read it as
// float4; a view starting elsewhere is copied: 4 KB at the real size).
[[maybe_unused]] torch::Tensor gamma_f32(const torch::Tensor& g) {
  auto t = g.to(torch::kFloat32).contiguous();
  return reinterpret_cast<uintptr_t>(t.data_ptr()) % 16 == 0 ? t : t.clone();
}

}  // namespace

int64_t launch_count() { return g_launches.load(); }
int64_t modulation_launch_count() { return g_modulation_launches.load(); }
void set_split_qkv_wide(bool on) { g_split_wide = on; }
bool split_qkv_wide() { return g_split_wide.load(); }
int64_t split_qkv_wide_launch_count() { return g_split_wide_launches.load(); }

bool is_low_precision(torch::ScalarType dtype) { return dtype == torch::kBFloat16 || dtype == torch::kHalf; }

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
                                               double eps, torch::ScalarType out) {
  check_low(out, "layer_norm_affine reference");
  auto n = at::layer_norm(x.to(torch::kFloat32), {x.size(-1)}, {}, {}, eps);  // [B, L, C]
  auto y = n * w.to(torch::kFloat32).unsqueeze(1);
  if (b.defined()) y = y + b.to(torch::kFloat32).unsqueeze(1);
  return y.to(out);
}

namespace {
// The forward kernel of layer_norm_affine_bf16 (no autograd).
torch::Tensor layer_norm_affine_launch(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b, double eps,
                                       torch::ScalarType out) {
  check_low(out, "layer_norm_affine_bf16");
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
  auto y = torch::empty({B, L, C}, x.options().dtype(out));
  const int64_t rows_per_w = w.size(0) == 1 ? B * L : L;
  ++g_launches;
  by_dtype(out, [&](auto t) {
    using T = decltype(t);
    check_cuda(kernels::layer_norm_affine<T>(x.data_ptr<float>(), wc.data_ptr<float>(),
                                             bc.defined() ? bc.data_ptr<float>() : nullptr, ptr<T>(y), B * L,
                                             std::max<int64_t>(rows_per_w, 1), static_cast<int>(C), static_cast<float>(eps),
                                             c10::cuda::getCurrentCUDAStream(x.device().index()).stream()),
               "layer_norm_affine");
  });
  return y;
#else
  return layer_norm_affine_bf16_reference(x, w, b, eps, out);
#endif
}

#ifdef SIMU_HAVE_CUDA_KERNELS
// dx of LN(x) * w (+ b) given gy (undefined: 0), plus gx_in (undefined: 0); with_dh: also
// dh = dx * gate as `low` (the residual's sublayer gradient; gy is read as `low` too). x: [B, L, C] fp32;
// w, gate: [1 or B, C] fp32.
std::pair<torch::Tensor, torch::Tensor> layer_norm_affine_backward_launch(const torch::Tensor& x, const torch::Tensor& w,
                                                                          const torch::Tensor& gy, const torch::Tensor& gx_in,
                                                                          const torch::Tensor& gate, bool with_dh, double eps,
                                                                          torch::ScalarType low) {
  const int64_t B = x.size(0), L = x.size(1), C = x.size(2);
  auto gyc = gy.defined() ? gy.to(low).contiguous() : gy;
  auto gxc = gx_in.defined() ? gx_in.to(torch::kFloat32).contiguous() : gx_in;
  auto dx = torch::empty_like(x);
  auto dh = with_dh ? torch::empty({B, L, C}, x.options().dtype(low)) : torch::Tensor();
  ++g_launches;
  by_dtype(low, [&](auto t) {
    using T = decltype(t);
    check_cuda(kernels::layer_norm_affine_backward<T>(
                   x.data_ptr<float>(), w.data_ptr<float>(), w.size(0) == 1 ? B * L : L,
                   gyc.defined() ? ptr<const T>(gyc) : nullptr, gxc.defined() ? gxc.data_ptr<float>() : nullptr,
                   gate.defined() ? gate.data_ptr<float>() : nullptr, gate.defined() && gate.size(0) == B ? L : B * L,
                   dx.data_ptr<float>(), with_dh ? ptr<T>(dh) : nullptr, B * L, static_cast<int>(C),
                   static_cast<float>(eps), c10::cuda::getCurrentCUDAStream(x.device().index()).stream()),
               "layer_norm_affine_backward");
  });
  return {dx, dh};
}

// Autograd node of layer_norm_affine_bf16: gradient for x only (w, b are frozen).
struct LayerNormAffineFn : public torch::autograd::Function<LayerNormAffineFn> {
  static torch::Tensor forward(torch::autograd::AutogradContext* ctx, const torch::Tensor& x, const torch::Tensor& w,
                               const torch::Tensor& b, double eps, int64_t out) {
    auto wc = w.contiguous();
    ctx->save_for_backward({x, wc});
    ctx->saved_data["eps"] = eps;
    ctx->saved_data["dtype"] = out;
    return layer_norm_affine_launch(x, wc, b, eps, static_cast<torch::ScalarType>(out));
  }
  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 torch::autograd::variable_list grad) {
    const auto saved = ctx->get_saved_variables();
    auto dx = layer_norm_affine_backward_launch(saved[0], saved[1], grad[0], {}, {}, false, ctx->saved_data["eps"].toDouble(),
                                                static_cast<torch::ScalarType>(ctx->saved_data["dtype"].toInt()))
                  .first;
    return {dx, torch::Tensor(), torch::Tensor(), torch::Tensor(), torch::Tensor()};
  }
};
#endif

// True when grad mode records a graph through one of the tensors (one requires a gradient). Asked of
// the activations (take the autograd node) and of the frozen-by-contract weights (the fused backward
// gives them no gradient: take the reference).
bool graph_through(std::initializer_list<torch::Tensor> tensors) {
  if (!at::GradMode::is_enabled()) return false;
  for (const auto& t : tensors)
    if (t.defined() && t.requires_grad()) return true;
  return false;
}
}  // namespace

torch::Tensor layer_norm_affine_bf16(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b, double eps,
                                     torch::ScalarType out) {
  if (graph_through({w, b})) return layer_norm_affine_bf16_reference(x, w, b, eps, out);
#ifdef SIMU_HAVE_CUDA_KERNELS
  // (Autograd functions take defined tensors only: a missing bias is a zero one, the same sums.)
  if (graph_through({x}))
    return LayerNormAffineFn::apply(x, w, b.defined() ? b : torch::zeros_like(w), eps, static_cast<int64_t>(out));
#endif
  return layer_norm_affine_launch(x, w, b, eps, out);
}

torch::ScalarType residual_output_dtype(const torch::Tensor& h) {
  return h.scalar_type() == torch::kHalf ? torch::kHalf : torch::kBFloat16;
}

bool supports_residual_layer_norm_affine(const torch::Tensor& x, const torch::Tensor& h) {
  return supports_layer_norm_affine(x) && h.is_cuda() && is_low_precision(h.scalar_type()) && h.is_contiguous() &&
         h.sizes() == x.sizes();
}

std::pair<torch::Tensor, torch::Tensor> residual_layer_norm_affine_bf16_reference(const torch::Tensor& x,
                                                                                   const torch::Tensor& h,
                                                                                   const torch::Tensor& gate,
                                                                                   const torch::Tensor& w,
                                                                                   const torch::Tensor& b, double eps) {
  auto x_new = gate.defined() ? torch::addcmul(x, h, gate.unsqueeze(1)) : x + h;  // [B, L, C] float32
  return {x_new, layer_norm_affine_bf16_reference(x_new, w, b, eps, residual_output_dtype(h))};
}

bool supports_residual_layer_norm_affine_tail(const torch::Tensor& x, const torch::Tensor& head, const torch::Tensor& tail) {
  return supports_layer_norm_affine(x) && head.is_cuda() && is_low_precision(head.scalar_type()) && head.is_contiguous() &&
         head.dim() == 3 && head.size(0) <= x.size(0) && head.size(1) == x.size(1) && head.size(2) == x.size(2) &&
         tail.defined() && tail.is_cuda() && tail.scalar_type() == head.scalar_type() && tail.is_contiguous() &&
         tail.numel() == x.size(2) && reinterpret_cast<uintptr_t>(tail.data_ptr()) % 16 == 0;
}

namespace {
// The forward kernel of residual_layer_norm_affine_bf16 (no autograd); with `tail`, h holds only the
// leading rows and the others read tail (residual_layer_norm_affine_tail_bf16).
std::pair<torch::Tensor, torch::Tensor> residual_layer_norm_affine_launch(const torch::Tensor& x, const torch::Tensor& h,
                                                                          const torch::Tensor& gate, const torch::Tensor& w,
                                                                          const torch::Tensor& b, double eps,
                                                                          const torch::Tensor& tail = torch::Tensor()) {
  const int64_t B = x.size(0), L = x.size(1), C = x.size(2);
  SIMU_CHECK(w.dim() == 2 && w.size(1) == C && (w.size(0) == 1 || w.size(0) == B) && w.scalar_type() == torch::kFloat32,
             "residual_layer_norm_affine_bf16: weight must be [1 or {}, {}] float32, got [{}] {}", B, C,
             fmt::join(w.sizes(), ", "), c10::toString(w.scalar_type()));
  SIMU_CHECK(!b.defined() || b.sizes() == w.sizes(), "residual_layer_norm_affine_bf16: bias must be shaped like the weight");
  SIMU_CHECK(!gate.defined() || (gate.dim() == 2 && gate.size(1) == C && (gate.size(0) == 1 || gate.size(0) == B)),
             "residual_layer_norm_affine_bf16: gate must be [1 or {}, {}], got [{}]", B, C, fmt::join(gate.sizes(), ", "));
#ifdef SIMU_HAVE_CUDA_KERNELS
  SIMU_CHECK(tail.defined() ? supports_residual_layer_norm_affine_tail(x, h, tail) : supports_residual_layer_norm_affine(x, h),
             "residual_layer_norm_affine_bf16: unsupported inputs x [{}] {}, h [{}] {}{} on {}", fmt::join(x.sizes(), ", "),
             c10::toString(x.scalar_type()), fmt::join(h.sizes(), ", "), c10::toString(h.scalar_type()),
             tail.defined() ? fmt::format(", tail [{}] {}", fmt::join(tail.sizes(), ", "), c10::toString(tail.scalar_type())) : "",
             x.device().str());
  auto wc = w.contiguous();
  auto bc = b.defined() ? b.contiguous() : b;
  auto gc = gate.defined() ? gate.to(torch::kFloat32).contiguous() : gate;
  auto x_new = torch::empty_like(x);
  auto y = torch::empty({B, L, C}, x.options().dtype(h.scalar_type()));
  ++g_launches;
  by_dtype(h.scalar_type(), [&](auto t) {
    using T = decltype(t);
    check_cuda(kernels::residual_layer_norm_affine<T>(
                   x.data_ptr<float>(), ptr<const T>(h), tail.defined() ? h.size(0) * L : B * L,
                   tail.defined() ? ptr<const T>(tail) : nullptr, gc.defined() ? gc.data_ptr<float>() : nullptr,
                   gc.defined() && gc.size(0) == B ? L : B * L, x_new.data_ptr<float>(), wc.data_ptr<float>(),
                   bc.defined() ? bc.data_ptr<float>() : nullptr, ptr<T>(y), B * L, w.size(0) == 1 ? B * L : L,
                   static_cast<int>(C), static_cast<float>(eps), c10::cuda::getCurrentCUDAStream(x.device().index()).stream()),
               "residual_layer_norm_affine");
  });
  return {x_new, y};
#else
  SIMU_CHECK(!tail.defined(), "residual_layer_norm_affine_tail_bf16: needs the CUDA kernels");
  return residual_layer_norm_affine_bf16_reference(x, h, gate, w, b, eps);
#endif
}

#ifdef SIMU_HAVE_CUDA_KERNELS
// Autograd node of residual_layer_norm_affine_bf16: gradients for x and h (gate, w, b are frozen).
//   d x = g_xnew + LN'(x_new)^T (g_y * w),  d h = d x * gate.
struct ResidualLayerNormAffineFn : public torch::autograd::Function<ResidualLayerNormAffineFn> {
  static torch::autograd::variable_list forward(torch::autograd::AutogradContext* ctx, const torch::Tensor& x,
                                                const torch::Tensor& h, const torch::Tensor& gate, const torch::Tensor& w,
                                                const torch::Tensor& b, double eps) {
    auto wc = w.contiguous();
    auto gc = gate.defined() ? gate.to(torch::kFloat32).contiguous() : gate;
    auto [x_new, y] = residual_layer_norm_affine_launch(x, h, gc, wc, b, eps);
    ctx->save_for_backward({x_new, wc, gc});
    ctx->saved_data["eps"] = eps;
    ctx->saved_data["dtype"] = static_cast<int64_t>(h.scalar_type());
    return {x_new, y};
  }
  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 torch::autograd::variable_list grad) {
    const auto saved = ctx->get_saved_variables();
    auto [dx, dh] = layer_norm_affine_backward_launch(saved[0], saved[1], grad[1], grad[0], saved[2], true,
                                                      ctx->saved_data["eps"].toDouble(),
                                                      static_cast<torch::ScalarType>(ctx->saved_data["dtype"].toInt()));
    return {dx, dh, torch::Tensor(), torch::Tensor(), torch::Tensor(), torch::Tensor()};
  }
};
#endif
}  // namespace

std::pair<torch::Tensor, torch::Tensor> residual_layer_norm_affine_bf16(const torch::Tensor& x, const torch::Tensor& h,
                                                                         const torch::Tensor& gate, const torch::Tensor& w,
                                                                         const torch::Tensor& b, double eps) {
  if (graph_through({gate, w, b})) return residual_layer_norm_affine_bf16_reference(x, h, gate, w, b, eps);
#ifdef SIMU_HAVE_CUDA_KERNELS
  if (graph_through({x, h})) {
    // (Autograd functions take defined tensors only: a missing gate is a gate of ones, x + h * 1 = x + h
    // exactly, and a missing bias a zero one.)
    auto out = ResidualLayerNormAffineFn::apply(x, h, gate.defined() ? gate : torch::ones({1, x.size(2)}, x.options()), w,
                                                b.defined() ? b : torch::zeros_like(w), eps);
    return {out[0], out[1]};
  }
#endif
  return residual_layer_norm_affine_launch(x, h, gate, w, b, eps);
}

std::pair<torch::Tensor, torch::Tensor> residual_layer_norm_affine_tail_bf16(const torch::Tensor& x, const torch::Tensor& head,
                                                                              const torch::Tensor& tail, const torch::Tensor& gate,
                                                                              const torch::Tensor& w, const torch::Tensor& b,
                                                                              double eps) {
  SIMU_CHECK(!graph_through({x, head, tail, gate, w, b}),
             "residual_layer_norm_affine_tail_bf16: inference only (no gradient), but an input requires one");
  return residual_layer_norm_affine_launch(x, head, gate, w, b, eps, tail);
}

torch::Tensor multi_head_rms_norm_reference(const torch::Tensor& x, const torch::Tensor& gamma, double scale) {
  auto inv = at::linalg_vector_norm(x, 2, {-1}, /*keepdim=*/true, torch::kFloat32).clamp_min(1e-12).reciprocal();
  auto y = x * inv;  // [..., H, D] float32
  y.mul_(gamma.to(torch::kFloat32) * scale);
  return y.to(x.scalar_type());
}

bool supports_split_qkv(const torch::Tensor& qkv) {
  if (!(compiled() && qkv.is_cuda() && qkv.dim() == 5 && qkv.size(2) == 3 && is_low_precision(qkv.scalar_type()) &&
        qkv.is_contiguous()))
    return false;
  const int64_t D = qkv.size(4);
  return D == 64 || D == 128 || D == 256;
}

void split_qkv_rms_norm_reference(const torch::Tensor& qkv, const torch::Tensor& gamma_q, const torch::Tensor& gamma_k,
                                  double scale, torch::Tensor q, torch::Tensor k, torch::Tensor v) {
  q.copy_(multi_head_rms_norm_reference(qkv.select(2, 0), gamma_q, scale));
  k.copy_(multi_head_rms_norm_reference(qkv.select(2, 1), gamma_k, scale));
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
  auto gq = gamma_f32(gamma_q), gk = gamma_f32(gamma_k);
  auto out = [](torch::Tensor& t) { return kernels::QkvOut{t.data_ptr(), t.stride(0), t.stride(1)}; };
  // The 16-byte kernel where everything is aligned for it (and it is not switched off), else the 4-byte one.
  const bool wide = g_split_wide && kernels::split_qkv_wide_ok(qkv.data_ptr(), gq.data_ptr<float>(), gk.data_ptr<float>(),
                                                                out(q), out(k), out(v));
  ++g_launches;
  if (wide) ++g_split_wide_launches;
  by_dtype(qkv.scalar_type(), [&](auto t) {
    using T = decltype(t);
    check_cuda(kernels::split_qkv_rms_norm<T>(ptr<const T>(qkv), gq.data_ptr<float>(), gk.data_ptr<float>(),
                                              static_cast<float>(scale), out(q), out(k), out(v), static_cast<int>(B),
                                              static_cast<int>(L), static_cast<int>(H), static_cast<int>(D), wide,
                                              c10::cuda::getCurrentCUDAStream(qkv.device().index()).stream()),
               "split_qkv_rms_norm");
  });
#else
  split_qkv_rms_norm_reference(qkv, gamma_q, gamma_k, scale, q, k, v);
#endif
}

torch::Tensor split_qkv_rms_norm_backward(const torch::Tensor& qkv, const torch::Tensor& gamma_q, const torch::Tensor& gamma_k,
                                          double scale, const torch::Tensor& dq, const torch::Tensor& dk,
                                          const torch::Tensor& dv) {
  const int64_t B = qkv.size(0), L = qkv.size(1), H = qkv.size(3), D = qkv.size(4);
  SIMU_CHECK(supports_split_qkv(qkv), "split_qkv_rms_norm_backward: unsupported qkv [{}] {} on {}",
             fmt::join(qkv.sizes(), ", "), c10::toString(qkv.scalar_type()), qkv.device().str());
  SIMU_CHECK(gamma_q.sizes() == torch::IntArrayRef({H, D}) && gamma_k.sizes() == gamma_q.sizes(),
             "split_qkv_rms_norm_backward: gammas must be [{}, {}]", H, D);
#ifdef SIMU_HAVE_CUDA_KERNELS
  auto gq = gamma_f32(gamma_q), gk = gamma_f32(gamma_k);
  // Incoming gradients as strided views in qkv's dtype with contiguous channels and 4-byte aligned rows
  // (what the 4-byte kernel needs; copied contiguous otherwise).
  std::vector<torch::Tensor> keep;
  auto view = [&](const torch::Tensor& g, const char* name) {
    if (!g.defined()) return kernels::QkvGrad{nullptr, 0, 0, 0};
    SIMU_CHECK(g.dim() == 4 && g.size(0) == B && g.size(1) == L && g.size(2) == H && g.size(3) == D,
               "split_qkv_rms_norm_backward: {} must be [{}, {}, {}, {}], got [{}]", name, B, L, H, D,
               fmt::join(g.sizes(), ", "));
    auto t = g.to(qkv.device(), qkv.scalar_type());
    const bool ok = t.stride(3) == 1 && t.stride(0) % 2 == 0 && t.stride(1) % 2 == 0 && t.stride(2) % 2 == 0 &&
                    reinterpret_cast<uintptr_t>(t.data_ptr()) % 4 == 0;
    if (!ok) t = t.contiguous();
    keep.push_back(t);
    return kernels::QkvGrad{t.data_ptr(), t.stride(0), t.stride(1), t.stride(2)};
  };
  const auto gdq = view(dq, "dq"), gdk = view(dk, "dk"), gdv = view(dv, "dv");
  auto dqkv = torch::empty_like(qkv);
  const bool wide = g_split_wide && kernels::split_qkv_backward_wide_ok(qkv.data_ptr(), gq.data_ptr<float>(),
                                                                         gk.data_ptr<float>(), gdq, gdk, gdv, dqkv.data_ptr());
  ++g_launches;
  if (wide) ++g_split_wide_launches;
  by_dtype(qkv.scalar_type(), [&](auto tag) {
    using T = decltype(tag);
    check_cuda(kernels::split_qkv_rms_norm_backward<T>(
                   ptr<const T>(qkv), gq.data_ptr<float>(), gk.data_ptr<float>(), static_cast<float>(scale), gdq, gdk, gdv,
                   ptr<T>(dqkv), static_cast<int>(B), static_cast<int>(L), static_cast<int>(H), static_cast<int>(D), wide,
                   c10::cuda::getCurrentCUDAStream(qkv.device().index()).stream()),
               "split_qkv_rms_norm_backward");
  });
  return dqkv;
#else
  simu::fail("split_qkv_rms_norm_backward: built without the CUDA kernels");
#endif
}

namespace {
// split_qkv_rms_norm into new contiguous q, k, v [B, L, H, D].
std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> split_into_new(const torch::Tensor& qkv, const torch::Tensor& gamma_q,
                                                                      const torch::Tensor& gamma_k, double scale) {
  auto q = torch::empty({qkv.size(0), qkv.size(1), qkv.size(3), qkv.size(4)}, qkv.options());
  auto k = torch::empty_like(q), v = torch::empty_like(q);
  split_qkv_rms_norm(qkv, gamma_q, gamma_k, scale, q, k, v);
  return {q, k, v};
}

#ifdef SIMU_HAVE_CUDA_KERNELS
// Autograd node of split_qkv_rms_norm_autograd: the gradient of qkv (the gammas are frozen).
struct SplitQkvRmsNormFn : public torch::autograd::Function<SplitQkvRmsNormFn> {
  static torch::autograd::variable_list forward(torch::autograd::AutogradContext* ctx, const torch::Tensor& qkv,
                                                const torch::Tensor& gamma_q, const torch::Tensor& gamma_k, double scale) {
    auto [q, k, v] = split_into_new(qkv, gamma_q, gamma_k, scale);
    ctx->set_materialize_grads(false);  // an output without a gradient reaches backward undefined: not read
    ctx->save_for_backward({qkv, gamma_f32(gamma_q), gamma_f32(gamma_k)});
    ctx->saved_data["scale"] = scale;
    return {q, k, v};
  }
  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 torch::autograd::variable_list grad) {
    const auto saved = ctx->get_saved_variables();
    auto dqkv = split_qkv_rms_norm_backward(saved[0], saved[1], saved[2], ctx->saved_data["scale"].toDouble(), grad[0],
                                            grad[1], grad[2]);
    return {dqkv, torch::Tensor(), torch::Tensor(), torch::Tensor()};
  }
};
#endif
}  // namespace

std::tuple<torch::Tensor, torch::Tensor, torch::Tensor> split_qkv_rms_norm_autograd(const torch::Tensor& qkv,
                                                                                   const torch::Tensor& gamma_q,
                                                                                   const torch::Tensor& gamma_k,
                                                                                   double scale) {
  // Reference (differentiable through ATen) when the gammas want gradients or there are no kernels.
  if (graph_through({gamma_q, gamma_k}) || !compiled())
    return {multi_head_rms_norm_reference(qkv.select(2, 0), gamma_q, scale),
            multi_head_rms_norm_reference(qkv.select(2, 1), gamma_k, scale), qkv.select(2, 2)};
#ifdef SIMU_HAVE_CUDA_KERNELS
  if (graph_through({qkv})) {
    auto out = SplitQkvRmsNormFn::apply(qkv, gamma_q, gamma_k, scale);
    return {out[0], out[1], out[2]};
  }
#endif
  return split_into_new(qkv, gamma_q, gamma_k, scale);
}

bool supports_modulation_rows(const torch::Tensor& m) {
  const auto dt = m.scalar_type();
  return compiled() && m.is_cuda() && m.dim() == 2 && m.size(1) % 6 == 0 && m.is_contiguous() &&
         (is_low_precision(dt) || dt == torch::kFloat32);
}

torch::Tensor modulation_rows_reference(const torch::Tensor& m) {
  SIMU_CHECK(m.dim() == 2 && m.size(1) % 6 == 0, "modulation_rows: m must be [G, 6C], got [{}]", fmt::join(m.sizes(), ", "));
  auto chunks = m.chunk(6, 1);  // [G, C] each
  std::vector<torch::Tensor> rows;
  for (size_t k = 0; k < chunks.size(); ++k)
    rows.push_back((k == 1 || k == 4 ? 1 + chunks[k] : chunks[k]).to(torch::kFloat32));
  return torch::stack(rows);  // [6, G, C]
}

torch::Tensor modulation_rows(const torch::Tensor& m) {
  if (graph_through({m}) || !supports_modulation_rows(m)) return modulation_rows_reference(m);
#ifdef SIMU_HAVE_CUDA_KERNELS
  const int64_t G = m.size(0), C = m.size(1) / 6;
  auto out = torch::empty({6, G, C}, m.options().dtype(torch::kFloat32));
  const auto stream = c10::cuda::getCurrentCUDAStream(m.device().index()).stream();
  ++g_modulation_launches;
  if (m.scalar_type() == torch::kFloat32) {
    check_cuda(kernels::modulation_rows<float>(m.data_ptr<float>(), out.data_ptr<float>(), G, C, stream), "modulation_rows");
  } else {
    by_dtype(m.scalar_type(), [&](auto t) {
      using T = decltype(t);
      check_cuda(kernels::modulation_rows<T>(ptr<const T>(m), out.data_ptr<float>(), G, C, stream), "modulation_rows");
    });
  }
  return out;
#else
  return modulation_rows_reference(m);
#endif
}

bool supports_linear_gelu(const torch::Tensor& x) { return compiled() && x.is_cuda() && x.dim() >= 2; }

torch::ScalarType linear_gelu_dtype(const torch::Tensor& x) {
  if (x.is_cuda() && at::autocast::is_autocast_enabled(at::kCUDA)) {
    const auto d = at::autocast::get_autocast_dtype(at::kCUDA);
    if (is_low_precision(d)) return d;
  }
  return x.scalar_type() == torch::kHalf ? torch::kHalf : torch::kBFloat16;
}

torch::Tensor linear_gelu_tanh_bf16_reference(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b) {
  const auto lp = linear_gelu_dtype(x);
  auto y = torch::linear(x.to(lp), w.to(lp), b.to(lp));
  return torch::gelu(y, "tanh");
}

torch::Tensor linear_gelu_tanh_bf16(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b) {
  SIMU_CHECK(supports_linear_gelu(x), "linear_gelu_tanh_bf16: needs a CUDA input of rank >= 2, got [{}] on {}",
             fmt::join(x.sizes(), ", "), x.device().str());
  SIMU_CHECK(w.dim() == 2 && w.size(1) == x.size(-1) && b.dim() == 1 && b.size(0) == w.size(0),
             "linear_gelu_tanh_bf16: weight [{}] / bias [{}] do not fit an input of {} features", fmt::join(w.sizes(), ", "),
             fmt::join(b.sizes(), ", "), x.size(-1));
  // The autocast cache holds the 16-bit weight copies for the whole autocast region (as for linear).
  const auto lp = linear_gelu_dtype(x);
  const bool ac = at::autocast::is_autocast_enabled(at::kCUDA) && at::autocast::get_autocast_dtype(at::kCUDA) == lp;
  auto wb = ac ? at::autocast::cached_cast(lp, w, c10::DeviceType::CUDA) : w.to(lp);
  auto bb = ac ? at::autocast::cached_cast(lp, b, c10::DeviceType::CUDA) : b.to(lp);
  auto x2 = x.to(lp).reshape({-1, x.size(-1)});
  ++g_launches;
  auto y = at::_addmm_activation(bb, x2, wb.t(), 1, 1, /*use_gelu=*/true);  // [rows, N]
  auto shape = x.sizes().vec();
  shape.back() = w.size(0);
  return y.view(shape);
}

}  // namespace simu::models::fused
