// bench_embedder: GPU time of the Stage-1 condition (both DINOv2 ViT-L/14-reg4 embedders at 518 px,
// the point-map embedder and the fuser) per object, at real size with random weights.
//
//   ./build/bench_embedder                      # bf16, batches 1 2 4 8
//   ./build/bench_embedder --dtype fp32 --batch 1 --iters 20
//   ./build/bench_embedder --config configs/cond_embedder_sam3d_stage1.yaml
//
// Prints a table: batch, ms per forward, ms per object, tokens, peak GPU memory; then the share of
// each embedder (its inputs alone, no fuser) at batch 1. Needs a CUDA device.
#include <c10/cuda/CUDACachingAllocator.h>
#include <fmt/format.h>
#include <fmt/ranges.h>

#include <chrono>

#include "common/cli.h"
#include "common/error.h"
#include "models/cond_embedder.h"

namespace {

using Clock = std::chrono::steady_clock;

// Random inputs of the official kwarg names at 518 px (point maps with 10% invalid points).
std::map<std::string, torch::Tensor> make_inputs(int64_t B, int64_t size, torch::ScalarType dt) {
  auto o = torch::TensorOptions().device(torch::kCUDA).dtype(dt);
  std::map<std::string, torch::Tensor> in;
  in["image"] = torch::rand({B, 3, size, size}, o);
  in["rgb_image"] = torch::rand({B, 3, size, size}, o);
  in["mask"] = (torch::rand({B, 1, size, size}, o) > 0.5).to(dt);
  in["rgb_image_mask"] = (torch::rand({B, 1, size, size}, o) > 0.5).to(dt);
  for (const char* k : {"pointmap", "rgb_pointmap"}) {
    auto p = torch::randn({B, 3, size, size}, o);
    in[k] = torch::where(torch::rand({B, 1, size, size}, o) < 0.1, torch::full_like(p, NAN), p);
  }
  return in;
}

// Mean milliseconds of fn over iters runs after warmup runs.
template <typename Fn>
double time_ms(Fn&& fn, int warmup, int iters) {
  for (int i = 0; i < warmup; ++i) fn();
  torch::cuda::synchronize();
  const auto t0 = Clock::now();
  for (int i = 0; i < iters; ++i) fn();
  torch::cuda::synchronize();
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count() / iters;
}

double peak_gib() {
  const auto stats = c10::cuda::CUDACachingAllocator::getDeviceStats(0);
  return static_cast<double>(stats.allocated_bytes[0].peak) / (1024.0 * 1024.0 * 1024.0);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"GPU time per object of the Stage-1 condition embedder (all embedders + fuser), real size, random weights"};
  std::string config_path, dtype_name = "bf16";
  std::vector<int64_t> batches = {1, 2, 4, 8};
  int warmup = 3, iters = 10;
  int64_t input_size = 518;
  app.add_option("--config", config_path, "condition embedder config (default: the built-in SAM 3D Stage-1 one)");
  app.add_option("--dtype", dtype_name, "bf16, fp16 or fp32")->check(CLI::IsMember({"bf16", "fp16", "fp32"}));
  app.add_option("--batch", batches, "batch sizes (objects per forward)");
  app.add_option("--warmup", warmup, "untimed runs first");
  app.add_option("--iters", iters, "timed runs");
  app.add_option("--input-size", input_size, "side of the random input images and point maps");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    if (!torch::cuda::is_available())
      simu::fail_hint("run it on the GPU machine", "bench_embedder needs a CUDA device and none is available");
    const auto dt = dtype_name == "bf16" ? torch::kBFloat16 : dtype_name == "fp16" ? torch::kFloat16 : torch::kFloat32;
    const auto cfg = config_path.empty() ? simu::models::CondEmbedderConfig::sam3d_stage1()
                                         : simu::models::CondEmbedderConfig::load(config_path, common.sets);
    torch::manual_seed(0);
    fmt::print("building the condition embedder ({} tokens x {} channels per object)...\n", cfg.num_tokens(),
               cfg.embed_dims());
    simu::models::CondEmbedder model(cfg);
    int64_t params = 0;
    for (const auto& p : model->parameters()) params += p.numel();
    model->to(torch::kCUDA, dt);
    model->eval();
    torch::NoGradGuard no_grad;
    fmt::print("{:.1f} M parameters, dtype {}, device {}\n\n", params / 1e6, dtype_name,
               torch::cuda::device_count() > 0 ? "cuda:0" : "?");

    // Whole condition per batch size.
    fmt::print("{:>6} {:>14} {:>14} {:>8} {:>12}\n", "batch", "ms/forward", "ms/object", "tokens", "peak GiB");
    for (const int64_t B : batches) {
      auto in = make_inputs(B, input_size, dt);
      c10::cuda::CUDACachingAllocator::resetPeakStats(0);
      torch::Tensor out;
      const double ms = time_ms([&] { out = model->forward(in); }, warmup, iters);
      SIMU_CHECK(out.size(0) == B && out.size(1) == cfg.num_tokens(), "unexpected output [{}]",
                 fmt::join(out.sizes(), ", "));
      fmt::print("{:>6} {:>14.2f} {:>14.2f} {:>8} {:>12.2f}\n", B, ms, ms / B, out.size(1), peak_gib());
    }

    // Share of each embedder at batch 1 (its inputs, no projection).
    fmt::print("\nper embedder, batch 1 (embedder alone, all its inputs):\n");
    fmt::print("{:<48} {:>12}\n", "embedder (inputs)", "ms/object");
    auto in = make_inputs(1, input_size, dt);
    for (size_t i = 0; i < cfg.embedders.size(); ++i) {
      std::vector<std::string> names;
      for (const auto& [k, g] : cfg.embedders[i].inputs) names.push_back(k);
      const double ms = time_ms(
          [&] {
            for (const auto& k : names) (void)model->embed(i, in.at(k));
          },
          warmup, iters);
      fmt::print("{:<48} {:>12.2f}\n", fmt::format("{} ({})", cfg.embedders[i].name, fmt::join(names, ", ")), ms);
    }
    return 0;
  });
}
