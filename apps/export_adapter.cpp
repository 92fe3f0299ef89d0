// export_adapter: LoRA adapter of a training checkpoint (or a PEFT directory) -> a PEFT LoRA
// directory (adapter_config.json + adapter_model.safetensors), or with --merge -> one full generator
// checkpoint (.safetensors, official key names, adapters merged into the base weights).
#include <optional>

#include "common/cli.h"
#include "common/config.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "lora/adapter_source.h"
#include "lora/lora.h"
#include "models/generator.h"

int main(int argc, char** argv) {
  CLI::App app{"Export a LoRA adapter (training checkpoint or PEFT dir) to a PEFT directory, or merge it into "
               "the base generator weights (--merge)"};
  std::string source, out, model_config, weights, run_config, description;
  bool merge = false, overwrite = false;
  app.add_option("source", source, "training checkpoint dir (adapter.safetensors + train_state.json) or PEFT dir")
      ->required();
  app.add_option("out", out, "output: PEFT directory, or with --merge a .safetensors file")->required();
  app.add_flag("--overwrite", overwrite, "replace an existing output (it is replaced whole, only once the new one is complete)");
  app.add_flag("--merge", merge, "write a full generator checkpoint with the adapters merged in");
  app.add_option("--model-config", model_config,
                 "generator config (official ss_generator.yaml/json or configs/stage1_*.yaml); required with "
                 "--merge, optional otherwise (then the adapter is checked against the model's shapes)");
  app.add_option("--weights", weights, "base generator weights (.safetensors); required with --merge");
  app.add_option("--config", run_config,
                 "run config whose lora: section gives r/alpha/targets when the checkpoint's train_state.json does not");
  app.add_option("--description", description, "base-model description written into adapter_config.json");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    SIMU_CHECK(common.sets.empty() || !run_config.empty(),
               "--set applies to the run config: pass --config run.yaml with it (got --set {})", common.sets.front());
    SIMU_CHECK(merge || weights.empty(), "--weights is only used with --merge (got --weights {})", weights);
    simu::fs::remove_stale_temps(out);
    simu::fs::check_overwrite(out, overwrite, merge ? "output file" : "output directory");
    // LoRA config fallback from the run config (its lora: section).
    std::optional<simu::lora::LoraConfig> fallback;
    if (!run_config.empty()) {
      auto root = simu::config::load_file(run_config, common.sets);
      simu::config::Reader reader(root, run_config);
      auto lora_reader = reader.child("lora");
      fallback = simu::lora::LoraConfig::from(lora_reader);
      // Only the lora: section is read here; a --set elsewhere would be silently ignored.
      for (const auto& s : common.sets)
        SIMU_CHECK(s.rfind("lora.", 0) == 0, "--set {}: export_adapter reads only the lora: section of {}", s, run_config);
    }
    const auto src = simu::lora::read_adapter_source(source, fallback);
    simu::log::info("{}: {} adapter tensors ({}), r={}, alpha={}", source, src.tensors.size(), src.kind, src.cfg.r,
                    src.cfg.alpha);

    if (merge) {
      SIMU_CHECK(!model_config.empty() && !weights.empty(), "--merge needs --model-config and --weights (the base model)");
      auto gen = simu::models::load_generator(model_config, weights, torch::kCPU);
      simu::lora::apply_adapter(src, *gen);
      simu::lora::save_merged(out, *gen);
      return 0;
    }
    // Optional check against the model (random init: only names and shapes matter).
    if (!model_config.empty()) {
      auto gen = simu::models::load_generator(model_config, "", torch::kCPU);
      simu::lora::apply_adapter(src, *gen);
      simu::log::info("adapter matches {} ({} layers)", model_config, simu::lora::lora_layers(*gen).size());
    }
    if (description.empty())
      description = "SAM 3D Objects Stage-1 ss_generator (ShortCut -> SparseStructureFlowTdfyWrapper), LoRA on the "
                    "shape-branch attention projections" +
                    (model_config.empty() ? std::string() : "; model config " + model_config);
    simu::lora::save_peft_tensors(out, src.tensors, src.cfg, description);
    return 0;
  });
}
