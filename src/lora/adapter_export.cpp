#include "lora/adapter_export.h"

#include <optional>

#include "common/config.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "lora/adapter_source.h"
#include "lora/lora.h"
#include "models/generator.h"

namespace simu::lora {

void export_adapter(const std::string& source, const std::string& out, const ExportOptions& o) {
  SIMU_CHECK(o.sets.empty() || !o.run_config.empty(),
             "--set applies to the run config: pass --config run.yaml with it (got --set {})", o.sets.front());
  SIMU_CHECK(o.merge || o.weights.empty(), "--weights is only used with --merge (got --weights {})", o.weights);
  simu::fs::remove_stale_temps(out);
  simu::fs::check_overwrite(out, o.overwrite, o.merge ? "output file" : "output directory");
  // LoRA config fallback from the run config (its lora: section).
  std::optional<LoraConfig> fallback;
  if (!o.run_config.empty()) {
    auto root = simu::config::load_file(o.run_config, o.sets);
    simu::config::Reader reader(root, o.run_config);
    auto lora_reader = reader.child("lora");
    fallback = LoraConfig::from(lora_reader);
    // Only the lora: section is read here; a --set elsewhere would be silently ignored.
    for (const auto& s : o.sets)
      SIMU_CHECK(s.rfind("lora.", 0) == 0, "--set {}: export_adapter reads only the lora: section of {}", s, o.run_config);
  }
  const auto src = read_adapter_source(source, fallback);
  simu::log::info("{}: {} adapter tensors ({}), r={}, alpha={}", source, src.tensors.size(), src.kind, src.cfg.r,
                  src.cfg.alpha);

  if (o.merge) {
    SIMU_CHECK(!o.model_config.empty() && !o.weights.empty(), "--merge needs --model-config and --weights (the base model)");
    auto gen = simu::models::load_generator(o.model_config, o.weights, torch::kCPU);
    apply_adapter(src, *gen);
    save_merged(out, *gen);
    return;
  }
  // Optional check against the model (random init: only names and shapes matter).
  if (!o.model_config.empty()) {
    auto gen = simu::models::load_generator(o.model_config, "", torch::kCPU);
    apply_adapter(src, *gen);
    simu::log::info("adapter matches {} ({} layers)", o.model_config, lora_layers(*gen).size());
  }
  std::string description = o.description;
  if (description.empty())
    description = "SAM 3D Objects Stage-1 ss_generator (ShortCut -> SparseStructureFlowTdfyWrapper), LoRA on the "
                  "shape-branch attention projections" +
                  (o.model_config.empty() ? std::string() : "; model config " + o.model_config);
  save_peft_tensors(out, src.tensors, src.cfg, description);
}

}  // namespace simu::lora
