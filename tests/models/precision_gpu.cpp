// Inference precision on CUDA (models/precision.h): fp16 autocast (the released pipeline.yaml dtype)
// and bf16 autocast (the training recipe) against the fp32 CPU fixtures made by the official code:
// condition embedder forward, flow model forward, decoder forward, and a CFG sample with the official
// inference settings. Prints every measured error (max |got - want| / max |want|) for the record;
// asserts fp16 closer than bf16 and loose upper bounds (the stated tolerances come from these prints).
#include <ATen/CPUGeneratorImpl.h>
#include <ATen/autocast_mode.h>

#include <cstdio>
#include <functional>

#include "data/safetensors.h"
#include "models/cond_embedder.h"
#include "models/fused_ops.h"
#include "models/generator.h"
#include "models/precision.h"
#include "models/ss_decoder.h"
#include "test_util.h"

namespace sm = simu::models;

namespace {

sm::Latents prefixed(const std::map<std::string, torch::Tensor>& io, const std::string& p, torch::Device d) {
  sm::Latents out;
  for (const auto& [k, v] : io)
    if (k.rfind(p, 0) == 0) out[k.substr(p.size())] = v.to(d);
  return out;
}

double latents_err(const sm::Latents& got, const std::map<std::string, torch::Tensor>& io, const std::string& p) {
  double e = 0;
  for (const auto& [k, w] : prefixed(io, p, torch::kCPU)) e = std::max(e, simu::testing::rel_err(got.at(k).cpu(), w));
  return e;
}

void report(const char* what, double e32, double e16, double ebf) {
  std::printf("precision %-28s fp32 %.3g  fp16 %.3g  bf16 %.3g  (bf16/fp16 %.1fx)\n", what, e32, e16, ebf,
              ebf / std::max(e16, 1e-12));
}

// Reports the three errors of one computation and checks them: fp32 below max32, fp16 closer than bf16
// (more mantissa bits), bf16 below maxbf.
void expect_precision_ladder(const char* what, double e32, double e16, double ebf, double max32, double maxbf) {
  SCOPED_TRACE(what);
  report(what, e32, e16, ebf);
  EXPECT_LT(e32, max32);
  EXPECT_LT(e16, ebf);
  EXPECT_LT(ebf, maxbf);
}

// forward() under autocast in fp32, fp16 and bf16 against want (rel_err in fp32 on the CPU), checked as above.
void expect_autocast_ladder(const char* what, const std::function<torch::Tensor()>& forward, const torch::Tensor& want,
                            double max32, double maxbf) {
  auto run = [&](sm::Precision p) {
    sm::Autocast ac(p);
    return simu::testing::rel_err(forward().to(torch::kCPU, torch::kFloat32), want);
  };
  const double e32 = run(sm::Precision::kFp32), e16 = run(sm::Precision::kFp16), ebf = run(sm::Precision::kBf16);
  expect_precision_ladder(what, e32, e16, ebf, max32, maxbf);
}

}  // namespace

TEST(PrecisionGpu, EmbedderForward) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  torch::NoGradGuard ng;
  auto m = sm::load_cond_embedder(simu::testing::fixture("cond_embedder_small.json"),
                                  simu::testing::fixture("cond_embedder_small.safetensors"), "", dev);
  const auto io = simu::data::load_safetensors(simu::testing::fixture("cond_embedder_small_io.safetensors"));
  std::map<std::string, torch::Tensor> in;
  for (const auto& [k, v] : io)
    if (k.rfind("in.", 0) == 0) in[k.substr(3)] = v.to(dev);
  expect_autocast_ladder("embedder forward", [&] { return m->forward(in); }, io.at("out.fused"), 1e-4, 1e-1);
}

TEST(PrecisionGpu, FlowForwardAndCfgSample) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  torch::NoGradGuard ng;
  auto gen = sm::load_generator(simu::testing::fixture("ss_generator_small.json"),
                                simu::testing::fixture("ss_generator_small.safetensors"), dev);
  const auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  const auto x = prefixed(io, "in.latent.", dev);
  const auto t = (io.at("in.t") * 1000).to(dev);
  const auto cond = io.at("in.cond").to(dev);
  const c10::optional<torch::Tensor> d = (io.at("in.d") * 1000).to(dev);
  auto fwd = [&](sm::Precision p) {
    sm::Autocast ac(p);
    return latents_err(gen->backbone()->forward(x, t, cond, d), io, "out.forward.");
  };
  // The fused kernels store bf16 or fp16: both low precisions take the fused path (when compiled in),
  // fp32 never does.
  const int64_t launches0 = sm::fused::launch_count();
  const double f16 = fwd(sm::Precision::kFp16);
  if (sm::fused::compiled()) EXPECT_GT(sm::fused::launch_count(), launches0) << "fp16 should take the fused path";
  const int64_t launches1 = sm::fused::launch_count();
  const double f32 = fwd(sm::Precision::kFp32);
  EXPECT_EQ(sm::fused::launch_count(), launches1) << "a fused kernel ran in fp32";
  const double fbf = fwd(sm::Precision::kBf16);
  if (sm::fused::compiled()) EXPECT_GT(sm::fused::launch_count(), launches1) << "bf16 should take the fused path";
  expect_precision_ladder("flow forward", f32, f16, fbf, 1e-4, 5e-2);

  // CFG sample with the official inference settings (4 steps as the fixture; CFG 7 amplifies rounding).
  sm::SamplerOverrides u;
  u.steps = 4;
  auto sample = [&](sm::Precision p) {
    auto o = sm::official_inference_options(gen->config(), u);
    o.precision = p;
    return latents_err(gen->sample(cond, prefixed(io, "in.sample.x0.", dev), o), io, "out.sample_cfg.");
  };
  const double s32 = sample(sm::Precision::kFp32), s16 = sample(sm::Precision::kFp16), sbf = sample(sm::Precision::kBf16);
  expect_precision_ladder("CFG sample (4 steps, cfg 7)", s32, s16, sbf, 1e-3, 0.15);
}

TEST(PrecisionGpu, DecoderForward) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  torch::NoGradGuard ng;
  auto dec = sm::load_ss_decoder(simu::testing::fixture("ss_decoder_small.json"),
                                 simu::testing::fixture("ss_decoder_small.safetensors"), dev);
  const auto io = simu::data::load_safetensors(simu::testing::fixture("ss_decoder_small.safetensors"));
  const auto in = io.at("io.in").to(dev);
  expect_autocast_ladder("decoder forward", [&] { return dec->forward(in); }, io.at("io.out"), 1e-4, 5e-2);
}

// The Autocast guard restores what was there (nested scopes, fp16 inside bf16).
TEST(PrecisionGpu, AutocastNestsAndRestores) {
  SIMU_REQUIRE_CUDA();
  EXPECT_FALSE(at::autocast::is_autocast_enabled(at::kCUDA));
  {
    sm::Autocast a(sm::Precision::kBf16);
    EXPECT_EQ(at::autocast::get_autocast_dtype(at::kCUDA), at::kBFloat16);
    {
      sm::Autocast b(sm::Precision::kFp16);
      EXPECT_EQ(at::autocast::get_autocast_dtype(at::kCUDA), at::kHalf);
      auto y = torch::matmul(torch::randn({4, 4}, torch::kCUDA), torch::randn({4, 4}, torch::kCUDA));
      EXPECT_EQ(y.scalar_type(), at::kHalf);
    }
    EXPECT_EQ(at::autocast::get_autocast_dtype(at::kCUDA), at::kBFloat16);
    // fp32 inside a bf16 scope: IEEE float32 (autocast off, no TF32 in matmuls or convolutions).
    {
      sm::Autocast c(sm::Precision::kFp32);
      EXPECT_FALSE(at::autocast::is_autocast_enabled(at::kCUDA));
      EXPECT_TRUE(at::NoTF32Guard::should_disable_tf32());
      EXPECT_EQ(at::globalContext().float32Precision(at::Float32Backend::CUDA, at::Float32Op::CONV),
                at::Float32Precision::IEEE);
      auto y = torch::matmul(torch::randn({4, 4}, torch::kCUDA), torch::randn({4, 4}, torch::kCUDA));
      EXPECT_EQ(y.scalar_type(), at::kFloat);
    }
    EXPECT_TRUE(at::autocast::is_autocast_enabled(at::kCUDA));
    EXPECT_FALSE(at::NoTF32Guard::should_disable_tf32());
  }
  EXPECT_FALSE(at::autocast::is_autocast_enabled(at::kCUDA));
}

// Real size (configs/stage1_real.yaml: 1024 channels, 24 blocks; 7,528 condition tokens of 1,024
// channels), random weights: fp16 and bf16 against fp32 on the same GPU, one forward and a 25-step CFG
// sample with the official inference settings. Prints the errors (the real-size table).
TEST(PrecisionGpu, RealSizeForwardAndSampleAgainstFp32) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  torch::NoGradGuard ng;
  torch::manual_seed(0);
  auto gen = sm::load_generator(simu::testing::source_dir() + "/configs/stage1_real.yaml", "", dev);
  const int64_t L = 7528;
  auto g = at::make_generator<at::CPUGeneratorImpl>(5);
  const auto cond = torch::randn({1, L, gen->config().backbone.cond_channels}, g).to(dev);
  const auto x0 = gen->noise(1, g, dev);
  const auto t = torch::full({1}, 300.0, torch::TensorOptions().device(dev));
  const c10::optional<torch::Tensor> d = torch::zeros({1}, torch::TensorOptions().device(dev));
  auto fwd = [&](sm::Precision p) {
    sm::Autocast ac(p);
    sm::Latents y = gen->backbone()->forward(x0, t, cond, d);
    for (auto& [k, v] : y) v = v.to(torch::kFloat32);
    return y;
  };
  auto err = [](const sm::Latents& a, const sm::Latents& ref) {
    double e = 0;
    for (const auto& [k, v] : ref) e = std::max(e, simu::testing::rel_err(a.at(k), v));
    return e;
  };
  const auto y32 = fwd(sm::Precision::kFp32);
  const double f16 = err(fwd(sm::Precision::kFp16), y32), fbf = err(fwd(sm::Precision::kBf16), y32);
  report("real-size forward vs fp32", 0.0, f16, fbf);
  EXPECT_LT(f16, fbf);
  auto sample = [&](sm::Precision p) {
    auto o = sm::official_inference_options(gen->config());
    o.precision = p;
    return gen->sample(cond, x0, o);
  };
  const auto s32 = sample(sm::Precision::kFp32);
  const double s16 = err(sample(sm::Precision::kFp16), s32), sbf = err(sample(sm::Precision::kBf16), s32);
  report("real-size 25-step CFG sample vs fp32", 0.0, s16, sbf);
  EXPECT_LT(s16, sbf);
}
