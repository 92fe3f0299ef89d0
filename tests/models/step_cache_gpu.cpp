// Step caching of Stage-1 sampling on CUDA (models/step_cache.h): with persistent CUDA graphs only the
// full steps run the model (counted graph replays), the graphed and eager cached samplings agree, and
// interval 1 is full sampling, in the released fp16 precision; the cached sample stays near the full one.
#include <ATen/CPUGeneratorImpl.h>

#include <cstdio>

#include "data/safetensors.h"
#include "models/generator.h"
#include "models/precision.h"
#include "test_util.h"

namespace {
namespace sm = simu::models;

double max_rel(const sm::Latents& a, const sm::Latents& b) {
  double e = 0;
  for (const auto& [k, v] : b)
    e = std::max(e, (a.at(k) - v).abs().max().item<double>() / std::max(v.abs().max().item<double>(), 1e-30));
  return e;
}
}  // namespace

TEST(StepCacheGpu, GraphsReplayOnlyTheFullSteps) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  auto gen = sm::load_generator(simu::testing::fixture("ss_generator_small.json"),
                                simu::testing::fixture("ss_generator_small.safetensors"), dev);
  auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  const auto cond = io.at("in.cond").to(dev);
  // The official inference sampler (25 steps, CFG on the first 19), fp16 as released.
  auto o = sm::official_inference_options(gen->config());
  o.precision = sm::Precision::kFp16;
  auto run = [&](bool graphs, int interval) {
    o.cuda_graphs = graphs;
    o.step_cache.enabled = interval > 0;
    o.step_cache.interval = std::max(interval, 1);
    auto g = at::make_generator<at::CPUGeneratorImpl>(5);
    return gen->sample(cond, gen->noise(2, g, dev), o);
  };
  gen->reverse_fn->clear_graphs();
  const auto full = run(false, 0);
  // Interval 1: every step full, the same numbers as without step caching.
  const auto every = run(false, 1);
  for (const auto& [k, v] : full) EXPECT_TRUE(torch::equal(v, every.at(k))) << k;
  // Interval 3, eager then graphed (overlapped capture: each batch shape's first evaluation is eager).
  const auto eager = run(false, 3);
  const int full_steps = gen->step_cache_stats().full_steps();
  EXPECT_EQ(full_steps, 10);  // 0, 1, 4, 7, 10, 13, 16, 19 (CFG ends), 22, 24
  const auto r0 = sm::GraphedForward::replay_count(), c0 = sm::GraphedForward::capture_count();
  const auto graphed = run(true, 3);
  const int64_t captures = sm::GraphedForward::capture_count() - c0;
  EXPECT_EQ(captures, 2);  // guided (2B) and unguided (B)
  EXPECT_EQ(sm::GraphedForward::replay_count() - r0, full_steps - captures);
  EXPECT_LE(max_rel(graphed, eager), 1e-6);
  // The cached fp16 sample against the full fp16 one: CPU fp32 measured 0.2% (shape, k = 3); fp16 rounding
  // amplified by CFG 7 moves a sample by up to 15% (FlowModelGpu.SamplingIsDeterministic's bound).
  const double shape_err = (graphed.at("shape") - full.at("shape")).abs().max().item<double>() /
                           full.at("shape").abs().max().item<double>();
  std::printf("[step cache k=3, fp16] shape max rel err vs full %.4f\n", shape_err);
  EXPECT_LT(shape_err, 0.15);
  gen->reverse_fn->clear_graphs();
}
