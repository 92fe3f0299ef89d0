// bench_resample: end-to-end time per resampled object of the in-process Resampler (Stage-1 sampling
// with the official defaults: 25 steps, rescale_t 3, CFG 7 on [0, 500]; sparse-structure decoder;
// marching cubes; pose decode) at batch 1 and batch 8, real-size model with random weights, bf16
// autocast on CUDA. Prints a table: total and per-object milliseconds split into sampling / decoder /
// mesh, and peak allocated GPU memory. Condition tokens are random (the embedder is timed elsewhere).
// Random weights give arbitrary occupancy, so the mesh time is for whatever the weights produce; the
// table reports the occupied voxels per object next to it.
#include <c10/cuda/CUDACachingAllocator.h>
#include <fmt/format.h>
#include <fmt/ranges.h>
#include <torch/cuda.h>

#include <algorithm>
#include <chrono>

#include "common/source_dir.h"
#include "common/cli.h"
#include "gpu_profile.h"
#include "common/error.h"
#include "common/log.h"
#include "pipeline/resample/resampler.h"

namespace {
double peak_gib(const torch::Device& d) {
  if (!d.is_cuda()) return 0;
  const auto s = c10::cuda::CUDACachingAllocator::getDeviceStats(d.index() < 0 ? 0 : d.index());
  return static_cast<double>(s.allocated_bytes[0].peak) / (1024.0 * 1024.0 * 1024.0);
}
}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Benchmark the in-process resampler: time per object at batch 1 and 8 (real size, random weights, bf16)"};
  std::string device = "cuda";
  std::vector<int64_t> batches = {1, 8};
  int64_t cond_len = 2800;
  int iters = 3, steps = 25;
  bool small = false, fp32 = false;
  app.add_option("--batches", batches, "objects per resample call")->capture_default_str();
  app.add_option("--cond-len", cond_len, "condition tokens per object")->capture_default_str();
  app.add_option("--steps", steps, "sampling steps")->capture_default_str();
  app.add_option("--iters", iters, "timed calls per batch size (median)")->capture_default_str();
  app.add_option("--device", device, "cuda | cuda:N | cpu (cpu needs --small)")->capture_default_str();
  app.add_flag("--small", small, "small configs (configs/stage1_small.yaml, tiny decoder): CPU smoke run");
  app.add_flag("--fp32", fp32, "no bf16 autocast");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    const torch::Device dev(device);
    if (!simu::bench::device_usable("bench_resample", dev, small)) return 0;
    simu::resample::ResamplerConfig cfg;  // official sampling defaults, real-size configs
    cfg.device = device;
    cfg.steps = steps;
    cfg.random_weights = true;  // timing only
    cfg.precision = fp32 ? "fp32" : "bf16";  // this benchmark's recorded figures are bf16
    if (small) {
      cfg.generator_config = simu::source_dir() + "/configs/stage1_small.yaml";
      cfg.decoder_config = simu::source_dir() + "/configs/ss_decoder_small.yaml";
      cond_len = std::min<int64_t>(cond_len, 16);
      iters = 1;
    }
    torch::NoGradGuard no_grad;
    simu::resample::Resampler rs(cfg);
    const auto& mc = rs.generator()->config().backbone;
    const auto& dc = rs.decoder()->config();
    fmt::print("device {}; generator {} ({} ch, {} blocks, {} heads, cond {} ch); decoder channels [{}]; {} steps, "
               "rescale_t {}, CFG {} on [{}, {}]; {}; condition {} tokens\n",
               dev.str(), cfg.generator_config, mc.model_channels, mc.num_blocks, mc.num_heads, mc.cond_channels,
               fmt::join(dc.channels, ", "), cfg.steps, cfg.rescale_t, cfg.cfg_strength, cfg.cfg_interval.first,
               cfg.cfg_interval.second, dev.is_cuda() ? cfg.precision + " autocast" : std::string("fp32"), cond_len);

    struct Row {
      int64_t batch;
      double total_ms, sample_ms, decode_ms, mesh_ms, peak;
      int64_t voxels;
    };
    std::vector<Row> rows;
    torch::manual_seed(0);
    for (const int64_t B : batches) {
      std::vector<simu::resample::ResampleRequest> reqs(static_cast<size_t>(B));
      for (auto& r : reqs) r.cond = torch::randn({cond_len, mc.cond_channels});
      // Warm-up (kernels, allocator), then timed calls; median by total time.
      (void)rs.resample(reqs, 0);
      if (dev.is_cuda()) c10::cuda::CUDACachingAllocator::resetPeakStats(dev.index() < 0 ? 0 : dev.index());
      std::vector<Row> runs;
      for (int i = 0; i < iters; ++i) {
        const auto t0 = std::chrono::steady_clock::now();
        const auto res = rs.resample(reqs, static_cast<uint64_t>(i + 1));
        const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        int64_t voxels = 0;
        for (const auto& o : res.objects) voxels += o[0].coords.defined() ? o[0].coords.size(0) : 0;
        runs.push_back({B, ms, res.seconds_sample * 1e3, res.seconds_decode * 1e3, res.seconds_mesh * 1e3, 0, voxels / B});
        simu::log::info("batch {}: call {}/{} {:.1f} ms", B, i + 1, iters, ms);
      }
      std::sort(runs.begin(), runs.end(), [](const Row& a, const Row& b) { return a.total_ms < b.total_ms; });
      Row r = runs[runs.size() / 2];
      r.peak = peak_gib(dev);
      rows.push_back(r);
    }
    fmt::print("\n| objects per call | call ms | per object ms | sampling ms/obj | decoder ms/obj | mesh+pose ms/obj | "
               "voxels/obj | peak alloc GiB |\n|---|---|---|---|---|---|---|---|\n");
    for (const auto& r : rows) {
      const double b = static_cast<double>(r.batch);
      fmt::print("| {} | {:.1f} | {:.1f} | {:.1f} | {:.1f} | {:.1f} | {} | {:.2f} |\n", r.batch, r.total_ms, r.total_ms / b,
                 r.sample_ms / b, r.decode_ms / b, r.mesh_ms / b, r.voxels, r.peak);
    }
    return 0;
  });
}
