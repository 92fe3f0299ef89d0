// bench_train_stage1: Stage-1 pretraining throughput without a cache: the model of a train_stage1
// config (default: the miniature) trained for a few steps on synthetic samples in memory at the
// config's sizes, through the trainer (read-ahead and the device-side update on CUDA). Prints the
// parameter counts, the analytic FLOPs per sample (training/stage1_model.h stage1_flops), samples/s
// after a warm-up, and the achieved rate against a matmul ceiling (--peak-tflops).
//   bench_train_stage1 --device cuda --batch 256 --steps 30
//   bench_train_stage1 --device cpu --batch 8 --steps 3 --warmup 1     (CPU smoke run)
#include <fmt/format.h>
#include <torch/cuda.h>

#include <algorithm>
#include <filesystem>

#include "common/source_dir.h"
#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "models/cond_embedder.h"
#include "training/distributed.h"
#include "training/flow_objective.h"
#include "training/launcher.h"
#include "training/stage1_config.h"
#include "training/stage1_data.h"
#include "training/stage1_model.h"
#include "training/trainer.h"

int main(int argc, char** argv) {
  CLI::App app{"Stage-1 pretraining throughput on synthetic samples (no cache needed)"};
  std::string config = simu::source_dir() + "/configs/miniature/train_stage1.yaml";
  std::string device = "cuda", precision = "bf16";
  int64_t batch = 256, micro = 0, steps = 30, warmup = 5, samples_n = 0, resolution = 32;
  double peak = 780;
  bool checkpointing = false;
  app.add_option("--config", config, "train_stage1 config (model and objective sections are used)")->capture_default_str();
  app.add_option("--device", device, "cuda | cpu")->capture_default_str();
  app.add_option("--precision", precision, "bf16 | fp32")->capture_default_str();
  app.add_option("--batch", batch, "global batch")->capture_default_str();
  app.add_option("--micro", micro, "micro-batch (0: the global batch)")->capture_default_str();
  app.add_option("--steps", steps, "timed steps")->capture_default_str();
  app.add_option("--warmup", warmup, "untimed steps first")->capture_default_str();
  app.add_option("--samples", samples_n, "synthetic samples in memory (0: 4 x batch)")->capture_default_str();
  app.add_option("--resolution", resolution, "occupancy side R")->capture_default_str();
  app.add_option("--peak-tflops", peak, "the device's bf16 matmul ceiling for the MFU column (H200: ~780 measured)")
      ->capture_default_str();
  app.add_flag("--activation-checkpointing", checkpointing, "per-block activation checkpointing of the flow model");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    using namespace simu::training;
    if (device == "cuda" && !torch::cuda::is_available()) {
      fmt::print("bench_train_stage1: skipped: no CUDA device (use --device cpu for a smoke run)\n");
      return 0;
    }
    const std::string out = (std::filesystem::temp_directory_path() / "bench_train_stage1").string();
    if (micro <= 0) micro = batch;
    auto cfg = Stage1Config::load(config, {"train.steps=" + std::to_string(warmup + steps), "train.device=" + device,
                                           "train.precision=" + precision, "data.global_batch=" + std::to_string(batch),
                                           "data.micro_batch=" + std::to_string(micro), "run.out_dir=" + out,
                                           "run.checkpoint_every=0", "targets.kind=random_linear",
                                           std::string("train.activation_checkpointing=") + (checkpointing ? "true" : "false")});
    const torch::Device dev = rank_device(device, 0);
    const auto gen_cfg = simu::models::GeneratorConfig::from_official_file(cfg.model.generator);
    const auto emb_cfg = simu::models::CondEmbedderConfig::load(cfg.model.embedder);
    // Input sizes from the embedder: the largest ViT input and the point-map input.
    int64_t S = 0, P = 0;
    for (const auto& e : emb_cfg.embedders)
      if (e.kind == simu::models::CondEmbedderEntry::Kind::kDino) S = std::max(S, e.dino.input_size);
      else P = std::max(P, e.point.input_size);
    auto samples = synthetic_stage1_samples(samples_n > 0 ? samples_n : 4 * batch, S, P, resolution, 1);
    auto model = make_stage1_model(cfg.model.generator, cfg.model.embedder, "", dev, cfg.train.seed);
    auto targets = make_shape_targets(cfg.targets, gen_cfg.backbone.latent("shape"), resolution, dev, cfg.file);
    const auto counts = count_parameters(model);
    const auto flops = stage1_flops(gen_cfg, emb_cfg);
    auto comm = make_solo_communicator();
    Trainer tr(cfg, std::make_unique<FlowObjective>(cfg, model, samples, targets, dev), *comm, dev);
    for (int64_t s = 0; s < warmup; ++s) tr.step();
    if (dev.is_cuda()) torch::cuda::synchronize();
    const auto t0 = std::chrono::steady_clock::now();
    double loss = 0;
    for (int64_t s = 0; s < steps; ++s) loss = tr.step().loss;
    if (dev.is_cuda()) torch::cuda::synchronize();
    const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const double per_s = static_cast<double>(batch * steps) / secs;
    const double tflops = per_s * flops.training_per_sample() / 1e12;
    fmt::print("config {}: flow model {:.3f} M parameters ({} ch, {} blocks), embedder {:.3f} M, {} condition tokens\n",
               config, counts.flow / 1e6, gen_cfg.backbone.model_channels, gen_cfg.backbone.num_blocks,
               counts.embedder / 1e6, flops.condition_tokens);
    fmt::print("forward GFLOP per sample: flow {:.3f}, embedder {:.3f}; training ~{:.3f} GFLOP per sample (3x)\n",
               flops.flow_forward / 1e9, flops.embedder_forward / 1e9, flops.training_per_sample() / 1e9);
    fmt::print("| device | precision | batch | micro | steps | s/step | samples/s | TFLOP/s | MFU vs {:.0f} | loss |\n"
               "|---|---|---|---|---|---|---|---|---|---|\n| {} | {} | {} | {} | {} | {:.4f} | {:.0f} | {:.2f} | {:.1f}% | {:.4f} |\n",
               peak, dev.str(), precision, batch, micro, steps, secs / steps, per_s, tflops, 100 * tflops / peak, loss);
    return 0;
  });
}
