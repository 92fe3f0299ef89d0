// The export_adapter program's work as a library call (apps/export_adapter.cpp, the Python module's
// simuscene.export_adapter): a training checkpoint's (or a PEFT directory's) LoRA adapter written as a
// PEFT directory, or merged into the base generator weights as one safetensors file.
#pragma once

#include <string>
#include <vector>

namespace simu::lora {

struct ExportOptions {
  bool merge = false;          // write the base generator with the adapters merged in (needs model_config, weights)
  bool overwrite = false;      // replace an existing output (only once the new one is complete)
  std::string model_config;    // generator config: required with merge; otherwise optional (shapes checked)
  std::string weights;         // base generator safetensors (merge only)
  std::string run_config;      // run config whose lora: section gives r/alpha/targets missing from the source
  std::vector<std::string> sets;  // "lora.a=v" overrides of run_config's lora: section
  std::string description;     // base-model description in adapter_config.json ("" = the Stage-1 default)
};

// Exports `source` (checkpoint dir with adapter.safetensors + train_state.json, or a PEFT dir) to `out`.
// Errors (simu::Error) name the flag or file: --weights without --merge, --set without a run config or
// outside lora:, an existing output without overwrite, a merge without the base model.
void export_adapter(const std::string& source, const std::string& out, const ExportOptions& options);

}  // namespace simu::lora
