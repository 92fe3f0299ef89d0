// Stage-1 flow model on CUDA: fp32 and bf16-autocast forwards against the fp32 CPU fixture, and
// determinism of sampling on the device.
#include <ATen/CPUGeneratorImpl.h>

#include "data/safetensors.h"
#include "models/generator.h"
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
      simu::models::Bf16Autocast ac(true);
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
  for (const std::string solver : {"euler", "rk4"}) {
    o.solver = solver;
    auto run = [&](bool graphs) {
      o.cuda_graphs = graphs;
      auto g = at::make_generator<at::CPUGeneratorImpl>(11);
      return gen->sample(io.at("in.cond").to(dev), gen->noise(2, g, dev), o);
    };
    const auto eager = run(false);
    const auto before = simu::models::GraphedForward::replay_count();
    const auto graphed = run(true);
    const int64_t evals = o.steps * (solver == "rk4" ? 4 : 1);
    // Every velocity evaluation is a replay (each batch shape is captured once, after an eager warm-up).
    EXPECT_EQ(simu::models::GraphedForward::replay_count() - before, evals) << solver;
    // The same kernels on the same inputs: the same numbers.
    for (const auto& [k, v] : eager) {
      const double err = (graphed.at(k) - v).abs().max().item<double>() / std::max(v.abs().max().item<double>(), 1e-30);
      EXPECT_LE(err, 1e-6) << solver << " " << k;
    }
  }
}
