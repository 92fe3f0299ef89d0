// PEFT LoRA directory export/import and merged full-checkpoint export.
#include <fmt/format.h>
#include <fmt/ranges.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "data/safetensors.h"
#include "lora/lora.h"
#include "models/weights.h"

namespace simu::lora {

namespace stdfs = std::filesystem;
using nlohmann::json;

namespace {

// A number as PEFT writes it: integers without a fraction (lora_alpha 8, not 8.0).
json number(double v) {
  if (std::floor(v) == v && std::abs(v) < 1e15) return static_cast<int64_t>(v);
  return v;
}

// adapter_config.json as PEFT 0.21 writes it for a plain LoRA (every field at its default except ours).
json peft_config_json(const LoraConfig& cfg, const std::string& base_description) {
  json j;
  j["alpha_pattern"] = json::object();
  j["auto_mapping"] = {{"base_model_class", "ShortCut"},
                       {"parent_library", "sam3d_objects.model.backbone.generator.shortcut.model"}};
  j["base_model_name_or_path"] = base_description.empty() ? json(nullptr) : json(base_description);
  j["bias"] = "none";
  j["exclude_modules"] = nullptr;
  j["fan_in_fan_out"] = false;
  j["inference_mode"] = true;
  j["init_lora_weights"] = true;
  j["layer_replication"] = nullptr;
  j["layers_pattern"] = nullptr;
  j["layers_to_transform"] = nullptr;
  j["loftq_config"] = json::object();
  j["lora_alpha"] = number(cfg.alpha);
  j["lora_bias"] = false;
  j["lora_dropout"] = cfg.dropout;
  j["megatron_config"] = nullptr;
  j["megatron_core"] = "megatron.core";
  j["modules_to_save"] = nullptr;
  j["peft_type"] = "LORA";
  j["peft_version"] = "0.21.0";
  j["r"] = cfg.r;
  j["rank_pattern"] = json::object();
  j["revision"] = nullptr;
  if (!cfg.target_regex.empty())
    j["target_modules"] = cfg.target_regex;
  else
    j["target_modules"] = cfg.target_suffixes;
  j["target_parameters"] = nullptr;
  j["task_type"] = nullptr;
  j["use_dora"] = false;
  j["use_rslora"] = cfg.use_rslora;
  return j;
}

}  // namespace

void check_adapter_tensors(const std::map<std::string, torch::Tensor>& tensors, int64_t r, const std::string& source) {
  SIMU_CHECK(!tensors.empty(), "{}: no adapter tensors", source);
  // module path -> (A, B) keys
  std::map<std::string, std::pair<std::string, std::string>> modules;
  int64_t rank = r;
  std::string rank_from;
  for (const auto& [key, t] : tensors) {
    std::string name;
    try {
      name = key.rfind("base_model.model.", 0) == 0 ? model_name_from_peft(key) : key;
    } catch (const Error& e) {
      fail("{}: tensor '{}' is not a LoRA A/B weight (expected base_model.model.<module>.lora_A.weight or .lora_B.weight)",
           source, key);
    }
    const bool is_a = name.size() > 14 && name.compare(name.size() - 14, 14, ".lora_A.weight") == 0;
    const bool is_b = name.size() > 14 && name.compare(name.size() - 14, 14, ".lora_B.weight") == 0;
    SIMU_CHECK(is_a || is_b, "{}: tensor '{}' is not a LoRA A/B weight (expected <module>.lora_A.weight or .lora_B.weight)",
               source, key);
    const auto st = t.scalar_type();
    SIMU_CHECK(st == torch::kFloat32 || st == torch::kFloat16 || st == torch::kBFloat16 || st == torch::kFloat64,
               "{}: tensor '{}' has dtype {}, expected a float type (F32, F16, BF16 or F64)", source, key,
               c10::toString(st));
    SIMU_CHECK(t.dim() == 2 && t.numel() > 0, "{}: tensor '{}' has shape [{}], expected a non-empty 2-D matrix", source,
               key, fmt::join(t.sizes(), ", "));
    SIMU_CHECK(torch::isfinite(t).all().item<bool>(), "{}: tensor '{}' holds NaN or Inf ({} non-finite of {} values)",
               source, key, (~torch::isfinite(t)).sum().item<int64_t>(), t.numel());
    const int64_t tr = is_a ? t.size(0) : t.size(1);
    if (rank <= 0) {
      rank = tr;
      rank_from = key;
    }
    SIMU_CHECK(tr == rank, "{}: tensor '{}' has shape [{}], which is not rank {} ({})", source, key,
               fmt::join(t.sizes(), ", "), rank, rank_from.empty() ? std::string("the config's r") : "as " + rank_from);
    auto& slot = modules[name.substr(0, name.size() - 14)];
    (is_a ? slot.first : slot.second) = key;
  }
  for (const auto& [module, keys] : modules) {
    SIMU_CHECK(!keys.first.empty(), "{}: '{}' has no lora_A partner (every module needs lora_A and lora_B)", source,
               keys.second);
    SIMU_CHECK(!keys.second.empty(), "{}: '{}' has no lora_B partner (every module needs lora_A and lora_B)", source,
               keys.first);
  }
}

void save_peft_tensors(const std::string& dir, const std::map<std::string, torch::Tensor>& tensors,
                       const LoraConfig& cfg, const std::string& base_description) {
  cfg.validate();
  SIMU_CHECK(!tensors.empty(), "save_peft: no adapter tensors to write to {}", dir);
  check_adapter_tensors(tensors, cfg.r, fmt::format("save_peft {}", dir));
  // Adapter weights in fp32 under PEFT file keys; every key must be a LoRA A/B weight.
  std::map<std::string, torch::Tensor> out;
  for (const auto& [key, t] : tensors) {
    model_name_from_peft(key);  // validates the name
    out.emplace(key, t.detach().to(torch::kCPU, torch::kFloat32).contiguous());
  }
  const std::string config_text = peft_config_json(cfg, base_description).dump(2) + "\n";

  // Built beside the target, then moved into place whole (the previous adapter stays on failure).
  const stdfs::path target(dir);
  SIMU_CHECK(!stdfs::exists(target) || stdfs::is_directory(target), "save_peft: {} exists and is not a directory", dir);
  fs::remove_stale_temps(target.string());
  const stdfs::path tmp = target.string() + ".tmp-" + std::to_string(::getpid());
  fs::remove_tree(tmp.string());
  stdfs::create_directories(tmp);
  try {
    data::save_safetensors((tmp / kPeftWeightsFile).string(), out, {{"format", "pt"}});
    fs::atomic_write((tmp / kPeftConfigFile).string(), config_text);
    fs::replace_dir(tmp.string(), target.string());
  } catch (...) {
    try {
      fs::remove_tree(tmp.string());
    } catch (...) {
    }
    throw;
  }
  log::info("lora: wrote PEFT adapter {} ({} tensors, r={}, alpha={})", dir, out.size(), cfg.r, cfg.alpha);
}

void save_peft(const std::string& dir, torch::nn::Module& root, const LoraConfig& cfg,
               const std::string& base_description) {
  const auto params = lora_parameters(root);
  SIMU_CHECK(!params.empty(), "save_peft: the model has no LoRA adapters (inject_lora first)");
  std::map<std::string, torch::Tensor> tensors;
  for (const auto& [name, t] : params) {
    SIMU_CHECK(t.size(0) == cfg.r || t.size(1) == cfg.r, "save_peft: '{}' has shape [{}] but the config says r={}",
               name, fmt::join(t.sizes(), ", "), cfg.r);
    tensors.emplace(peft_file_key(name), t);
  }
  save_peft_tensors(dir, tensors, cfg, base_description);
}

LoraConfig load_peft(const std::string& dir, torch::nn::Module& root) {
  const LoraConfig cfg = read_peft_config(dir);
  const std::string weights = (stdfs::path(dir) / kPeftWeightsFile).string();
  SIMU_CHECK(stdfs::exists(weights), "{}: missing (a PEFT LoRA directory holds {} and {})", weights, kPeftConfigFile,
             kPeftWeightsFile);
  const auto file = data::SafeTensorsFile::open(weights);
  check_adapter_tensors(file.all(), cfg.r, weights);

  // Inject with the file's config, or give existing adapters the file's scale and dropout.
  const bool injected = ensure_lora(root, cfg);
  try {
    load_lora_tensors(root, file.all(), weights);
  } catch (...) {
    if (injected) remove_lora(root);
    throw;
  }
  log::info("lora: loaded PEFT adapter {} ({} tensors, r={}, alpha={})", dir, file.keys().size(), cfg.r, cfg.alpha);
  return cfg;
}

void save_merged(const std::string& path, torch::nn::Module& root, const std::string& prefix) {
  torch::NoGradGuard no_grad;
  // Merged weight per wrapped Linear (the model itself is left as it is).
  std::map<std::string, torch::Tensor> merged_weights;
  for (auto& [p, linear] : lora_layers(root)) {
    auto adapter = lora_adapter(*linear);
    const std::string name = p.empty() ? "weight" : p + ".weight";
    if (adapter->merged || !adapter->enabled)
      merged_weights[name] = linear->weight;  // already merged, or adapter off = base model
    else
      merged_weights[name] =
          (linear->weight.to(torch::kFloat32) + adapter->delta_weight()).to(linear->weight.scalar_type());
  }
  // Every base parameter and buffer under its official name; no lora_* entries.
  std::vector<std::pair<std::string, torch::Tensor>> out;
  for (const auto& [name, t] : models::state_dict(root)) {
    const bool is_lora = name.rfind("lora_A.", 0) == 0 || name.rfind("lora_B.", 0) == 0 ||
                         name.find(".lora_A.") != std::string::npos || name.find(".lora_B.") != std::string::npos;
    if (is_lora) continue;
    auto it = merged_weights.find(name);
    out.emplace_back(prefix + name, it != merged_weights.end() ? it->second : t);
  }
  data::save_safetensors(path, out, {{"format", "pt"}});
  log::info("lora: wrote merged checkpoint {} ({} tensors, {} layers merged)", path, out.size(), merged_weights.size());
}

}  // namespace simu::lora
