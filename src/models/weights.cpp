#include "models/weights.h"

#include <fmt/ranges.h>

#include <set>

#include "common/error.h"
#include "data/safetensors.h"

namespace simu::models {

namespace {
bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}
bool starts_with(const std::string& s, const std::string& prefix) { return s.rfind(prefix, 0) == 0; }
}  // namespace

int64_t load_state_strict(torch::nn::Module& module, const std::map<std::string, torch::Tensor>& state,
                          const LoadOptions& options) {
  // Targets: every parameter and buffer of the module tree.
  std::map<std::string, torch::Tensor> targets;
  for (const auto& p : module.named_parameters(true)) targets[p.key()] = p.value();
  for (const auto& b : module.named_buffers(true)) targets[b.key()] = b.value();

  std::vector<std::string> unexpected, mismatched;
  std::set<std::string> seen;
  int64_t loaded = 0;
  torch::NoGradGuard no_grad;
  for (const auto& [raw_key, value] : state) {
    if (!options.strip_prefix.empty() && !starts_with(raw_key, options.strip_prefix)) continue;
    const std::string key = raw_key.substr(options.strip_prefix.size());
    bool ignored = false;
    for (const auto& ip : options.ignore_prefixes) ignored = ignored || starts_with(key, ip);
    if (ignored) continue;
    const auto it = targets.find(key);
    if (it == targets.end()) {
      unexpected.push_back(key);
      continue;
    }
    seen.insert(key);
    auto& target = it->second;
    if (target.sizes() != value.sizes()) {
      mismatched.push_back(fmt::format("{}: got [{}] expected [{}]", key, fmt::join(value.sizes(), ", "),
                                       fmt::join(target.sizes(), ", ")));
      continue;
    }
    target.copy_(value.to(target.device(), target.scalar_type()));
    ++loaded;
  }
  std::vector<std::string> missing;
  for (const auto& [k, _] : targets)
    if (!seen.count(k)) missing.push_back(k);

  if (!mismatched.empty() || (options.strict && (!missing.empty() || !unexpected.empty()))) {
    std::string msg = fmt::format("{}: weights do not match the model ({} loaded)", options.source, loaded);
    auto list = [&](const char* what, const std::vector<std::string>& keys) {
      if (keys.empty()) return;
      msg += fmt::format("\n  {} ({}):", what, keys.size());
      for (size_t i = 0; i < keys.size() && i < 40; ++i) msg += "\n    " + keys[i];
      if (keys.size() > 40) msg += fmt::format("\n    ... and {} more", keys.size() - 40);
    };
    list("shape mismatches", mismatched);
    if (options.strict) {
      list("missing keys", missing);
      list("unexpected keys", unexpected);
    }
    throw Error(msg, "check that the model config matches the checkpoint (channels, blocks, heads, latent names)");
  }
  return loaded;
}

int64_t load_safetensors_into(torch::nn::Module& module, const std::string& path, LoadOptions options) {
  for (const char* ext : {".ckpt", ".pt", ".pth", ".bin"})
    if (ends_with(path, ext))
      fail_hint("python3 scripts/convert_checkpoint.py " + path + " <out>.safetensors",
                "{} is a PyTorch pickle checkpoint; convert it to safetensors first with scripts/convert_checkpoint.py", path);
  options.source = path;
  return load_state_strict(module, data::load_safetensors(path), options);
}

std::map<std::string, torch::Tensor> state_dict(const torch::nn::Module& module) {
  std::map<std::string, torch::Tensor> out;
  for (const auto& p : module.named_parameters(true)) out[p.key()] = p.value();
  for (const auto& b : module.named_buffers(true)) out[b.key()] = b.value();
  return out;
}

}  // namespace simu::models
