// Strict loading of weights by official name and shape into a torch::nn::Module tree.
#pragma once

#include <torch/torch.h>

#include <map>
#include <string>

namespace simu::models {

struct LoadOptions {
  // Only keys starting with this prefix are considered, and the prefix is removed
  // (e.g. "_base_models.generator." for the official generator checkpoint). Empty: all keys.
  std::string strip_prefix;
  // Keys (after stripping) starting with any of these are ignored (e.g. other sub-models).
  std::vector<std::string> ignore_prefixes;
  // Missing or unexpected keys are errors unless false; shape mismatches always are.
  bool strict = true;
  // File name for messages.
  std::string source = "<memory>";
};

// Copies tensors into module's parameters and buffers (names from named_parameters/named_buffers).
// Values are converted to each parameter's dtype and device. Throws one simu::Error listing every
// missing key, unexpected key and shape mismatch ("got [..] expected [..]"), naming the source.
// Returns the number of tensors loaded.
int64_t load_state_strict(torch::nn::Module& module, const std::map<std::string, torch::Tensor>& state,
                          const LoadOptions& options);

// Convenience: reads a safetensors file and loads it strictly. A path ending in .ckpt/.pt/.pth gives
// a one-line error telling to convert it with scripts/convert_checkpoint.py.
int64_t load_safetensors_into(torch::nn::Module& module, const std::string& path, LoadOptions options);

// The module's state (parameters then buffers) by name, for saving.
std::map<std::string, torch::Tensor> state_dict(const torch::nn::Module& module);

}  // namespace simu::models
