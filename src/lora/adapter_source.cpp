// Adapter tensors + config from a training checkpoint directory or a PEFT directory.
#include "lora/adapter_source.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <filesystem>
#include <nlohmann/json.hpp>

#include "common/error.h"
#include "common/fs.h"
#include "common/text.h"
#include "data/safetensors.h"

namespace simu::lora {

namespace stdfs = std::filesystem;
using nlohmann::json;

namespace {

// LoRA config from a JSON object using our names or PEFT's (r, alpha|lora_alpha, ...).
LoraConfig config_from_json(const json& j, const std::string& where) {
  LoraConfig c;
  try {
    if (j.contains("r")) c.r = j.at("r").get<int64_t>();
    if (j.contains("alpha")) c.alpha = j.at("alpha").get<double>();
    if (j.contains("lora_alpha")) c.alpha = j.at("lora_alpha").get<double>();
    if (j.contains("dropout")) c.dropout = j.at("dropout").get<double>();
    if (j.contains("lora_dropout")) c.dropout = j.at("lora_dropout").get<double>();
    if (j.contains("use_rslora")) c.use_rslora = j.at("use_rslora").get<bool>();
    if (j.contains("target_modules")) {
      const json& tm = j.at("target_modules");
      c.target_suffixes.clear();
      if (tm.is_string())
        c.target_regex = tm.get<std::string>();
      else
        c.target_suffixes = tm.get<std::vector<std::string>>();
    }
  } catch (const json::exception& e) {
    fail("{}: key 'lora': expected an object with r (integer), alpha (number), dropout (number), use_rslora "
         "(true/false), target_modules (string or list of strings), got {}",
         where, text::excerpt(j));
  }
  try {
    c.validate();
  } catch (const Error& e) {
    fail("{}: key 'lora': {}", where, e.what());
  }
  return c;
}

// The training checkpoint's adapter file, renamed to PEFT file keys.
std::map<std::string, torch::Tensor> read_checkpoint_tensors(const std::string& path) {
  std::map<std::string, torch::Tensor> out;
  const auto all = data::load_safetensors(path);
  check_adapter_tensors(all, 0, path);
  for (auto& [key, t] : all) {
    const std::string name = model_name_from_peft(key);  // accepts file or in-memory PEFT names
    SIMU_CHECK(out.emplace(peft_file_key(name), t).second, "{}: '{}' appears twice", path, name);
  }
  return out;
}

}  // namespace

AdapterSource read_adapter_source(const std::string& dir, const std::optional<LoraConfig>& fallback) {
  AdapterSource src;
  src.dir = dir;
  const stdfs::path d(dir);
  SIMU_CHECK(stdfs::is_directory(d), "{}: not a directory (expected a training checkpoint or a PEFT adapter dir)", dir);

  if (stdfs::exists(d / kPeftConfigFile)) {
    // PEFT directory.
    src.kind = "peft";
    src.cfg = read_peft_config(dir);
    const std::string weights = (d / kPeftWeightsFile).string();
    SIMU_CHECK(stdfs::is_regular_file(weights), "{}: missing (a PEFT LoRA directory holds {} and {})", weights,
               kPeftConfigFile, kPeftWeightsFile);
    const auto all = data::load_safetensors(weights);
    check_adapter_tensors(all, src.cfg.r, weights);
    for (auto& [key, t] : all) src.tensors.emplace(peft_file_key(model_name_from_peft(key)), t);
  } else if (stdfs::exists(d / "adapter.safetensors")) {
    // Training checkpoint of this toolkit (src/training/checkpoint.*): adapter.safetensors + train_state.json.
    src.kind = "training-checkpoint";
    src.tensors = read_checkpoint_tensors((d / "adapter.safetensors").string());
    const std::string state_path = (d / "train_state.json").string();
    json state;
    if (stdfs::exists(state_path)) {
      state = text::parse_json(fs::read_file(state_path), state_path);
    }
    if (state.is_object() && state.contains("lora") && state["lora"].is_object())
      src.cfg = config_from_json(state["lora"], state_path);
    else if (fallback)
      src.cfg = *fallback;
    else
      fail_hint("pass the run config (--config run.yaml with a lora: section) so r/alpha/targets are known",
                "{}: no \"lora\" object in {} to say the adapter's config", dir, state_path);
  } else {
    fail_hint("a training checkpoint holds adapter.safetensors + train_state.json; a PEFT dir holds "
              "adapter_config.json + adapter_model.safetensors",
              "{}: neither a training checkpoint nor a PEFT adapter directory", dir);
  }

  // The config's rank must agree with the tensors (A is [r, in], B is [out, r]), every A with its B,
  // float dtypes, finite values.
  check_adapter_tensors(src.tensors, src.cfg.r, dir);
  return src;
}

void apply_adapter(const AdapterSource& source, torch::nn::Module& root) {
  const bool injected = ensure_lora(root, source.cfg);
  try {
    load_lora_tensors(root, source.tensors, source.dir);
  } catch (...) {
    if (injected) remove_lora(root);
    throw;
  }
}

}  // namespace simu::lora
