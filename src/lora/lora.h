// LoRA adapters for simu::models::Linear, with PEFT-compatible injection, files and semantics.
//
// A wrapped Linear computes   y = x W^T + b + scale * B(A(dropout(x)))
//   A: [r, in]  Kaiming-uniform (a = sqrt(5)), like PEFT's default init
//   B: [out, r] zeros (so a fresh adapter changes nothing)
//   scale = alpha / r, or alpha / sqrt(r) with use_rslora
// A and B are registered on the Linear as submodules `lora_A` / `lora_B`, so the model's parameter
// names read `<path>.lora_A.weight` (PEFT keeps `<path>.lora_A.default.weight` in memory and writes
// `base_model.model.<path>.lora_A.weight` to adapter_model.safetensors). Adapter parameters are fp32
// always (they ignore Module::to(dtype)); under autocast their compute follows autocast, otherwise
// the input is cast to fp32 and the adapter output back to the input's dtype (PEFT does the same).
//
// Order of use: construct the model, load its base weights, then inject (or load_peft) — the
// base-weight loader does not know the lora_* parameters.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "common/config.h"
#include "lora/lora_config.h"
#include "models/linear.h"

namespace simu::lora {

// What inject_lora did.
struct InjectReport {
  int layers = 0;                   // Linear layers wrapped
  int64_t parameters = 0;           // adapter parameters added (sum of r * (in + out))
  std::vector<std::string> paths;   // module paths wrapped, in module order
};

// One LoRA matrix (`weight`, [rows, cols]) that stays fp32 whatever dtype the model is cast to.
class LoraWeightImpl : public torch::nn::Module {
 public:
  LoraWeightImpl(int64_t rows, int64_t cols, torch::Device device);
  void to(torch::Device device, torch::Dtype dtype, bool non_blocking = false) override;  // device only
  void to(torch::Dtype dtype, bool non_blocking = false) override;                        // no-op
  void to(torch::Device device, bool non_blocking = false) override;
  torch::Tensor weight;
};
TORCH_MODULE(LoraWeight);

// The adapter a wrapped Linear calls: delta(x) = scale * B(A(dropout(x))).
class LoraAdapter : public models::LinearAdapter {
 public:
  LoraAdapter(LoraWeight A, LoraWeight B, double scale, double dropout);
  // x: [..., in] -> [..., out]
  torch::Tensor delta(const torch::Tensor& x) override;
  // Under autocast: y + scale * (x A^T) B^T as one matrix product accumulating into y (beta 1, alpha
  // scale; one rounding, no full-size scale and sum passes). Otherwise y + delta(x).
  torch::Tensor add_to(const torch::Tensor& y, const torch::Tensor& x) override;
  // Under autocast with a frozen base (w, b without grad) and no dropout at work: the whole wrapped
  // layer x W^T + b + scale (x A^T) B^T as one autograd node (lora_linear.cpp). Same products as
  // Linear + add_to; the up-projection accumulates into the base output in place and the backward's
  // two input-gradient products into one buffer (dx = dy W + scale (dy B) A), which saves a full-size
  // copy forward and a full-size sum backward per layer. Undefined (caller's path) otherwise, or when
  // fused_base is off (the reference the tests compare it with).
  torch::Tensor forward_with_base(const torch::Tensor& x, const torch::Tensor& w, const torch::Tensor& b) override;
  // The rank-r projection A(dropout(x)) (dropout only in training mode): [..., in] -> [..., r].
  torch::Tensor down(const torch::Tensor& x);
  // scale * B @ A in fp32: [out, in]
  torch::Tensor delta_weight() const;
  int64_t rank() const { return A->weight.size(0); }

  LoraWeight A, B;
  double scale, dropout;
  bool enabled = true;   // user switch (set_lora_enabled)
  bool merged = false;   // delta currently added into the Linear's weight
  bool fused_base = true;  // forward_with_base allowed (off: Linear + add_to, the reference path)
};

// The Linear modules under root that carry a LoraAdapter, with their paths, in module order.
std::vector<std::pair<std::string, std::shared_ptr<models::LinearImpl>>> lora_layers(torch::nn::Module& root);
// The LoraAdapter of a Linear, or nullptr.
std::shared_ptr<LoraAdapter> lora_adapter(const models::LinearImpl& linear);

// Wraps every Linear whose path (relative to root, e.g. "reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape")
// is targeted by cfg, then freezes every non-LoRA parameter of root (requires_grad false).
// Matching follows PEFT (lora_config.h: a regex must match the whole path, on RE2; a list entry
// matches the path or a ".entry" suffix).
// Errors (one simu::Error listing all): a regex matching nothing, a suffix matching nothing, a
// targeted module that is not a models::Linear, a Linear already wrapped. Logs the report.
InjectReport inject_lora(torch::nn::Module& root, const LoraConfig& cfg);

// Injects with cfg when root has no adapters yet; otherwise gives the existing adapters cfg's scale
// and dropout (their rank and targets stay; a mismatch shows when tensors are loaded).
// Returns true when it injected.
bool ensure_lora(torch::nn::Module& root, const LoraConfig& cfg);

// Removes every adapter (unmerging first) and its parameters; base parameters stay frozen.
void remove_lora(torch::nn::Module& root);

// Switches every adapter under root on or off (off: outputs are the base model's exactly; a merged
// model is unmerged first, as PEFT does).
void set_lora_enabled(torch::nn::Module& root, bool enabled);

// Which Linear layers the FP8 frozen base covers: the LoRA-wrapped ones (kAdapted), or those and
// every other frozen Linear whose in/out sizes are multiples of 16 (kAll: also the MLPs, the
// modulation and timestep layers). "adapted" / "all" <-> enum; parse throws naming `what`.
enum class Fp8Scope { kAdapted, kAll };
Fp8Scope parse_fp8_scope(const std::string& name, const std::string& what);
std::string fp8_scope_name(Fp8Scope s);

// Opt-in FP8 frozen base (models/fp8_linear.h): enabled -> the Linear layers of `scope` under root
// compute their frozen x W^T + b with e4m3 GEMMs (W quantised now, once, per output channel; inputs
// per row at each call; bf16 out), their input gradient as `backward` says; the adapters, the loss and
// the optimizer are untouched. disabled -> every FP8 copy under root is freed and the layers are
// bit-identical to before. Costs fidelity (measured by bench/fp8_fidelity, docs/benchmarks.md "FP8 frozen base").
// Re-enabling re-quantises (after the base weights changed). Errors: merged adapters (merge changes
// W), no adapters at all. Device checks are the caller's (models::require_fp8_device); on CPU the
// products run through the reference emulation (tests). Returns the layers switched.
int set_fp8_base(torch::nn::Module& root, bool enabled, models::Fp8Backward backward = models::Fp8Backward::kFp8,
                 Fp8Scope scope = Fp8Scope::kAdapted);

// The adapter parameters by model name `<path>.lora_A.weight` / `<path>.lora_B.weight` (A then B
// per layer, in module order). The tensors are the live parameters (not copies).
std::vector<std::pair<std::string, torch::Tensor>> lora_parameters(torch::nn::Module& root);

// W += scale * B @ A for every adapter (in fp32, rounded to W's dtype); the adapter term is then
// skipped in forward. Already merged layers are left alone. Disabled adapters -> error.
void merge_lora(torch::nn::Module& root);
// W -= scale * B @ A for every merged adapter (restores W to within float rounding).
void unmerge_lora(torch::nn::Module& root);

// PEFT names: "<path>.lora_A.weight" <-> "base_model.model.<path>.lora_A.weight" (file) and
// "base_model.model.<path>.lora_A.default.weight" (PEFT's in-memory parameter name).
std::string peft_file_key(const std::string& model_name);
std::string peft_param_key(const std::string& model_name);
// Inverse of both (accepts either form); throws on a key that is neither.
std::string model_name_from_peft(const std::string& peft_key);

// Checks adapter tensors (any key form model_name_from_peft accepts) before they are written or
// loaded: each a LoRA A/B weight of a float dtype (F32, F16, BF16, F64), 2-D, finite; every lora_A
// has the lora_B of the same module and back; A is [r, in], B is [out, r] with one r (= r when r > 0).
// Throws simu::Error naming source and the tensor, and saying what was expected.
void check_adapter_tensors(const std::map<std::string, torch::Tensor>& tensors, int64_t r, const std::string& source);

// Writes root's adapters as a PEFT directory. base_description (free text naming the base model and
// its config) goes into base_model_name_or_path. The directory is built beside dir
// ("<dir>.tmp-<pid>") and moved into place in one step (an existing dir is replaced whole, so a failed
// run leaves the previous adapter intact); temporaries of dead writers are removed first. Refuses
// tensors that check_adapter_tensors refuses. (Programs decide whether replacing is allowed.)
void save_peft(const std::string& dir, torch::nn::Module& root, const LoraConfig& cfg,
               const std::string& base_description);
// Same from tensors already named by PEFT file keys (for converters that have no model).
void save_peft_tensors(const std::string& dir, const std::map<std::string, torch::Tensor>& tensors,
                       const LoraConfig& cfg, const std::string& base_description);

// Loads a PEFT directory into root: injects with the file's config when root has no adapters yet
// (otherwise the existing adapters get the file's scale/dropout), then loads strictly: one error
// lists every missing key, unexpected key, and shape mismatch (file [..] vs model [..]). On an error
// the adapters this call injected are removed again.
LoraConfig load_peft(const std::string& dir, torch::nn::Module& root);
// Strict load of adapter tensors (PEFT file or in-memory names, or model names) into the existing
// adapters of root; source names the file for messages.
void load_lora_tensors(torch::nn::Module& root, const std::map<std::string, torch::Tensor>& tensors,
                       const std::string& source);

// Writes the base model with the adapters merged (root itself is not modified) as one safetensors
// file with official key names: prefix + parameter/buffer name (no lora_* keys).
void save_merged(const std::string& path, torch::nn::Module& root,
                 const std::string& prefix = "_base_models.generator.");

}  // namespace simu::lora
