// Linear layer of the Stage-1 model with an optional adapter hook (LoRA lives in src/lora).
//
// Official checkpoints name the parameters `<path>.weight` / `<path>.bias`, exactly like
// torch.nn.Linear, so state dicts line up. An adapter adds a term to the output:
//   y = x W^T + b + adapter(x)   (when an adapter is set and enabled)
// Opt-in: an FP8 copy of the frozen weight (fp8_linear.h) computes x W^T + b instead of torch::linear
// when one is set (set_fp8_weight); without one the layer is exactly torch::linear.
// Opt-in: a compute copy (ComputeCopy below, set_compute_copy): weight and bias kept in the 16-bit
// autocast dtype, so that a product under autocast does not cast the fp32 weight at every call. Same
// values as autocast's own cast (one rounding of the fp32 weight), hence bit-identical outputs; the
// reference path (the fp32 weight through autocast) stays and is taken whenever the copy cannot be used.
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

// A 16-bit copy of a Linear's fp32 weight and bias, with what it was made from (storage and version
// counters of weight and bias), so that a weight changed in place (merge_lora / unmerge_lora, a load,
// copy_, an optimizer step) is noticed: refresh() copies it again into the same memory (CUDA graphs
// that read the copy stay valid), and a weight moved or replaced (other storage, device or shape) no
// longer fits() and needs a new copy.
class ComputeCopy {
 public:
  // weight [out, in] and bias [out] (or undefined) float32 -> copies in dtype (bf16 or fp16), same device.
  ComputeCopy(const torch::Tensor& weight, const torch::Tensor& bias, torch::ScalarType dtype);
  // The copy can stand for these tensors (same storage, device, shape), possibly after a refresh.
  bool fits(const torch::Tensor& weight, const torch::Tensor& bias) const;
  // Copies weight/bias again (in place, no autograd) when either changed since the last copy; returns
  // whether it copied. Precondition: fits(weight, bias).
  bool refresh(const torch::Tensor& weight, const torch::Tensor& bias);
  torch::ScalarType dtype() const { return w_.scalar_type(); }
  const torch::Tensor& weight() const { return w_; }  // [out, in] dtype
  const torch::Tensor& bias() const { return b_; }    // [out] dtype or undefined
  int64_t bytes() const;

 private:
  torch::Tensor w_, b_;
  const void* w_src_ = nullptr;
  const void* b_src_ = nullptr;
  int64_t w_version_ = 0, b_version_ = 0;
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

  // Compute copy (opt-in; the caller enables it for frozen weights, see set_compute_copies): with a
  // dtype (bf16 or fp16), products whose input x is under autocast in that dtype on x's device
  // use a copy of weight/bias in that dtype instead of autocast's per-call cast (autocast caches its
  // casts only for weights that require a gradient, and only within one autocast region). The copy is
  // made at the first such product (layers that never run cost nothing) and kept: 2 bytes per weight
  // (the real Stage-1 flow model: 958M Linear weights = 1.8 GiB; FM-DPO's shape-only forward uses
  // 555M of them = 1.0 GiB). Used only when the weight is float32 on x's device and no gradient is
  // wanted for weight or bias (grad mode off, or neither requires one); otherwise the reference
  // (weight/bias through autocast). A stale copy (weight changed in place) is refreshed before use.
  // nullopt frees the copy.
  void set_compute_copy(c10::optional<torch::ScalarType> dtype);
  c10::optional<torch::ScalarType> compute_copy_dtype() const { return compute_dtype_; }
  // The current copy (null until a product made it); CUDA graphs that read it keep it alive.
  const std::shared_ptr<ComputeCopy>& compute_copy() const { return compute_; }
  // The weight and bias a product with x uses: the compute copy (made or refreshed as needed) when it
  // applies, else weight and bias. Callers that compute the product themselves (a fused GELU
  // epilogue) take them from here.
  std::pair<torch::Tensor, torch::Tensor> product_weights(const torch::Tensor& x);

  int64_t in_features, out_features;
  torch::Tensor weight;  // [out, in]
  torch::Tensor bias;    // [out] or undefined

 private:
  std::shared_ptr<LinearAdapter> adapter_;
  bool adapter_enabled_ = true;
  std::shared_ptr<const Fp8Weight> fp8_;
  c10::optional<torch::ScalarType> compute_dtype_;
  std::shared_ptr<ComputeCopy> compute_;
};
TORCH_MODULE(Linear);

// Sets the compute copy dtype (LinearImpl::set_compute_copy) of every Linear under root whose weight and
// bias do not require a gradient (frozen_only) or of every Linear; nullopt switches them off and frees
// the copies. Returns the number of layers set.
int set_compute_copies(torch::nn::Module& root, c10::optional<torch::ScalarType> dtype, bool frozen_only = true);

}  // namespace simu::models
