// export_adapter: LoRA adapter of a training checkpoint (or a PEFT directory) -> a PEFT LoRA
// directory (adapter_config.json + adapter_model.safetensors), or with --merge -> one full generator
// checkpoint (.safetensors, official key names, adapters merged into the base weights).
#include "common/cli.h"
#include "lora/adapter_export.h"

int main(int argc, char** argv) {
  CLI::App app{"Export a LoRA adapter (training checkpoint or PEFT dir) to a PEFT directory, or merge it into "
               "the base generator weights (--merge)"};
  std::string source, out;
  simu::lora::ExportOptions opt;
  app.add_option("source", source, "training checkpoint dir (adapter.safetensors + train_state.json) or PEFT dir")
      ->required();
  app.add_option("out", out, "output: PEFT directory, or with --merge a .safetensors file")->required();
  app.add_flag("--overwrite", opt.overwrite, "replace an existing output (it is replaced whole, only once the new one is complete)");
  app.add_flag("--merge", opt.merge, "write a full generator checkpoint with the adapters merged in");
  app.add_option("--model-config", opt.model_config,
                 "generator config (official ss_generator.yaml/json or configs/stage1_*.yaml); required with "
                 "--merge, optional otherwise (then the adapter is checked against the model's shapes)");
  app.add_option("--weights", opt.weights, "base generator weights (.safetensors); required with --merge");
  app.add_option("--config", opt.run_config,
                 "run config whose lora: section gives r/alpha/targets when the checkpoint's train_state.json does not");
  app.add_option("--description", opt.description, "base-model description written into adapter_config.json");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    opt.sets = common.sets;
    simu::lora::export_adapter(source, out, opt);
    return 0;
  });
}
