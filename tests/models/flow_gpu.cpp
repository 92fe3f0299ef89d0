// Stage-1 flow model on CUDA: fp32 and bf16-autocast forwards against the fp32 CPU fixture, and
// determinism of sampling on the device.
#include <ATen/CPUGeneratorImpl.h>

#include "data/safetensors.h"
#include "models/flow_model_internal.h"
#include "models/generator.h"
#include "models/precision.h"
#include "test_util.h"

namespace {
simu::models::Latents prefixed(const std::map<std::string, torch::Tensor>& io, const std::string& p, torch::Device d) {
  simu::models::Latents out;
  for (const auto& [k, v] : io)
    if (k.rfind(p, 0) == 0) out[k.substr(p.size())] = v.to(d);
  return out;
}
// The fixture's small generator with its weights, on dev.
simu::models::Generator small_generator(torch::Device dev) {
  return simu::models::load_generator(simu::testing::fixture("ss_generator_small.json"),
                                      simu::testing::fixture("ss_generator_small.safetensors"), dev);
}
}  // namespace

TEST(FlowModelGpu, ForwardMatchesCpuReference) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  for (const char* name : {"ss_generator_small", "ss_generator_variant"}) {
    const std::string n = name;
    auto gen = simu::models::load_generator(simu::testing::fixture(n + ".json"), simu::testing::fixture(n + ".safetensors"), dev);
    auto io = simu::data::load_safetensors(simu::testing::fixture(n + "_io.safetensors"));
    torch::NoGradGuard ng;
    auto x = prefixed(io, "in.latent.", dev);
    auto t = (io.at("in.t") * 1000).to(dev);
    auto cond = io.at("in.cond").to(dev);
    c10::optional<torch::Tensor> d;
    if (gen->config().backbone.is_shortcut_model) d = (io.at("in.d") * 1000).to(dev);
    auto y32 = gen->backbone()->forward(x, t, cond, d);
    simu::models::Latents y16;
    {
      simu::models::Autocast ac(simu::models::Precision::kBf16);
      y16 = gen->backbone()->forward(x, t, cond, d);
    }
    for (const auto& [k, v] : prefixed(io, "out.forward.", torch::kCPU)) {
      EXPECT_TRUE(simu::testing::close(y32.at(k).cpu(), v, 1e-4, n + " fp32 " + k));
      EXPECT_TRUE(simu::testing::close(y16.at(k).cpu(), v, 5e-2, n + " bf16 " + k));
    }
  }
}

TEST(FlowModelGpu, SamplingIsDeterministic) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  auto gen = small_generator(dev);
  auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  auto o = simu::models::SampleOptions::from(gen->config());
  auto run = [&] {
    auto g = at::make_generator<at::CPUGeneratorImpl>(11);
    return gen->sample(io.at("in.cond").to(dev), gen->noise(2, g, dev), o);
  };
  auto a = run(), b = run();
  for (const auto& [k, v] : a) EXPECT_TRUE(torch::equal(v, b.at(k))) << k;
  // The bf16 sample stays near the fp32 CPU sample of the fixture noise.
  auto y = gen->sample(io.at("in.cond").to(dev), prefixed(io, "in.sample.x0.", dev), o);
  EXPECT_TRUE(simu::testing::close(y.at("shape").cpu(), io.at("out.sample_cfg.shape"), 0.15, "bf16 sample shape (CFG 7 amplifies bf16 rounding)"));
}

TEST(FlowModelGpu, CudaGraphSamplingMatchesEager) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  auto gen = small_generator(dev);
  auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  auto o = simu::models::SampleOptions::from(gen->config());
  // Guided and unguided steps both occur (CFG interval) and each batch shape gets its own graph.
  o.cfg_interval = {0.0, 500.0};
  // Capture schemes, with the lagged two-stream schedule (the default: the graph joins the side
  // stream's branch once, at the end) and with a join at every block.
  for (const int scheme : {0, 1, 2})
    for (const std::string solver : {"euler", "rk4"}) {
      const bool overlapped = scheme != 1;
      SCOPED_TRACE(scheme == 0 ? "overlapped capture" : scheme == 1 ? "synchronous capture" : "overlapped, joined per block");
      simu::models::GraphedForward::set_overlapped_capture(overlapped);
      gen->backbone()->set_stream_lag(scheme != 2);
      gen->reverse_fn->clear_graphs();
      o.solver = solver;
      auto run = [&](bool graphs) {
        o.cuda_graphs = graphs;
        auto g = at::make_generator<at::CPUGeneratorImpl>(11);
        return gen->sample(io.at("in.cond").to(dev), gen->noise(2, g, dev), o);
      };
      const auto eager = run(false);
      const auto before = simu::models::GraphedForward::replay_count();
      const auto captures = simu::models::GraphedForward::capture_count();
      const auto graphed = run(true);
      const int64_t evals = o.steps * (solver == "rk4" ? 4 : 1);
      // Each batch shape (guided 2B, unguided B) is captured once. Synchronous: every velocity evaluation
      // is a replay (after a discarded warm-up); overlapped: the first evaluation of each shape is the
      // eager warm-up itself, every other one a replay.
      // (The fixture's 4 Euler steps are all guided: one shape; RK4's midpoints leave the interval: two.)
      const int64_t n = simu::models::GraphedForward::capture_count() - captures;
      EXPECT_EQ(n, solver == "rk4" ? 2 : 1) << solver;
      EXPECT_EQ(simu::models::GraphedForward::replay_count() - before, overlapped ? evals - n : evals) << solver;
      // The same kernels on the same inputs: the same numbers.
      for (const auto& [k, v] : eager) {
        const double err = (graphed.at(k) - v).abs().max().item<double>() / std::max(v.abs().max().item<double>(), 1e-30);
        EXPECT_LE(err, 1e-6) << solver << " " << k;
      }
    }
  simu::models::GraphedForward::set_overlapped_capture(true);
  gen->backbone()->set_stream_lag(true);
  gen->reverse_fn->clear_graphs();
}

namespace {
double max_rel(const simu::models::Latents& a, const simu::models::Latents& b) {
  double e = 0;
  for (const auto& [k, v] : b)
    e = std::max(e, (a.at(k) - v).abs().max().item<double>() / std::max(v.abs().max().item<double>(), 1e-30));
  return e;
}
}  // namespace

// Graphs persist across sample() calls: the second call captures nothing and replays only; a new
// condition of the same shape, weights changed in place and fp16 or bf16 autocast all give the eager
// numbers; a model change (adapters off/on, another precision) is a new capture, not a stale replay.
TEST(FlowModelGpu, CudaGraphsPersistAcrossSampleCalls) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  auto gen = small_generator(dev);
  gen->reverse_fn->clear_graphs();
  auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  auto o = simu::models::SampleOptions::from(gen->config());
  o.cfg_interval = {0.0, 500.0};
  const auto cond_a = io.at("in.cond").to(dev);
  for (const auto precision : {simu::models::Precision::kFp16, simu::models::Precision::kBf16}) {
    SCOPED_TRACE(simu::models::precision_name(precision));
    o.precision = precision;
    auto run = [&](bool graphs, const torch::Tensor& cond) {
      o.cuda_graphs = graphs;
      auto g = at::make_generator<at::CPUGeneratorImpl>(11);
      return gen->sample(cond, gen->noise(2, g, dev), o);
    };
    const auto c0 = simu::models::GraphedForward::capture_count();
    const auto first = run(true, cond_a);
    // One graph per batch shape the solve uses (guided 2B, unguided B).
    const int64_t n = simu::models::GraphedForward::capture_count() - c0;
    EXPECT_GE(n, 1);
    // Second call: replays only, the same numbers.
    const auto r0 = simu::models::GraphedForward::replay_count();
    const auto second = run(true, cond_a);
    EXPECT_EQ(simu::models::GraphedForward::capture_count() - c0, n) << "graphs re-captured instead of reused";
    EXPECT_EQ(simu::models::GraphedForward::replay_count() - r0, o.steps);
    EXPECT_LE(max_rel(second, first), 1e-6);
    EXPECT_LE(max_rel(second, run(false, cond_a)), 1e-6);
    // Another condition of the same shape through the same graphs.
    const auto cond_b = cond_a.flip(1) * 0.5 + 0.1;
    EXPECT_LE(max_rel(run(true, cond_b), run(false, cond_b)), 1e-6) << "condition not refreshed";
    // Weights updated in place (a training step, say): the graphs read the new values.
    {
      torch::NoGradGuard ng;
      for (auto& p : gen->backbone()->parameters()) p.mul_(1.01);
    }
    const auto g_new = run(true, cond_a), e_new = run(false, cond_a);
    EXPECT_LE(max_rel(g_new, e_new), 1e-6) << "weights not refreshed";
    EXPECT_GT(max_rel(g_new, second), 1e-4) << "the weight change should show";
    EXPECT_EQ(simu::models::GraphedForward::capture_count() - c0, n);
    // Kernel switch off: a different forward, so new captures that match eager.
    gen->backbone()->set_fused_kernels(false);
    EXPECT_LE(max_rel(run(true, cond_a), run(false, cond_a)), 1e-6);
    EXPECT_EQ(simu::models::GraphedForward::capture_count() - c0, 2 * n);
    gen->backbone()->set_fused_kernels(true);
  }
  EXPECT_LE(gen->reverse_fn->graph_cache.graphs.size(), gen->reverse_fn->graph_cache.max_graphs);
  gen->reverse_fn->clear_graphs();
}

// Few queries over many keys (the pose stream's 4 tokens in sampling) take FlashAttention's kernel;
// its result is the attention of the same fp16 values computed in fp32 by PyTorch's math backend.
// With grad mode on, or many queries, PyTorch's own choice runs instead.
TEST(FlowModelGpu, FewQueryAttentionTakesFlashAndMatchesMath) {
  SIMU_REQUIRE_CUDA();
  const auto f16 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat16);
  torch::manual_seed(5);
  for (int64_t Lk : {7528, 2800}) {
    for (int64_t B : {1, 2}) {
      // Keys/values as views of one projection, like the condition cache: [B, Lk, 2, H, D].
      auto kv = torch::randn({B, Lk, 2, 16, 64}, f16);
      auto k = kv.select(2, 0), v = kv.select(2, 1);  // [B, Lk, H, D]
      auto q = torch::randn({B, 4, 16, 64}, f16);      // [B, 4, H, D]
      torch::NoGradGuard ng;
      ASSERT_TRUE(simu::models::few_query_flash(q, k)) << Lk << " " << B;
      auto got = simu::models::sdpa_blhd(q, k, v).to(torch::kFloat32);
      auto want = at::_scaled_dot_product_attention_math(q.permute({0, 2, 1, 3}).to(torch::kFloat32),
                                                        k.permute({0, 2, 1, 3}).to(torch::kFloat32),
                                                        v.permute({0, 2, 1, 3}).to(torch::kFloat32));
      EXPECT_TRUE(simu::testing::close(got, std::get<0>(want).permute({0, 2, 1, 3}), 3e-3, "few-query flash"));
    }
  }
  // Not taken: a graph is recorded, or many queries (PyTorch's choice runs).
  auto k = torch::randn({1, 512, 16, 64}, f16);
  EXPECT_FALSE(simu::models::few_query_flash(torch::randn({1, 4096, 16, 64}, f16), k));
  {
    torch::AutoGradMode on(true);
    EXPECT_FALSE(simu::models::few_query_flash(torch::randn({1, 4, 16, 64}, f16), k));
  }
  // Not taken inside FewQueryFlashOff(true) (the pose stream's work on the side stream), nested scopes
  // restoring the state they found; the result is then PyTorch's kernel's, the same attention.
  torch::NoGradGuard ng;
  auto q4 = torch::randn({1, 4, 16, 64}, f16);
  auto v = torch::randn({1, 512, 16, 64}, f16);
  const auto flash = simu::models::sdpa_blhd(q4, k, v).to(torch::kFloat32);
  {
    const simu::models::detail::FewQueryFlashOff off(true);
    EXPECT_FALSE(simu::models::few_query_flash(q4, k));
    {
      const simu::models::detail::FewQueryFlashOff on(false);
      EXPECT_TRUE(simu::models::few_query_flash(q4, k));
    }
    EXPECT_FALSE(simu::models::few_query_flash(q4, k));
    const auto other = simu::models::sdpa_blhd(q4, k, v).to(torch::kFloat32);
    EXPECT_TRUE(simu::testing::close(other, flash, 3e-3, "few-query attention, PyTorch's choice against flash"));
  }
  EXPECT_TRUE(simu::models::few_query_flash(q4, k));
}
