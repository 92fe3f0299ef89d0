// bench_stage1: speed of the Stage-1 flow model (real size, random weights; --precision fp16 = the
// released inference precision, the default; bf16 = the training recipe) on CUDA.
// Measures one forward at batch 2 (the CFG pair) and a full CFG sampling (25 steps by default) at
// condition lengths 7528 (the released embedder: 4 x 1,370 + 2 x 1,024 tokens per object, the headline)
// and 2800: median milliseconds, achieved TFLOP/s (analytic matmul FLOPs, see
// simu::models::flow_forward_flops) and peak allocated memory; plus the plain bf16 matmul rate of the
// device for reference. On a machine without CUDA it says so (or runs tiny with --device cpu --small).
#include <ATen/CPUGeneratorImpl.h>
#include <c10/cuda/CUDACachingAllocator.h>
#include <fmt/ranges.h>
#include <torch/cuda.h>

#include <algorithm>
#include <chrono>

#include "common/source_dir.h"
#include "common/cli.h"
#include "gpu_profile.h"
#include "common/error.h"
#include "common/log.h"
#include "models/generator.h"
#include "models/precision.h"

namespace {

void sync(const torch::Device& d) {
  if (d.is_cuda()) torch::cuda::synchronize(d.index() < 0 ? 0 : d.index());
}

// Median wall time in ms of fn over `iters` runs after `warmup` runs (device synchronized around each).
double time_ms(const torch::Device& d, int warmup, int iters, const std::function<void()>& fn) {
  for (int i = 0; i < warmup; ++i) fn();
  sync(d);
  std::vector<double> ms;
  for (int i = 0; i < iters; ++i) {
    sync(d);
    const auto t0 = std::chrono::steady_clock::now();
    fn();
    sync(d);
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
  std::sort(ms.begin(), ms.end());
  return ms[ms.size() / 2];
}

void reset_peak(const torch::Device& d) {
  if (d.is_cuda()) c10::cuda::CUDACachingAllocator::resetPeakStats(d.index() < 0 ? 0 : d.index());
}
double peak_gib(const torch::Device& d) {
  if (!d.is_cuda()) return 0;
  const auto s = c10::cuda::CUDACachingAllocator::getDeviceStats(d.index() < 0 ? 0 : d.index());
  return static_cast<double>(s.allocated_bytes[0].peak) / (1024.0 * 1024.0 * 1024.0);
}

struct Row {
  int64_t cond_len;
  std::string what;
  double ms, tflops, peak;
};

// What every measurement shares.
struct Bench {
  simu::models::Generator gen;
  torch::Device dev;
  simu::models::Precision prec;
  int warmup, iters, sample_iters, steps;
  double cfg;
  bool profile;
  std::vector<std::string> captures;
  std::vector<Row> rows;
  std::vector<int> cache_intervals;         // --step-cache: cached sampling rows, one per interval
  simu::models::StepCacheOptions cache_opts;  // their other settings
};

// Plain bf16 matmul rate of this device (TFLOP/s).
double matmul_ceiling(const torch::Device& dev) {
  const int64_t n = 8192;
  auto a = torch::randn({n, n}, torch::TensorOptions().device(dev).dtype(torch::kBFloat16));
  auto b = torch::randn({n, n}, torch::TensorOptions().device(dev).dtype(torch::kBFloat16));
  // Ceiling: the best of 5 batches of 10 back-to-back products (after 20 to warm the clocks), so
  // that host synchronisation does not lower it and the ratios below are not flattered.
  const int reps = 10;
  for (int i = 0; i < 20; ++i) (void)torch::mm(a, b);
  double best_ms = 1e30;
  for (int k = 0; k < 5; ++k)
    best_ms = std::min(best_ms, time_ms(dev, 0, 1, [&] {
                         for (int i = 0; i < reps; ++i) (void)torch::mm(a, b);
                       }) / reps);
  const double mm_tflops = 2.0 * n * n * n / (best_ms * 1e-3) / 1e12;
  fmt::print("bf16 matmul {}^3: {:.3f} ms = {:.1f} TFLOP/s (best of 5 x 10 back-to-back)\n", n, best_ms, mm_tflops);
  return mm_tflops;
}

// One forward at batch 2 (the CFG pair), eager and replayed from a CUDA graph.
void time_forward(Bench& bn, int64_t L, const torch::Tensor& cond1, at::Generator& rng) {
  auto& gen = bn.gen;
  const auto& dev = bn.dev;
  const auto& mc = gen->config().backbone;
  // One forward at batch 2 (the CFG pair: conditional + unconditional).
  {
    auto x = gen->noise(2, rng, dev);
    auto cond = torch::cat({cond1, cond1 * 0}, 0);
    // One t for the pair (as the sampler passes it: [1], broadcast over the batch).
    auto t = torch::full({1}, 500.0, torch::TensorOptions().device(dev));
    c10::optional<torch::Tensor> d;
    if (mc.is_shortcut_model) d = torch::zeros({1}, torch::TensorOptions().device(dev));
    auto fwd = [&] { auto y = gen->backbone()->forward(x, t, cond, d); };
    reset_peak(dev);
    // One autocast region around all runs: the bf16 copies of the weights are made once and cached,
    // as in sampling (Generator::sample keeps one region over all steps).
    simu::models::Autocast ac(bn.prec, dev.is_cuda());
    const double ms = time_ms(dev, bn.warmup, bn.iters, fwd);
    const double flops = simu::models::flow_forward_flops(mc, 2, L);
    bn.rows.push_back({L, "forward B=2", ms, flops / (ms * 1e-3) / 1e12, peak_gib(dev)});
    simu::log::info("cond {}: forward {:.2f} ms", L, ms);
    if (bn.profile && dev.is_cuda()) {
      simu::bench::print_gpu_kernel_profile(fmt::format("forward B=2, cond {}", L), fwd);
      simu::bench::print_gpu_op_profile(fmt::format("forward B=2, cond {}", L), fwd);
    }
    // The same forward replayed from a CUDA graph (as the sampler runs it): no launch gaps.
    if (dev.is_cuda()) {
      simu::models::GraphedForward graphed(gen->backbone(), cond, nullptr);
      auto fwd_graph = [&] { auto y = graphed.run(x, t, d); };
      reset_peak(dev);
      const double gms = time_ms(dev, bn.warmup, bn.iters, fwd_graph);
      bn.rows.push_back({L, "forward B=2, CUDA graph", gms, flops / (gms * 1e-3) / 1e12, peak_gib(dev)});
      simu::log::info("cond {}: forward (CUDA graph) {:.2f} ms", L, gms);
    }
  }
}

// Matrix-product FLOPs of a sampling: one forward per full step (batch 2 where guided), the condition
// keys/values once per batch size (ConditionCache), nothing for the cheap steps of step caching.
double sampling_flops(const simu::models::FlowModelConfig& mc, int64_t L, const std::vector<bool>& guided,
                      const std::vector<bool>& full) {
  double flops = 0;
  bool any_guided = false, any_plain = false;
  for (size_t i = 0; i < guided.size(); ++i) {
    if (!full[i]) continue;
    const int64_t b = guided[i] ? 2 : 1;
    flops += simu::models::flow_forward_flops(mc, b, L) - simu::models::flow_condition_kv_flops(mc, b, L);
    (guided[i] ? any_guided : any_plain) = true;
  }
  if (any_guided) flops += simu::models::flow_condition_kv_flops(mc, 2, L);
  if (any_plain) flops += simu::models::flow_condition_kv_flops(mc, 1, L);
  return flops;
}

// Step-cached sampling (--step-cache k...), eager and with persistent CUDA graphs, after the full
// sampling rows: the speed-up predicted from the FLOPs of the full evaluations it skips, and measured.
void time_cached_sampling(Bench& bn, int64_t L, const torch::Tensor& cond1, const simu::models::Latents& x0,
                          simu::models::SampleOptions o, double full_flops) {
  auto& gen = bn.gen;
  const auto& dev = bn.dev;
  // The full sampling's medians (eager, graphs) measured just before, for the ratios.
  double full_eager = 0, full_graph = 0;
  for (const auto& r : bn.rows)
    if (r.cond_len == L && r.what.rfind("sample", 0) == 0 && r.what.find("first call") == std::string::npos)
      (r.what.find("eager") != std::string::npos ? full_eager : full_graph) = r.ms;
  for (const int k : bn.cache_intervals) {
    o.step_cache = bn.cache_opts;
    o.step_cache.enabled = true;
    o.step_cache.interval = k;
    auto run = [&] { auto y = gen->sample(cond1, x0, o); };
    for (const bool graphs : {false, true}) {
      if (graphs && !dev.is_cuda()) continue;
      o.cuda_graphs = graphs;
      reset_peak(dev);
      const double ms = time_ms(dev, 1, bn.sample_iters, run);
      const auto& st = gen->step_cache_stats();
      const double flops = sampling_flops(gen->config().backbone, L, st.guided, st.full);
      const double base = graphs ? full_graph : full_eager;
      bn.rows.push_back({L,
                         fmt::format("sample {} steps CFG {}, step cache k={} ({} of {} full; predicted x{:.2f}, "
                                     "measured x{:.2f}), {}",
                                     o.steps, bn.cfg, k, st.full_steps(), o.steps, full_flops / flops,
                                     base > 0 ? base / ms : 0.0, graphs ? "persistent CUDA graphs" : "eager"),
                         ms, flops / (ms * 1e-3) / 1e12, peak_gib(dev)});
      simu::log::info("cond {}: step-cached sampling k={} ({}) {:.1f} ms", L, k, graphs ? "graphs" : "eager", ms);
    }
    gen->reverse_fn->clear_graphs();
  }
}

// Full 25-step CFG sampling: eager, then each graph capture scheme (first call and persistent replays).
void time_sampling(Bench& bn, int64_t L, const torch::Tensor& cond1, at::Generator& rng) {
  auto& gen = bn.gen;
  const auto& dev = bn.dev;
  const auto& mc = gen->config().backbone;
  // Full sampling with CFG (batch 1 -> batch-2 forwards while guided).
  {
    auto o = simu::models::SampleOptions::from(gen->config());
    o.steps = bn.steps;
    o.cfg_strength = bn.cfg;
    o.precision = bn.prec;
    auto x0 = gen->noise(1, rng, dev);
    auto run = [&] { auto y = gen->sample(cond1, x0, o); };
    // FLOPs: one forward per step, batch 2 where CFG is active.
    const auto grid = gen->time_grid(o.steps, o.rescale_t, o.reversed_timestamp);
    std::vector<bool> guided(o.steps);
    for (int i = 0; i < o.steps; ++i)
      guided[i] = simu::models::guidance_active(grid[i] * gen->config().time_scale, o.cfg_strength, o.cfg_interval);
    const double flops = sampling_flops(mc, L, guided, std::vector<bool>(o.steps, true));
    // Eager launches and persistent CUDA graphs (captured in the first call, replayed by every later
    // one: the timed calls; the first call's time is its own row).
    // Graph captures: "overlap" (the default: the first evaluation eager, the capture recorded while
    // the device runs it) and/or "sync" (the earlier host-synchronous capture), --captures.
    std::vector<std::string> modes = {"eager"};
    if (dev.is_cuda())
      for (const auto& c : bn.captures) modes.push_back(c);
    for (const auto& mode : modes) {
      const bool graphs = mode != "eager";
      o.cuda_graphs = graphs;
      simu::models::GraphedForward::set_overlapped_capture(mode != "sync");
      reset_peak(dev);
      if (graphs) {
        gen->reverse_fn->clear_graphs();
        const double first = time_ms(dev, 0, 1, run);
        bn.rows.push_back({L, fmt::format("sample {} steps CFG {}, first call ({} capture)", o.steps, bn.cfg, mode), first,
                        flops / (first * 1e-3) / 1e12, peak_gib(dev)});
      }
      const double ms = time_ms(dev, graphs ? 0 : 1, bn.sample_iters, run);
      bn.rows.push_back({L, fmt::format("sample {} steps CFG {}{}", o.steps, bn.cfg, graphs ? ", persistent CUDA graphs (" + mode + ")" : ", eager"), ms,
                      flops / (ms * 1e-3) / 1e12, peak_gib(dev)});
      simu::log::info("cond {}: sampling ({}) {:.1f} ms", L, mode, ms);
      // Profiled once per mode: graph replays show their kernels too (CUPTI), without launch gaps.
      if (bn.profile && dev.is_cuda()) {
        simu::bench::print_gpu_kernel_profile(fmt::format("sample {} steps, cond {}, {}", o.steps, L, mode), run, 12);
        // The ATen call chains of a 2-step sampling call (the per-op table is quadratic in the op count).
        if (!graphs) {
          auto o2 = o;
          o2.steps = 2;
          simu::bench::print_gpu_op_profile(fmt::format("sample 2 steps, cond {}, eager", L),
                                            [&] { auto y = gen->sample(cond1, x0, o2); }, 40);
        }
      }
    }
    simu::models::GraphedForward::set_overlapped_capture(true);
    gen->reverse_fn->clear_graphs();  // the next condition length starts without them
    if (!bn.cache_intervals.empty()) time_cached_sampling(bn, L, cond1, x0, o, flops);
  }
}

// --step-cache K... and the settings of those rows.
void add_step_cache_options(CLI::App& app, std::vector<int>& intervals, simu::models::StepCacheOptions& o) {
  app.add_option("--step-cache", intervals,
                 "also time step-cached sampling (models/step_cache.h), one row pair (eager, graphs) per full-evaluation "
                 "interval k given, e.g. --step-cache 2 3")
      ->check(CLI::PositiveNumber);
  app.add_option("--step-cache-order", o.order, "step caching: shape extrapolation order 0 | 1 | 2")->capture_default_str();
  app.add_option("--step-cache-momentum", o.pose_momentum, "step caching: pose momentum in [0, 1]")->capture_default_str();
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Benchmark the Stage-1 flow model: forward at batch 2 and full CFG sampling (random weights)"};
  std::string precision = "fp16";
  std::string config = simu::source_dir() + "/configs/stage1_real.yaml", device = "cuda";
  std::vector<int64_t> cond_lens = {7528, 2800};  // released embedder first
  int steps = 25, iters = 5, sample_iters = 3, warmup = 2;
  double cfg = 7.0;
  bool small = false, fp32 = false, profile = false, one_stream = false, sampling_one_stream = false;
  std::string sdp = "default";
  std::vector<std::string> captures = {"overlap"};
  std::vector<int> cache_intervals;
  simu::models::StepCacheOptions cache_opts;
  app.add_option("--config", config, "generator config (official or project layout)")->capture_default_str();
  app.add_option("--cond-lens", cond_lens, "condition lengths")->capture_default_str();
  app.add_option("--steps", steps, "sampling steps")->capture_default_str();
  app.add_option("--cfg-strength", cfg, "CFG strength (interval from the config)")->capture_default_str();
  app.add_option("--iters", iters, "timed forwards (median)")->capture_default_str();
  app.add_option("--sample-iters", sample_iters, "timed samplings (median)")->capture_default_str();
  app.add_option("--warmup", warmup, "untimed warm-up runs")->capture_default_str();
  app.add_option("--device", device, "cuda | cuda:N | cpu (cpu needs --small)")->capture_default_str();
  app.add_flag("--small", small, "use configs/stage1_small.yaml and short conditions (CPU smoke run)");
  app.add_option("--precision", precision, "autocast precision on CUDA: fp16 (released inference) | bf16 (training) | fp32")
      ->check(CLI::IsMember({"fp16", "bf16", "fp32"}))->capture_default_str();
  app.add_flag("--fp32", fp32, "same as --precision fp32");
  app.add_flag("--profile", profile, "print the GPU kernels of one forward by time (Kineto/CUPTI)");
  app.add_flag("--one-stream", one_stream, "run the pose stream on the same CUDA stream as the shape stream");
  app.add_flag("--sampling-one-stream", sampling_one_stream,
               "run the pose stream on the shape stream's CUDA stream when the condition's keys/values are cached "
               "(sampling), as before the overlap was measured faster there");
  std::string stream_lag = "default";
  app.add_option("--stream-lag", stream_lag,
                 "pose stream on one side CUDA stream joined once per forward (on) or at every block (off); "
                 "default: the model's")
      ->check(CLI::IsMember({"default", "on", "off"}))->capture_default_str();
  std::string few_query = "default";
  app.add_option("--side-few-query", few_query,
                 "attention of the pose stream's few queries on the side stream: flash (keys split over thread blocks) | "
                 "default (the model's: PyTorch's choice)")
      ->check(CLI::IsMember({"flash", "default"}))->capture_default_str();
  app.add_option("--sdp-backend", sdp, "attention backend tried first: default | flash | cudnn | efficient")
      ->check(CLI::IsMember({"default", "flash", "cudnn", "efficient"}))->capture_default_str();
  app.add_option("--captures", captures, "graph capture schemes timed after eager sampling: overlap (default) | sync")
      ->check(CLI::IsMember({"overlap", "sync"}))->capture_default_str();
  add_step_cache_options(app, cache_intervals, cache_opts);
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    const torch::Device dev(device);
    if (!simu::bench::device_usable("bench_stage1", dev, small)) return 0;
    if (small) {
      config = simu::source_dir() + "/configs/stage1_small.yaml";
      cond_lens = {10, 30};
      steps = std::min(steps, 4);
    }
    torch::NoGradGuard no_grad;
    // Attention backend order (PyTorch's default tries flash, then memory-efficient, math, cuDNN).
    if (sdp != "default") {
      using B = at::SDPBackend;
      const B first = sdp == "flash" ? B::flash_attention : sdp == "cudnn" ? B::cudnn_attention : B::efficient_attention;
      std::vector<int64_t> order{static_cast<int64_t>(first)};
      for (B b : {B::flash_attention, B::cudnn_attention, B::efficient_attention, B::math, B::overrideable})
        if (b != first) order.push_back(static_cast<int64_t>(b));
      at::globalContext().setSDPUseCuDNN(true);
      at::globalContext().setSDPPriorityOrder(order);
      fmt::print("attention backend order: {} first\n", sdp);
    }
    auto gen = simu::models::load_generator(config, "", dev, common.sets);
    const auto& mc = gen->config().backbone;
    if (one_stream) gen->backbone()->set_stream_overlap(false);
    if (sampling_one_stream) gen->backbone()->set_stream_overlap_cached(false);
    if (few_query == "flash") gen->backbone()->set_side_few_query_flash(true);
    if (stream_lag != "default") gen->backbone()->set_stream_lag(stream_lag == "on");
    if (fp32) precision = "fp32";
    const auto prec = dev.is_cuda() ? simu::models::parse_precision(precision, dev, "--precision") : simu::models::Precision::kFp32;
    fmt::print("device {}, config {}\nmodel: {} channels, {} blocks, {} heads, streams [{}], cond {} ch; {}\n", device,
               config, mc.model_channels, mc.num_blocks, mc.num_heads, fmt::join(mc.stream_names(), ", "), mc.cond_channels,
               prec == simu::models::Precision::kFp32
                   ? std::string("fp32")
                   : simu::models::precision_name(prec) + " autocast (fp32 weights, fp32 norms/residual)");
    fmt::print("pose stream: {}, {}, side few-query attention {}\n",
               one_stream ? "same CUDA stream" : sampling_one_stream ? "side stream (not when sampling)" : "side stream",
               gen->backbone()->stream_lag() ? "lagged (one join per forward)" : "joined at every block", few_query);
    fmt::print("FLOPs (2 per multiply-add, per sample, per block and stream of T tokens, C channels, Lc condition tokens):\n"
               "  self qkv 6TC^2 + out 2TC^2 + attention 4*T*Tk*C (Tk = T for shape, all tokens for pose)\n"
               "  + cross q 2TC^2 + kv 4*Lc*Cc*C + out 2TC^2 + attention 4*T*Lc*C + MLP 4*T*C*(ratio*C); + adaLN, latent io\n");

    const double mm_tflops = dev.is_cuda() ? matmul_ceiling(dev) : 0;
    cache_opts.validate("step caching (--step-cache-*): ");
    Bench bn{gen, dev, prec, warmup, iters, sample_iters, steps, cfg, profile, captures, {}, cache_intervals, cache_opts};
    auto rng = at::make_generator<at::CPUGeneratorImpl>(0);
    for (const int64_t L : cond_lens) {
      auto cond1 = torch::randn({1, L, mc.cond_channels}, rng).to(dev);
      time_forward(bn, L, cond1, rng);
      time_sampling(bn, L, cond1, rng);
    }
    const auto& rows = bn.rows;
    fmt::print("\n| cond tokens | run | ms (median) | TFLOP/s | % of matmul rate | peak alloc GiB |\n|---|---|---|---|---|---|\n");
    for (const auto& r : rows)
      fmt::print("| {} | {} | {:.2f} | {:.1f} | {} | {:.2f} |\n", r.cond_len, r.what, r.ms, r.tflops,
                 mm_tflops > 0 ? fmt::format("{:.0f}%", 100 * r.tflops / mm_tflops) : "-", r.peak);
    return 0;
  });
}
