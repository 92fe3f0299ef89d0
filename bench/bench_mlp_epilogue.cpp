// bench_mlp_epilogue: one flow block's frozen MLP (fc1 -> GELU(tanh) -> fc2, the FeedForwardNet module with
// the trainer's settings: frozen weights with bf16/fp16 compute copies, training kernels, CUDA autocast) at
// training size, its ATen path (fused kernels off: addmm, GELU kernel, addmm; backward mm, GELU backward
// kernel, mm) against the cuBLASLt epilogue path (models/mlp_epilogue.h: GELU_AUX_BIAS forward, DGELU
// backward). Per call, in microseconds (host clock around --iters calls after --warmup, synchronised):
//   policy: forward with a graph + backward of the input gradient;  reference: forward without a graph.
// Then the prediction for one FM-DPO step: --blocks x (policy difference + reference difference) (one
// policy forward/backward and one reference forward per block and step, as the step's profile counts them).
#include <fmt/format.h>
#include <torch/cuda.h>

#include <algorithm>
#include <chrono>
#include <functional>

#include "common/cli.h"
#include "common/error.h"
#include "models/flow_model.h"
#include "models/linear.h"
#include "models/mlp_epilogue.h"
#include "models/precision.h"

namespace {

namespace sm = simu::models;

struct Args {
  int64_t rows = 16384;  // micro 2: 2 pairs x 2 members x 4,096 shape tokens
  int64_t channels = 1024;
  double ratio = 4.0;
  std::string precision = "bf16";
  int iters = 50, warmup = 10, blocks = 24;
  int candidates = 0;  // heuristic ranks timed per epilogue product (0: none)
};

// Mean microseconds per call of f over iters calls after warmup calls.
double time_us(const std::function<void()>& f, int iters, int warmup) {
  for (int i = 0; i < warmup; ++i) f();
  torch::cuda::synchronize();
  const auto t0 = std::chrono::steady_clock::now();
  for (int i = 0; i < iters; ++i) f();
  torch::cuda::synchronize();
  return std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count() / iters;
}

// The epilogue products alone at the step's shapes under each heuristic rank 0..n-1 (set_algo_ranks), with
// the plain ATen product of the same shape (no epilogue) as the ceiling they are measured against, and each
// rank's largest difference from rank 0's output (0: the same bits).
void time_candidates(const Args& a, torch::ScalarType dt) {
  namespace me = sm::mlp_epilogue;
  const int64_t K = a.channels, N = static_cast<int64_t>(a.channels * a.ratio);
  const auto o = torch::TensorOptions().device(torch::kCUDA).dtype(dt);
  auto x2 = torch::randn({a.rows, K}, o), w1 = torch::randn({N, K}, o) * 0.03, b1 = torch::randn({N}, o) * 0.1;  // fc1
  auto dy = torch::randn({a.rows, K}, o), w2 = torch::randn({K, N}, o) * 0.03;                                    // fc2^T
  const double flop = 2.0 * static_cast<double>(a.rows) * static_cast<double>(K) * static_cast<double>(N);
  auto rate = [&](double us) { return flop / (us * 1e-6) / 1e12; };
  const double plain_fwd = time_us([&] { (void)at::addmm(b1, x2, w1.t()); }, a.iters, a.warmup);
  const double plain_bwd = time_us([&] { (void)at::mm(dy, w2); }, a.iters, a.warmup);
  fmt::print("\nepilogue products by heuristic rank: rows {}, {} x {}, {}; plain ATen product of the same shape: "
             "fc1 {:.1f} us ({:.0f} TFLOP/s), dY W2 {:.1f} us ({:.0f} TFLOP/s)\n",
             a.rows, K, N, c10::toString(dt), plain_fwd, rate(plain_fwd), plain_bwd, rate(plain_bwd));
  fmt::print("| product | rank asked | rank run (of found) | algorithm | us | TFLOP/s | vs plain | max abs diff vs rank 0 |\n"
             "|---|---|---|---|---|---|---|---|\n");
  torch::Tensor h0, pre0, d0;
  const auto before = me::algo_ranks();
  for (int r = 0; r < a.candidates; ++r) {
    me::set_algo_ranks(r, r);
    auto [h, pre] = me::linear_gelu_aux(x2, w1, b1);
    const auto fi = me::last_algo();
    const double fus = time_us([&] { (void)me::linear_gelu_aux(x2, w1, b1); }, a.iters, a.warmup);
    if (r == 0) h0 = h, pre0 = pre;
    const double fdiff = std::max((h - h0).abs().max().item<double>(), (pre - pre0).abs().max().item<double>());
    fmt::print("| GELU_AUX_BIAS | {} | {} ({}) | {} | {:.1f} | {:.0f} | {:.2f} | {:.3g} |\n", r, fi.rank, fi.found,
               fi.config, fus, rate(fus), plain_fwd / fus, fdiff);
    auto d = me::linear_dgelu(dy, w2, pre0);
    const auto bi = me::last_algo();
    const double bus = time_us([&] { (void)me::linear_dgelu(dy, w2, pre0); }, a.iters, a.warmup);
    if (r == 0) d0 = d;
    fmt::print("| DGELU | {} | {} ({}) | {} | {:.1f} | {:.0f} | {:.2f} | {:.3g} |\n", r, bi.rank, bi.found, bi.config, bus,
               rate(bus), plain_bwd / bus, (d - d0).abs().max().item<double>());
  }
  me::set_algo_ranks(before.first, before.second);
}

void run(const Args& a) {
  // A missing device or cuBLASLt is not an error for a benchmark (as the other benches): say why, run nothing.
  if (!torch::cuda::is_available() || !sm::mlp_epilogue::compiled()) {
    fmt::print("bench_mlp_epilogue times cuBLASLt epilogue products: needs a CUDA device (available: {}) and the "
               "epilogue path (built against cublasLt.h with LibTorch's libcublasLt loaded: {})\n",
               torch::cuda::is_available(), sm::mlp_epilogue::compiled());
    return;
  }
  const auto p = sm::parse_precision(a.precision, torch::kCUDA, "--precision");
  SIMU_CHECK(p != sm::Precision::kFp32, "--precision: bf16 or fp16 (the epilogue path stores 16-bit), got fp32");
  const auto dt = sm::precision_dtype(p);
  torch::manual_seed(0);
  sm::FeedForwardNet ffn(a.channels, a.ratio);
  ffn->to(torch::kCUDA);
  for (auto& q : ffn->parameters()) q.set_requires_grad(false);
  sm::set_compute_copies(*ffn, dt);
  ffn->inference_kernels = false;  // the trainer's set_training_kernels(true)
  const auto o = torch::TensorOptions().device(torch::kCUDA).dtype(dt);
  auto x0 = torch::randn({a.rows, a.channels}, o);  // a fused LayerNorm's 16-bit output
  auto gy = torch::randn({a.rows, a.channels}, o);
  sm::Autocast ac(p);
  fmt::print("bench_mlp_epilogue: rows {}, {} -> {} -> {} channels, {}, {} iters after {} warm-up\n", a.rows, a.channels,
             ffn->fc1->out_features, a.channels, sm::precision_name(p), a.iters, a.warmup);
  fmt::print("| path | policy fwd+bwd (us) | reference fwd (us) | epilogue launches per policy call |\n|---|---|---|---|\n");
  double pol[2] = {0, 0}, ref[2] = {0, 0};
  for (const bool fused : {false, true}) {
    ffn->fused_kernels = fused;
    const auto n0 = sm::mlp_epilogue::launch_count();
    auto x = x0.clone().requires_grad_();
    auto policy = [&] {
      x.mutable_grad() = torch::Tensor();
      ffn->forward(x).backward(gy);
    };
    policy();
    const auto launches = sm::mlp_epilogue::launch_count() - n0;
    pol[fused] = time_us(policy, a.iters, a.warmup);
    ref[fused] = time_us(
        [&] {
          torch::NoGradGuard ng;
          (void)ffn->forward(x0);
        },
        a.iters, a.warmup);
    fmt::print("| {} | {:.1f} | {:.1f} | {} |\n", fused ? "cuBLASLt epilogues" : "ATen (addmm, gelu, addmm)", pol[fused],
               ref[fused], launches);
  }
  const double step_ms = a.blocks * ((pol[0] - pol[1]) + (ref[0] - ref[1])) / 1000.0;
  fmt::print("saving per call: policy {:.1f} us, reference {:.1f} us; per training step ({} blocks, one policy and one "
             "reference forward each): {:.2f} ms\n",
             pol[0] - pol[1], ref[0] - ref[1], a.blocks, step_ms);
  if (a.candidates > 0) time_candidates(a, dt);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"One flow block's frozen MLP at training size: ATen GELU vs cuBLASLt GELU epilogues, per call and per "
               "FM-DPO step"};
  Args a;
  app.add_option("--rows", a.rows, "token rows (micro-batch pairs x 2 members x 4,096 shape tokens)")
      ->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--channels", a.channels, "model channels C (fc1: C -> ratio C)")->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_option("--ratio", a.ratio, "MLP ratio")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--precision", a.precision, "bf16 (training) | fp16")->capture_default_str();
  app.add_option("--iters", a.iters, "timed calls per path")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--warmup", a.warmup, "untimed calls first")->capture_default_str()->check(CLI::NonNegativeNumber);
  app.add_option("--candidates", a.candidates,
                 "also time fc1's GELU_AUX_BIAS and the DGELU product alone under heuristic ranks 0..N-1 "
                 "(mlp_epilogue::set_algo_ranks; 0: skip)")
      ->capture_default_str()->check(CLI::Range(0, 16));
  app.add_option("--blocks", a.blocks, "transformer blocks per step (the real model: 24)")->capture_default_str()
      ->check(CLI::PositiveNumber);
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    run(a);
    return 0;
  });
}
