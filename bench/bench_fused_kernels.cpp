// bench_fused_kernels: the flow model's q/k RMS-norm split kernels alone, at the real model's shapes
// (16 heads of 64 channels; sampling: fp16, batch 2 (CFG), 4,096 shape tokens and 4 pose tokens;
// training: bf16, batch 4 (micro 2, both members), 4,096 shape tokens), through the 4-byte kernels
// (set_split_qkv_wide(false)) and the 16-byte ones, against the device's own copy rate of the same
// bytes. Method: GPU time per call = the CUPTI durations (Kineto) of the GPU activities of `iters`
// back-to-back calls after `warmup` ones, divided by iters; bytes = what a call must read and write
// (forward: q, k, v in and out, 6 x B L H D x 2 bytes; backward: q, k and the three gradients in,
// dqkv out, 8 x B L H D x 2 bytes; the fp32 gammas are left out); the ceiling is a device-to-device
// tensor copy of the training forward's bytes (half read, half written). Prints a table and, from
// the measured times, the saving per 25-step sampling (600 shape + 600 pose calls: 24 blocks x 25
// steps) and per FM-DPO step at micro 2 (48 forwards, 24 backwards).
#include <fmt/format.h>
#include <torch/csrc/autograd/profiler_kineto.h>
#include <torch/cuda.h>

#include <functional>
#include <set>

#include "common/cli.h"
#include "models/fused_ops.h"

namespace {

namespace fused = simu::models::fused;

// Mean GPU time in microseconds of one call of fn: CUPTI activity durations over iters calls.
double gpu_us(const std::function<void()>& fn, int warmup, int iters) {
  namespace prof = torch::autograd::profiler;
  namespace impl = torch::profiler::impl;
  for (int i = 0; i < warmup; ++i) fn();
  const impl::ProfilerConfig cfg(impl::ProfilerState::KINETO);
  const std::set<impl::ActivityType> acts{impl::ActivityType::CPU, impl::ActivityType::CUDA};
  prof::prepareProfiler(cfg, acts);
  torch::cuda::synchronize();
  prof::enableProfiler(cfg, acts);
  for (int i = 0; i < iters; ++i) fn();
  torch::cuda::synchronize();
  const auto result = prof::disableProfiler();
  double ns = 0;
  for (const auto& e : result->events())
    if (e.deviceType() == c10::DeviceType::CUDA) ns += static_cast<double>(e.durationNs());
  return ns * 1e-3 / iters;
}

struct Row {
  std::string what;
  double bytes, narrow_us, wide_us;
};

// Forward and backward rows of one split shape [B, L, 3, H, D] in dt; k and v land in a key/value buffer
// of L + extra tokens at token offset `extra` (the inference layout); backward only when `backward`.
void split_rows(std::vector<Row>& rows, const std::string& what, torch::ScalarType dt, int64_t B, int64_t L, int64_t H,
                int64_t D, int64_t extra, bool backward, int warmup, int iters) {
  const auto opt = torch::TensorOptions().device(torch::kCUDA).dtype(dt);
  const auto f32 = opt.dtype(torch::kFloat32);
  auto qkv = (torch::randn({B, L, 3, H, D}, f32) * 4).to(dt);
  auto gq = 1 + 0.1 * torch::randn({H, D}, f32), gk = 1 + 0.1 * torch::randn({H, D}, f32);
  auto q = torch::empty({B, L, H, D}, opt);
  auto k_buf = torch::empty({B, L + extra, H, D}, opt), v_buf = torch::empty_like(k_buf);
  auto k = k_buf.narrow(1, extra, L), v = v_buf.narrow(1, extra, L);
  const double n = static_cast<double>(B * L * H * D);
  auto time_both = [&](const std::function<void()>& fn) {
    fused::set_split_qkv_wide(false);
    const double a = gpu_us(fn, warmup, iters);
    fused::set_split_qkv_wide(true);
    return std::make_pair(a, gpu_us(fn, warmup, iters));
  };
  auto [fn_us, fw_us] = time_both([&] { fused::split_qkv_rms_norm(qkv, gq, gk, 8.0, q, k, v); });
  rows.push_back({fmt::format("{} forward {} [{}, {}, 3, {}, {}]", what, dt == torch::kHalf ? "fp16" : "bf16", B, L, H, D),
                  6 * n * 2, fn_us, fw_us});
  if (!backward) return;
  // Incoming gradients as attention's backward hands them: [B, H, L, D] tensors seen as [B, L, H, D].
  auto g = [&] { return torch::randn({B, H, L, D}, f32).to(dt).permute({0, 2, 1, 3}); };
  auto dq = g(), dk = g(), dv = g();
  auto [bn_us, bw_us] = time_both([&] { (void)fused::split_qkv_rms_norm_backward(qkv, gq, gk, 8.0, dq, dk, dv); });
  rows.push_back({fmt::format("{} backward {} (gradients [B, H, L, D] permuted)", what, dt == torch::kHalf ? "fp16" : "bf16"),
                  8 * n * 2, bn_us, bw_us});
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Time the fused q/k RMS-norm split kernels alone at the real model's shapes: 4-byte vs 16-byte kernels, TB/s"};
  std::string device = "cuda";
  int warmup = 5, iters = 100;
  int64_t tokens = 4096, pose_tokens = 4, heads = 16, head_dim = 64, sample_batch = 2, train_batch = 4;
  app.add_option("--iters", iters, "timed calls per kernel (mean GPU time)")->capture_default_str();
  app.add_option("--warmup", warmup, "untimed calls before")->capture_default_str();
  app.add_option("--tokens", tokens, "shape tokens (16^3 / 1 = 4096 for the real model)")->capture_default_str();
  app.add_option("--pose-tokens", pose_tokens, "pose stream tokens")->capture_default_str();
  app.add_option("--heads", heads, "attention heads")->capture_default_str();
  app.add_option("--head-dim", head_dim, "channels per head (64, 128 or 256)")->capture_default_str();
  app.add_option("--sample-batch", sample_batch, "sampling batch (2 = CFG's pair)")->capture_default_str();
  app.add_option("--train-batch", train_batch, "training batch (micro 2 x both members = 4)")->capture_default_str();
  app.add_option("--device", device, "cuda only (a kernel benchmark)")->capture_default_str();
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    const torch::Device dev(device);
    // A missing device or kernels is not an error for a benchmark: say so and stop.
    if (!dev.is_cuda() || !torch::cuda::is_available() || !fused::compiled()) {
      fmt::print("bench_fused_kernels times CUDA kernels: needs a CUDA device (--device {}, available: {}) and a build "
                 "with nvcc (kernels compiled: {})\n", device, torch::cuda::is_available(), fused::compiled());
      return 0;
    }
    torch::manual_seed(0);
    // The ceiling: a device-to-device copy of the training forward's bytes (read + written).
    const int64_t copy_elems = 3 * train_batch * tokens * heads * head_dim;
    auto src = torch::randn({copy_elems}, torch::TensorOptions().device(dev)).to(torch::kBFloat16), dst = torch::empty_like(src);
    const double copy_us = gpu_us([&] { dst.copy_(src); }, warmup, iters);
    const double copy_tbs = 2.0 * copy_elems * 2 / (copy_us * 1e-6) / 1e12;
    fmt::print("device copy of {:.1f} MB (read + write {:.1f} MB): {:.1f} us = {:.2f} TB/s (the ceiling below)\n",
               copy_elems * 2 / 1e6, 2.0 * copy_elems * 2 / 1e6, copy_us, copy_tbs);
    std::vector<Row> rows;
    split_rows(rows, "sampling shape", torch::kHalf, sample_batch, tokens, heads, head_dim, pose_tokens, false, warmup, iters);
    split_rows(rows, "sampling pose", torch::kHalf, sample_batch, pose_tokens, heads, head_dim, 0, false, warmup, iters);
    split_rows(rows, "training", torch::kBFloat16, train_batch, tokens, heads, head_dim, 0, true, warmup, iters);
    fmt::print("\n| call | MB moved | 4-byte us | TB/s | % of copy | 16-byte us | TB/s | % of copy | speed-up |\n"
               "|---|---|---|---|---|---|---|---|---|\n");
    for (const auto& r : rows) {
      auto tbs = [&](double us) { return r.bytes / (us * 1e-6) / 1e12; };
      fmt::print("| {} | {:.1f} | {:.1f} | {:.2f} | {:.0f}% | {:.1f} | {:.2f} | {:.0f}% | {:.2f}x |\n", r.what, r.bytes / 1e6,
                 r.narrow_us, tbs(r.narrow_us), 100 * tbs(r.narrow_us) / copy_tbs, r.wide_us, tbs(r.wide_us),
                 100 * tbs(r.wide_us) / copy_tbs, r.narrow_us / r.wide_us);
    }
    // Savings per sampling (600 shape + 600 pose calls) and per FM-DPO step at micro 2 (48 forwards, 24 backwards).
    auto saved = [&](size_t i, double calls) { return calls * (rows[i].narrow_us - rows[i].wide_us) * 1e-3; };
    fmt::print("\nsaved per 25-step sampling: {:.2f} ms (shape {:.2f}, pose {:.2f}); per FM-DPO step (micro 2): {:.2f} ms "
               "(forward {:.2f}, backward {:.2f})\n",
               saved(0, 600) + saved(1, 600), saved(0, 600), saved(1, 600), saved(2, 48) + saved(3, 24), saved(2, 48),
               saved(3, 24));
    return 0;
  });
}
