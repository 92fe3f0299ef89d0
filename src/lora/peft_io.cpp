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

// True when a JSON field is absent, null, false, or an empty object/list/string.
bool unset(const json& j, const char* key) {
  if (!j.contains(key)) return true;
  const json& v = j.at(key);
  return v.is_null() || (v.is_boolean() && !v.get<bool>()) || (v.is_object() && v.empty()) ||
         (v.is_array() && v.empty()) || (v.is_string() && v.get<std::string>().empty());
}

}  // namespace

void save_peft_tensors(const std::string& dir, const std::map<std::string, torch::Tensor>& tensors,
                       const LoraConfig& cfg, const std::string& base_description) {
  cfg.validate();
  SIMU_CHECK(!tensors.empty(), "save_peft: no adapter tensors to write to {}", dir);
  // Adapter weights in fp32 under PEFT file keys; every key must be a LoRA A/B weight.
  std::map<std::string, torch::Tensor> out;
  for (const auto& [key, t] : tensors) {
    model_name_from_peft(key);  // validates the name
    out.emplace(key, t.detach().to(torch::kCPU, torch::kFloat32).contiguous());
  }
  const std::string config_text = peft_config_json(cfg, base_description).dump(2) + "\n";

  // New directory: build it beside the target and rename it into place; existing: replace per file.
  const stdfs::path target(dir);
  if (!stdfs::exists(target)) {
    const stdfs::path tmp = target.string() + ".tmp-" + std::to_string(::getpid());
    fs::remove_tree(tmp.string());
    stdfs::create_directories(tmp);
    data::save_safetensors((tmp / kPeftWeightsFile).string(), out, {{"format", "pt"}});
    fs::atomic_write((tmp / kPeftConfigFile).string(), config_text);
    fs::atomic_rename(tmp.string(), target.string());
  } else {
    SIMU_CHECK(stdfs::is_directory(target), "save_peft: {} exists and is not a directory", dir);
    data::save_safetensors((target / kPeftWeightsFile).string(), out, {{"format", "pt"}});
    fs::atomic_write((target / kPeftConfigFile).string(), config_text);
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

LoraConfig read_peft_config(const std::string& dir) {
  const std::string path = (stdfs::path(dir) / kPeftConfigFile).string();
  json j;
  try {
    j = json::parse(fs::read_file(path));
  } catch (const json::exception& e) {
    fail("{}: not valid JSON: {}", path, e.what());
  }
  SIMU_CHECK(j.is_object(), "{}: expected a JSON object", path);
  try {
    // Only plain LoRA is implemented: refuse every PEFT feature that would change the math.
    const std::string type = j.value("peft_type", std::string());
    SIMU_CHECK(type == "LORA", "{}: peft_type is '{}', expected 'LORA'", path, type);
    const std::string bias = j.contains("bias") && !j["bias"].is_null() ? j["bias"].get<std::string>() : "none";
    SIMU_CHECK(bias == "none", "{}: bias '{}' is not supported (only \"none\")", path, bias);
    for (const char* key : {"use_dora", "fan_in_fan_out", "lora_bias", "rank_pattern", "alpha_pattern",
                            "modules_to_save", "layers_to_transform", "layers_pattern", "exclude_modules",
                            "layer_replication", "target_parameters", "use_qalora", "use_bdlora"})
      SIMU_CHECK(unset(j, key), "{}: '{}' = {} is not supported by this toolkit", path, key, j.at(key).dump());

    LoraConfig cfg;
    SIMU_CHECK(j.contains("r") && j["r"].is_number_integer(), "{}: 'r' must be an integer", path);
    cfg.r = j["r"].get<int64_t>();
    SIMU_CHECK(j.contains("lora_alpha") && j["lora_alpha"].is_number(), "{}: 'lora_alpha' must be a number", path);
    cfg.alpha = j["lora_alpha"].get<double>();
    cfg.dropout = j.contains("lora_dropout") && j["lora_dropout"].is_number() ? j["lora_dropout"].get<double>() : 0.0;
    cfg.use_rslora = j.contains("use_rslora") && j["use_rslora"].is_boolean() && j["use_rslora"].get<bool>();
    const json& tm = j.contains("target_modules") ? j["target_modules"] : json(nullptr);
    cfg.target_suffixes.clear();
    if (tm.is_string()) {
      cfg.target_regex = tm.get<std::string>();
    } else if (tm.is_array()) {
      for (const auto& item : tm) {
        SIMU_CHECK(item.is_string(), "{}: target_modules entries must be strings", path);
        cfg.target_suffixes.push_back(item.get<std::string>());
      }
    } else {
      fail("{}: target_modules must be a regex string or a list of names, got {}", path, tm.dump());
    }
    cfg.validate();
    return cfg;
  } catch (const json::exception& e) {
    fail("{}: unexpected value type: {}", path, e.what());
  } catch (const Error& e) {
    const std::string msg = e.what();
    if (msg.rfind(path, 0) == 0) throw;
    throw Error(path + ": " + msg, e.hint());
  }
}

LoraConfig load_peft(const std::string& dir, torch::nn::Module& root) {
  const LoraConfig cfg = read_peft_config(dir);
  const std::string weights = (stdfs::path(dir) / kPeftWeightsFile).string();
  SIMU_CHECK(stdfs::exists(weights), "{}: missing (a PEFT LoRA directory holds {} and {})", weights, kPeftConfigFile,
             kPeftWeightsFile);
  const auto file = data::SafeTensorsFile::open(weights);

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
