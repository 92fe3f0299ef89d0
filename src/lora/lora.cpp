// LoRA layer, injection by target pattern, enable/disable, merge/unmerge.
#include "lora/lora.h"

#include <ATen/autocast_mode.h>
#include <fmt/format.h>
#include <fmt/ranges.h>

#include <cmath>
#include <set>

#include "common/error.h"
#include "common/log.h"

namespace simu::lora {

namespace {

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

// Last dotted component of a module path.
std::string leaf(const std::string& path) {
  const auto dot = path.rfind('.');
  return dot == std::string::npos ? path : path.substr(dot + 1);
}

// True for "<path>.lora_A.<param>" / "<path>.lora_B.<param>" (the owning module is lora_A/lora_B).
bool is_lora_name(const std::string& name) {
  const auto dot = name.rfind('.');
  if (dot == std::string::npos) return false;
  const std::string owner = leaf(name.substr(0, dot));
  return owner == "lora_A" || owner == "lora_B";
}

// Shape as "[a, b]" for messages.
std::string shape_str(const torch::Tensor& t) { return fmt::format("[{}]", fmt::join(t.sizes(), ", ")); }

}  // namespace

// ---------------------------------------------------------------- layer

LoraWeightImpl::LoraWeightImpl(int64_t rows, int64_t cols, torch::Device device) {
  weight = register_parameter("weight", torch::zeros({rows, cols}, torch::dtype(torch::kFloat32).device(device)));
}

void LoraWeightImpl::to(torch::Device device, torch::Dtype /*dtype*/, bool non_blocking) {
  // Adapter weights stay fp32: follow the device only.
  weight.set_data(weight.to(device, torch::kFloat32, non_blocking));
}

void LoraWeightImpl::to(torch::Dtype /*dtype*/, bool /*non_blocking*/) {}

void LoraWeightImpl::to(torch::Device device, bool non_blocking) {
  weight.set_data(weight.to(device, torch::kFloat32, non_blocking));
}

LoraAdapter::LoraAdapter(LoraWeight a, LoraWeight b, double s, double p)
    : A(std::move(a)), B(std::move(b)), scale(s), dropout(p) {}

torch::Tensor LoraAdapter::down(const torch::Tensor& x) {
  auto h = x;  // [..., in]
  if (dropout > 0 && A->is_training()) h = torch::dropout(h, dropout, /*train=*/true);
  return torch::linear(h, A->weight);  // [..., r]
}

torch::Tensor LoraAdapter::delta(const torch::Tensor& x) {
  // Under autocast torch::linear casts to the autocast dtype itself; otherwise compute in fp32.
  const bool autocast = at::autocast::is_autocast_enabled(x.device().type());
  auto out = torch::linear(down(autocast ? x : x.to(torch::kFloat32)), B->weight) * scale;  // [..., out]
  return autocast ? out : out.to(x.scalar_type());
}

torch::Tensor LoraAdapter::add_to(const torch::Tensor& y, const torch::Tensor& x) {
  if (!at::autocast::is_autocast_enabled(x.device().type())) return y + delta(x);
  auto a = down(x);  // [..., r] in the autocast dtype
  // [rows, out] = y + scale * a B^T, then back to y's shape.
  auto out = torch::addmm(y.reshape({-1, y.size(-1)}), a.reshape({-1, a.size(-1)}), B->weight.t(), /*beta=*/1, /*alpha=*/scale);
  return out.view(y.sizes());
}

torch::Tensor LoraAdapter::delta_weight() const {
  return torch::matmul(B->weight.to(torch::kFloat32), A->weight.to(torch::kFloat32)) * scale;  // [out, in]
}

std::shared_ptr<LoraAdapter> lora_adapter(const models::LinearImpl& linear) {
  return std::dynamic_pointer_cast<LoraAdapter>(linear.adapter());
}

std::vector<std::pair<std::string, std::shared_ptr<models::LinearImpl>>> lora_layers(torch::nn::Module& root) {
  std::vector<std::pair<std::string, std::shared_ptr<models::LinearImpl>>> out;
  for (const auto& item : root.named_modules("", /*include_self=*/true)) {
    auto linear = std::dynamic_pointer_cast<models::LinearImpl>(item.value());
    if (linear && lora_adapter(*linear)) out.emplace_back(item.key(), linear);
  }
  return out;
}

// ---------------------------------------------------------------- injection

InjectReport inject_lora(torch::nn::Module& root, const LoraConfig& cfg) {
  const TargetMatcher matcher(cfg);  // validates cfg
  const bool use_regex = matcher.is_regex();
  std::set<std::string> unused_suffixes(cfg.target_suffixes.begin(), cfg.target_suffixes.end());
  std::vector<std::string> problems;
  std::vector<std::pair<std::string, std::shared_ptr<models::LinearImpl>>> targets;

  // Find every module whose path the config targets (PEFT: re.fullmatch, or equal / ends with ".suffix").
  for (const auto& item : root.named_modules("", /*include_self=*/false)) {
    const std::string& path = item.key();
    const std::string name = leaf(path);
    if (name == "lora_A" || name == "lora_B") continue;  // our own adapter matrices
    if (!matcher.matches(path)) continue;
    for (const auto& s : matcher.matching_entries(path)) unused_suffixes.erase(s);
    auto linear = std::dynamic_pointer_cast<models::LinearImpl>(item.value());
    if (!linear) {
      problems.push_back(fmt::format("'{}' is a {}, not a models::Linear", path, item.value()->name()));
    } else if (linear->adapter()) {
      problems.push_back(fmt::format("'{}' already has an adapter", path));
    } else {
      targets.emplace_back(path, linear);
    }
  }
  if (use_regex && targets.empty() && problems.empty())
    problems.push_back(fmt::format("regex '{}' matches no module", cfg.target_regex));
  for (const auto& s : unused_suffixes) problems.push_back(fmt::format("target '{}' matches no module", s));
  if (!problems.empty())
    fail_hint("target_modules is a regex over full module paths (e.g. reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape) "
              "or a list of path suffixes",
              "inject_lora: {}", fmt::join(problems, "; "));

  // Wrap each target: A Kaiming-uniform(a=sqrt(5)) like nn.Linear/PEFT, B zeros; fp32 on the weight's device.
  InjectReport report;
  for (auto& [path, linear] : targets) {
    const auto device = linear->weight.device();
    LoraWeight A(cfg.r, linear->in_features, device);
    LoraWeight B(linear->out_features, cfg.r, device);
    {
      torch::NoGradGuard no_grad;
      torch::nn::init::kaiming_uniform_(A->weight, std::sqrt(5.0));
    }
    linear->register_module("lora_A", A);
    linear->register_module("lora_B", B);
    A->train(linear->is_training());
    B->train(linear->is_training());
    linear->set_adapter(std::make_shared<LoraAdapter>(A, B, cfg.scale(), cfg.dropout));
    linear->set_adapter_enabled(true);
    report.layers += 1;
    report.parameters += A->weight.numel() + B->weight.numel();
    report.paths.push_back(path);
  }

  // Freeze the base model: only lora_A / lora_B parameters train.
  for (auto& p : root.named_parameters(/*recurse=*/true)) {
    p.value().set_requires_grad(is_lora_name(p.key()));
  }
  log::info("lora: wrapped {} Linear layers, {} adapter parameters (r={}, alpha={}, scale={})", report.layers,
            report.parameters, cfg.r, cfg.alpha, cfg.scale());
  return report;
}

bool ensure_lora(torch::nn::Module& root, const LoraConfig& cfg) {
  auto layers = lora_layers(root);
  if (layers.empty()) {
    inject_lora(root, cfg);
    return true;
  }
  for (auto& [path, linear] : layers) {
    auto adapter = lora_adapter(*linear);
    adapter->scale = cfg.scale();
    adapter->dropout = cfg.dropout;
  }
  return false;
}

void remove_lora(torch::nn::Module& root) {
  unmerge_lora(root);
  for (auto& [path, linear] : lora_layers(root)) {
    linear->set_adapter(nullptr);
    linear->set_adapter_enabled(true);
    linear->unregister_module("lora_A");
    linear->unregister_module("lora_B");
  }
}

// ---------------------------------------------------------------- switches

void set_lora_enabled(torch::nn::Module& root, bool enabled) {
  if (!enabled) unmerge_lora(root);
  for (auto& [path, linear] : lora_layers(root)) {
    auto adapter = lora_adapter(*linear);
    adapter->enabled = enabled;
    linear->set_adapter_enabled(enabled && !adapter->merged);
  }
}

Fp8Scope parse_fp8_scope(const std::string& name, const std::string& what) {
  if (name == "adapted") return Fp8Scope::kAdapted;
  if (name == "all") return Fp8Scope::kAll;
  fail("{}: expected 'adapted' or 'all', got '{}'", what, name);
}

std::string fp8_scope_name(Fp8Scope s) { return s == Fp8Scope::kAdapted ? "adapted" : "all"; }

int set_fp8_base(torch::nn::Module& root, bool enabled, models::Fp8Backward backward, Fp8Scope scope) {
  SIMU_CHECK(!lora_layers(root).empty(), "set_fp8_base: the model has no LoRA-wrapped layers (the FP8 base is for LoRA training)");
  int switched = 0;
  for (const auto& item : root.named_modules("", /*include_self=*/true)) {
    auto linear = std::dynamic_pointer_cast<models::LinearImpl>(item.value());
    if (!linear) continue;
    if (!enabled) {
      switched += linear->fp8_weight() != nullptr;
      linear->set_fp8_weight(nullptr);
      continue;
    }
    auto adapter = lora_adapter(*linear);
    if (adapter) {
      SIMU_CHECK(!adapter->merged, "set_fp8_base: the adapter of '{}' is merged into its weight; unmerge first", item.key());
      SIMU_CHECK(linear->in_features % 16 == 0 && linear->out_features % 16 == 0,
                 "set_fp8_base: '{}' is [{} -> {}]; FP8 GEMMs need sizes that are multiples of 16", item.key(),
                 linear->in_features, linear->out_features);
    } else {
      // Scope all: every other frozen Linear whose sizes FP8 GEMMs take (multiples of 16).
      const bool frozen = !linear->weight.requires_grad() && !(linear->bias.defined() && linear->bias.requires_grad());
      if (scope == Fp8Scope::kAdapted || !frozen || linear->in_features % 16 != 0 || linear->out_features % 16 != 0) continue;
    }
    linear->set_fp8_weight(models::make_fp8_weight(linear->weight, linear->bias, backward));
    ++switched;
  }
  log::info("lora: FP8 frozen base {} for {} Linear layers{}", enabled ? "on" : "off", switched,
            enabled ? fmt::format(" (scope {}, input gradients in {})", fp8_scope_name(scope), models::fp8_backward_name(backward))
                    : "");
  return switched;
}

std::vector<std::pair<std::string, torch::Tensor>> lora_parameters(torch::nn::Module& root) {
  std::vector<std::pair<std::string, torch::Tensor>> out;
  for (auto& [path, linear] : lora_layers(root)) {
    auto adapter = lora_adapter(*linear);
    out.emplace_back(path + ".lora_A.weight", adapter->A->weight);
    out.emplace_back(path + ".lora_B.weight", adapter->B->weight);
  }
  return out;
}

void merge_lora(torch::nn::Module& root) {
  torch::NoGradGuard no_grad;
  for (auto& [path, linear] : lora_layers(root)) {
    auto adapter = lora_adapter(*linear);
    if (adapter->merged) continue;
    SIMU_CHECK(!linear->fp8_weight(), "merge_lora: '{}' computes with an FP8 copy of its weight; set_fp8_base off first", path);
    SIMU_CHECK(adapter->enabled, "merge_lora: the adapter of '{}' is disabled; enable adapters before merging", path);
    // W [out, in] += scale * B @ A, summed in fp32 then rounded to W's dtype.
    auto merged = (linear->weight.to(torch::kFloat32) + adapter->delta_weight()).to(linear->weight.scalar_type());
    linear->weight.copy_(merged);
    adapter->merged = true;
    linear->set_adapter_enabled(false);
  }
}

void unmerge_lora(torch::nn::Module& root) {
  torch::NoGradGuard no_grad;
  for (auto& [path, linear] : lora_layers(root)) {
    auto adapter = lora_adapter(*linear);
    if (!adapter->merged) continue;
    // W [out, in] -= scale * B @ A.
    auto base = (linear->weight.to(torch::kFloat32) - adapter->delta_weight()).to(linear->weight.scalar_type());
    linear->weight.copy_(base);
    adapter->merged = false;
    linear->set_adapter_enabled(adapter->enabled);
  }
}

// ---------------------------------------------------------------- names

namespace {
const std::string kPeftPrefix = "base_model.model.";
}

std::string peft_file_key(const std::string& model_name) { return kPeftPrefix + model_name; }

std::string peft_param_key(const std::string& model_name) {
  for (const char* m : {".lora_A.weight", ".lora_B.weight"}) {
    const std::string marker = m;
    if (ends_with(model_name, marker)) {
      const std::string base = model_name.substr(0, model_name.size() - marker.size());
      return kPeftPrefix + base + marker.substr(0, 7) + ".default.weight";
    }
  }
  fail("lora: '{}' is not a LoRA parameter name (<path>.lora_A.weight or <path>.lora_B.weight)", model_name);
}

std::string model_name_from_peft(const std::string& peft_key) {
  SIMU_CHECK(peft_key.rfind(kPeftPrefix, 0) == 0, "lora: key '{}' does not start with '{}'", peft_key, kPeftPrefix);
  std::string name = peft_key.substr(kPeftPrefix.size());
  for (const char* m : {".lora_A.default.weight", ".lora_B.default.weight"}) {
    const std::string marker = m;
    if (ends_with(name, marker)) return name.substr(0, name.size() - marker.size()) + marker.substr(0, 7) + ".weight";
  }
  SIMU_CHECK(ends_with(name, ".lora_A.weight") || ends_with(name, ".lora_B.weight"),
             "lora: key '{}' is not a LoRA A/B weight (PEFT features like lora bias, DoRA magnitude or "
             "modules_to_save are not supported)",
             peft_key);
  return name;
}

// ---------------------------------------------------------------- strict tensor load

void load_lora_tensors(torch::nn::Module& root, const std::map<std::string, torch::Tensor>& tensors,
                       const std::string& source) {
  // Expected: the live adapter parameters by model name.
  std::map<std::string, torch::Tensor> expected;
  for (auto& [name, t] : lora_parameters(root)) expected.emplace(name, t);
  SIMU_CHECK(!expected.empty(), "{}: the model has no LoRA adapters to load into", source);
  for (auto& [path, linear] : lora_layers(root))
    SIMU_CHECK(!lora_adapter(*linear)->merged, "{}: cannot load adapters into a merged model (unmerge first)", source);

  // Match file keys (PEFT file/in-memory names or model names) to parameters; collect every problem.
  std::vector<std::string> unexpected, mismatched;
  std::set<std::string> mismatched_names;
  std::map<std::string, torch::Tensor> found;
  for (const auto& [key, value] : tensors) {
    std::string name = key;
    if (key.rfind(kPeftPrefix, 0) == 0) {
      try {
        name = model_name_from_peft(key);
      } catch (const Error&) {
        unexpected.push_back(key);
        continue;
      }
    }
    auto it = expected.find(name);
    if (it == expected.end()) {
      unexpected.push_back(key);
      continue;
    }
    if (value.sizes() != it->second.sizes()) {
      mismatched.push_back(fmt::format("{}: file {} vs model {}", key, shape_str(value), shape_str(it->second)));
      mismatched_names.insert(name);
      continue;
    }
    SIMU_CHECK(found.count(name) == 0, "{}: parameter '{}' appears twice (as '{}')", source, name, key);
    found.emplace(name, value);
  }
  std::vector<std::string> missing;
  for (const auto& [name, t] : expected)
    if (!found.count(name) && !mismatched_names.count(name)) missing.push_back(peft_file_key(name));
  if (!missing.empty() || !unexpected.empty() || !mismatched.empty()) {
    std::string msg = fmt::format("{}: LoRA adapter does not match the model:", source);
    if (!mismatched.empty()) msg += fmt::format("\n  shape mismatch ({}): {}", mismatched.size(), fmt::join(mismatched, "; "));
    if (!missing.empty()) msg += fmt::format("\n  missing ({}): {}", missing.size(), fmt::join(missing, ", "));
    if (!unexpected.empty()) msg += fmt::format("\n  unexpected ({}): {}", unexpected.size(), fmt::join(unexpected, ", "));
    throw Error(msg, "the adapter's r and target_modules must match the model it is loaded into");
  }

  // Copy (fp32, onto each parameter's device).
  torch::NoGradGuard no_grad;
  for (auto& [name, param] : expected) param.copy_(found.at(name).to(param.device(), param.scalar_type()));
}

}  // namespace simu::lora
