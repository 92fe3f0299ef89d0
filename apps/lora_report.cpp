// lora_report: builds the generator from a config (random init, no weights), injects LoRA and prints
// the wrapped layers and the adapter parameter count (e.g. 120 layers at real size, r = 64).
#include <fmt/format.h>

#include "common/cli.h"
#include "common/config.h"
#include "common/error.h"
#include "common/log.h"
#include "lora/lora.h"
#include "models/generator.h"

int main(int argc, char** argv) {
  CLI::App app{"Count the LoRA layers and adapter parameters on a generator config (no weights needed)"};
  std::string model_config = "configs/stage1_real.yaml", run_config;
  simu::lora::LoraConfig cfg;
  bool bf16 = false, list = false;
  app.add_option("--model-config", model_config, "generator config (official or project layout)")->capture_default_str();
  app.add_option("--config", run_config, "run config whose lora: section gives r/alpha/targets (else the options)");
  app.add_option("--r", cfg.r, "LoRA rank")->capture_default_str();
  app.add_option("--alpha", cfg.alpha, "LoRA alpha")->capture_default_str();
  app.add_flag("--bf16", bf16, "build the base model in bf16 (half the memory; the counts are the same)");
  app.add_flag("--list", list, "print every wrapped module path");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    if (!run_config.empty()) {
      auto root = simu::config::load_file(run_config, common.sets);
      simu::config::Reader reader(root, run_config);
      auto lora_reader = reader.child("lora");
      cfg = simu::lora::LoraConfig::from(lora_reader);
    }
    // Base model with random init (the default dtype decides the base parameters' dtype).
    simu::log::info("building {} (random init{})", model_config, bf16 ? ", bf16" : "");
    const auto previous = torch::get_default_dtype();
    if (bf16) torch::set_default_dtype(caffe2::TypeMeta::Make<at::BFloat16>());
    auto gen = simu::models::load_generator(model_config, "", torch::kCPU);
    torch::set_default_dtype(previous);
    int64_t base = 0;
    for (const auto& p : gen->parameters()) base += p.numel();

    const auto report = simu::lora::inject_lora(*gen, cfg);
    if (list)
      for (const auto& p : report.paths) fmt::print("{}\n", p);
    fmt::print("base parameters      {}\n", base);
    fmt::print("wrapped layers       {}\n", report.layers);
    fmt::print("adapter parameters   {} (r={}, alpha={}, scale={})\n", report.parameters, cfg.r, cfg.alpha, cfg.scale());
    return 0;
  });
}
