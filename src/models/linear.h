// Linear layer of the Stage-1 model with an optional adapter hook (LoRA lives in src/lora).
//
// Official checkpoints name the parameters `<path>.weight` / `<path>.bias`, exactly like
// torch.nn.Linear, so state dicts line up. An adapter adds a term to the output:
//   y = x W^T + b + adapter(x)   (when an adapter is set and enabled)
// Opt-in: an FP8 copy of the frozen weight (fp8_linear.h) computes x W^T + b instead of torch::linear
// when one is set (set_fp8_weight); without one the layer is exactly torch::linear.
#pragma once

#include <torch/torch.h>

#include <memory>

#include "models/fp8_linear.h"

namespace simu::models {

// Something that adds to a Linear's output given its input; src/lora implements it.
class LinearAdapter {
 public:
  virtual ~LinearAdapter() = default;
  // x: [..., in_features] -> [..., out_features]
  virtual torch::Tensor delta(const torch::Tensor& x) = 0;
  // y + delta(x), y: the Linear's output [..., out]. An adapter may fuse the sum into its last product.
  virtual torch::Tensor add_to(const torch::Tensor& y, const torch::Tensor& x) { return y + delta(x); }
  // The whole layer, x W^T + b + delta(x), where the adapter can compute it as one fused step (w, b:
  // the weights the Linear would use); undefined when it cannot: the Linear then computes x W^T + b
  // and calls add_to.
  virtual torch::Tensor forward_with_base(const torch::Tensor& /*x*/, const torch::Tensor& /*w*/,
                                          const torch::Tensor& /*b*/) {
    return {};
  }
};

class LinearImpl : public torch::nn::Module {
 public:
  LinearImpl(int64_t in_features, int64_t out_features, bool with_bias = true);
  // x: [..., in] -> [..., out]
  torch::Tensor forward(const torch::Tensor& x);

  // Installs (or, with nullptr, removes) the adapter; its parameters are registered by the caller.
  void set_adapter(std::shared_ptr<LinearAdapter> adapter) { adapter_ = std::move(adapter); }
  const std::shared_ptr<LinearAdapter>& adapter() const { return adapter_; }
  // Switches the adapter term on or off without removing it (reference model = adapters off).
  void set_adapter_enabled(bool enabled) { adapter_enabled_ = enabled; }
  bool adapter_enabled() const { return adapter_enabled_; }
  // Installs (or, with nullptr, frees) the FP8 copy of weight/bias used by forward. The copy is not
  // updated when weight changes: the caller sets it for a frozen weight (lora::set_fp8_base).
  void set_fp8_weight(std::shared_ptr<const Fp8Weight> w) { fp8_ = std::move(w); }
  const std::shared_ptr<const Fp8Weight>& fp8_weight() const { return fp8_; }

  int64_t in_features, out_features;
  torch::Tensor weight;  // [out, in]
  torch::Tensor bias;    // [out] or undefined

 private:
  std::shared_ptr<LinearAdapter> adapter_;
  bool adapter_enabled_ = true;
  std::shared_ptr<const Fp8Weight> fp8_;
};
TORCH_MODULE(Linear);

}  // namespace simu::models
