// Helpers shared by the flow model's source files (flow_model.cpp, flow_layers.cpp); not a public API.
#pragma once

#include <torch/torch.h>

#include <string>
#include <vector>

#include "models/flow_model.h"

namespace simu::models::detail {

// Registers `modules` under one ModuleDict named `name` (keys = stream names) so state-dict keys read
// `<name>.<stream>.<param>` like the official torch.nn.ModuleDict.
template <typename Holder>
void register_dict(torch::nn::Module& owner, const std::string& name, const std::vector<std::string>& keys,
                   const std::vector<Holder>& modules) {
  std::vector<std::pair<std::string, std::shared_ptr<torch::nn::Module>>> items;
  for (size_t i = 0; i < keys.size(); ++i) items.emplace_back(keys[i], modules[i].ptr());
  owner.register_module(name, torch::nn::ModuleDict(items));
}

// The kernels without a backward (GELU epilogue, q/k/v into the key/value buffer, second stream): only
// where allowed (not in training mode) and when no graph is recorded.
inline bool inference_only_ok(bool inference_kernels) { return inference_kernels && !at::GradMode::is_enabled(); }

// While alive (and `off`), few-query attention on this thread takes PyTorch's choice rather than the
// flash kernel (few_query_flash is false): for work on a side stream beside the big kernels
// (MOTBlockImpl::side_few_query_flash). Restores the previous state when destroyed.
class FewQueryFlashOff {
 public:
  explicit FewQueryFlashOff(bool off);
  ~FewQueryFlashOff();
  FewQueryFlashOff(const FewQueryFlashOff&) = delete;
  FewQueryFlashOff& operator=(const FewQueryFlashOff&) = delete;

 private:
  bool previous_;
};

// SDPA on [B, L, H, D] tensors (official scaled_dot_product_attention, "sdpa" backend; sdpa_blhd).
// inference_kernels: the caller's permission for the few-query flash kernel (off in training mode, so
// that a no-grad forward computes what the graph forward computes).
inline torch::Tensor attention(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v,
                               bool inference_kernels) {
  return sdpa_blhd(q, k, v, inference_kernels);
}

}  // namespace simu::models::detail
