// A LoRA-wrapped Linear with a frozen base as one autograd node under autocast (lora.h:
// LoraAdapter::forward_with_base). Same products as the unfused path (Linear + add_to); what it saves
// is memory traffic: the adapter's up-projection accumulates into the base output in place (no copy of
// y), and the backward accumulates both input-gradient products into one buffer (no separate sum).
#include <ATen/autocast_mode.h>
#include <torch/autograd.h>

#include "common/error.h"
#include "lora/lora.h"

namespace simu::lora {

namespace {

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

// y = x W^T + b + scale (x A^T) B^T in the autocast dtype; W and b frozen, A and B fp32 parameters.
struct LoraLinearFn : public torch::autograd::Function<LoraLinearFn> {
  // x: [..., in], w: [out, in], b: [out] or undefined, a_w: [r, in], b_w: [out, r] -> [..., out]
  static torch::Tensor forward(AutogradContext* ctx, const torch::Tensor& x, const torch::Tensor& w,
                               const torch::Tensor& b, const torch::Tensor& a_w, const torch::Tensor& b_w, double scale,
                               at::ScalarType dt) {
    const int64_t in = w.size(1), out = w.size(0);
    auto x2 = x.to(dt).reshape({-1, in});  // [M, in]
    auto wl = w.to(dt), al = a_w.to(dt), bl = b_w.to(dt);
    auto y2 = b.defined() ? at::addmm(b.to(dt), x2, wl.t()) : at::mm(x2, wl.t());  // [M, out]
    auto a2 = at::mm(x2, al.t());                                                    // [M, r]
    y2.addmm_(a2, bl.t(), /*beta=*/1, /*alpha=*/scale);
    ctx->save_for_backward({x2, wl, al, bl, a2});
    ctx->saved_data["scale"] = scale;
    ctx->saved_data["x_dtype"] = static_cast<int64_t>(x.scalar_type());
    ctx->saved_data["x_sizes"] = x.sizes().vec();
    auto sizes = x.sizes().vec();
    sizes.back() = out;
    return y2.view(sizes);
  }

  static variable_list backward(AutogradContext* ctx, variable_list grads) {
    const auto saved = ctx->get_saved_variables();
    const auto &x2 = saved[0], &wl = saved[1], &al = saved[2], &bl = saved[3], &a2 = saved[4];
    const double scale = ctx->saved_data["scale"].toDouble();
    auto dy2 = grads[0].reshape({-1, wl.size(0)}).to(wl.scalar_type());  // [M, out]
    auto g = at::mm(dy2, bl);                                          // [M, r]: dy B
    torch::Tensor dx;
    if (ctx->needs_input_grad(0)) {
      // dx = dy W + scale (dy B) A, the second product accumulating into the first.
      auto dx2 = at::mm(dy2, wl);  // [M, in]
      dx2.addmm_(g, al, /*beta=*/1, /*alpha=*/scale);
      const auto x_dtype = static_cast<at::ScalarType>(ctx->saved_data["x_dtype"].toInt());
      dx = dx2.view(ctx->saved_data["x_sizes"].toIntVector()).to(x_dtype);
    }
    // dA = scale (dy B)^T x, dB = scale dy^T (x A^T); fp32 like the parameters. The scale rides in the
    // product's alpha (beta 0: nothing is read from the first operand), one kernel fewer per gradient than
    // a separate multiply; for a power-of-two scale (alpha / r = 2 in the recipes) the bits are the same.
    auto scaled_product = [scale](const torch::Tensor& l, const torch::Tensor& r) {
      auto out = torch::empty({l.size(0), r.size(1)}, l.options());
      return at::addmm_out(out, out, l, r, /*beta=*/0, /*alpha=*/scale).to(torch::kFloat32);
    };
    auto d_a = ctx->needs_input_grad(3) ? scaled_product(g.t(), x2) : torch::Tensor();
    auto d_b = ctx->needs_input_grad(4) ? scaled_product(dy2.t(), a2) : torch::Tensor();
    return {dx, torch::Tensor(), torch::Tensor(), d_a, d_b, torch::Tensor(), torch::Tensor()};
  }
};

}  // namespace

torch::Tensor LoraAdapter::forward_with_base(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b) {
  const auto dev = x.device().type();
  // Only the case it was made for: autocast on, a frozen base, no dropout at work; else the caller's path.
  if (!fused_base || !at::autocast::is_autocast_enabled(dev) || w.requires_grad() || (b.defined() && b.requires_grad()) ||
      (dropout > 0 && A->is_training()))
    return {};
  // The node casts its operands to the autocast dtype itself (autocast's own casts would be no-ops).
  return LoraLinearFn::apply(x, w, b, A->weight, B->weight, scale, at::autocast::get_autocast_dtype(dev));
}

}  // namespace simu::lora
