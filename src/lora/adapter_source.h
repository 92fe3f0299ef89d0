// Reading adapters from wherever they live: a training checkpoint of this toolkit or a PEFT directory.
#pragma once

#include <torch/torch.h>

#include <map>
#include <optional>
#include <string>

#include "lora/lora.h"

namespace simu::lora {

// Adapter tensors by PEFT file key ("base_model.model.<path>.lora_A.weight") and their config.
struct AdapterSource {
  std::string dir;
  std::string kind;  // "peft" or "training-checkpoint"
  LoraConfig cfg;
  std::map<std::string, torch::Tensor> tensors;
};

// Reads dir, which is either
//  - a PEFT LoRA directory (adapter_config.json + adapter_model.safetensors), or
//  - a training checkpoint of this toolkit: adapter.safetensors (adapter tensors under PEFT names, file
//    or in-memory form) + train_state.json. The LoRA config comes from train_state.json's "lora" object
//    (keys r, alpha | lora_alpha, dropout | lora_dropout, use_rslora, target_modules) when present,
//    otherwise from `fallback` (e.g. the run config's lora section); neither -> error with a hint.
// The rank in the config must agree with the tensors. Throws simu::Error naming the file.
AdapterSource read_adapter_source(const std::string& dir, const std::optional<LoraConfig>& fallback = std::nullopt);

// Puts the source's adapters into root: injects with source.cfg when root has none (otherwise the
// existing adapters take its scale/dropout), then loads the tensors strictly (see load_lora_tensors).
void apply_adapter(const AdapterSource& source, torch::nn::Module& root);

}  // namespace simu::lora
