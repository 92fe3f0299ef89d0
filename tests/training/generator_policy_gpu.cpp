// The generator policy's opt-in FP8 frozen base (set_policy_fp8_base) on CUDA: one FM-DPO evaluation
// of a mid-size model with random adapters, FP8 base (LoRA-wrapped layers with FP8 or bf16 input
// gradients; every frozen Linear) against the bf16 base on the same inputs: the
// adapters' gradient cosine and the d_theta - d_ref terms (printed for the record, asserted loosely:
// the real-size figures are bench/fp8_fidelity's), and switching off gives the bf16 loss back
// exactly. Skips without a GPU that has FP8 (cc >= 8.9).
#include <ATen/CPUGeneratorImpl.h>

#include <cstdio>

#include "flow_mid_config.h"
#include "models/fp8_linear.h"
#include "models/generator.h"
#include "models/precision.h"
#include "test_util.h"
#include "training/fmdpo.h"
#include "training/generator_policy.h"

namespace {

namespace st = simu::training;

// Loss terms and the adapters' gradients (flattened, float64) of one evaluation under bf16 autocast.
std::pair<st::FmdpoTerms, torch::Tensor> evaluate(st::PolicyModel& policy, const st::FmdpoInputs& in) {
  for (auto& [name, p] : policy.adapter_parameters()) p.mutable_grad() = torch::Tensor();
  st::FmdpoTerms terms;
  {
    simu::models::Autocast ac(simu::models::Precision::kBf16);
    terms = st::fmdpo_terms(policy, in, 500.0, false);
  }
  terms.loss.backward();
  std::vector<torch::Tensor> g;
  for (auto& [name, p] : policy.adapter_parameters()) g.push_back(p.grad().flatten().to(torch::kFloat64));
  return {terms, torch::cat(g)};
}

}  // namespace

TEST(GeneratorPolicyGpu, Fp8BaseCloseToBf16AndOffRestores) {
  SIMU_REQUIRE_CUDA();
  if (!simu::models::fp8_supported(torch::kCUDA)) GTEST_SKIP() << "needs a GPU with FP8 tensor cores (cc >= 8.9)";
  const torch::Device dev(torch::kCUDA);
  const auto path = simu::testing::mid_flow_config("generator_policy_gpu");
  torch::manual_seed(3);
  auto policy = st::make_generator_policy(path, "", YAML::Node(), "", dev);
  {
    // Adapters with B != 0 so that the policy differs from the reference and A gets gradients.
    torch::NoGradGuard ng;
    for (auto& [name, p] : policy->adapter_parameters()) p.add_(torch::randn_like(p) * 0.02);
  }
  auto gen = simu::models::load_generator(path, "", torch::kCPU);
  auto rng = at::make_generator<at::CPUGeneratorImpl>(7);
  auto shape0 = gen->noise(4, rng, torch::kCPU).at("shape");
  st::FmdpoInputs in;
  in.x_pos = torch::randn(shape0.sizes(), rng).to(dev);
  in.x_neg = torch::randn(shape0.sizes(), rng).to(dev);
  in.eps_pos = torch::randn(shape0.sizes(), rng).to(dev);
  in.eps_neg = torch::randn(shape0.sizes(), rng).to(dev);
  in.cond = torch::randn({4, 96, gen->config().backbone.cond_channels}, rng).to(dev);
  in.t = torch::tensor({0.2f, 0.4f, 0.6f, 0.8f}).to(dev);
  in.w = torch::tensor({1.0f, 0.1f, 1.0f, 0.1f}).to(dev);
  auto [bf16, g_bf16] = evaluate(*policy, in);
  using simu::lora::Fp8Scope;
  using simu::models::Fp8Backward;
  for (auto [mode, scope] : {std::pair{Fp8Backward::kFp8, Fp8Scope::kAdapted}, std::pair{Fp8Backward::kBf16, Fp8Scope::kAdapted},
                             std::pair{Fp8Backward::kFp8, Fp8Scope::kAll}}) {
    st::set_policy_fp8_base(*policy, false, mode, "test");
    st::set_policy_fp8_base(*policy, true, mode, "test", scope);
    auto [fp8, g_fp8] = evaluate(*policy, in);
    const double cos = (g_fp8.dot(g_bf16) / (g_fp8.norm() * g_bf16.norm())).item<double>();
    const auto dd_bf16 = (bf16.d_theta - bf16.d_ref).to(torch::kFloat64).cpu();
    const auto dd_fp8 = (fp8.d_theta - fp8.d_ref).to(torch::kFloat64).cpu();
    const double dd_err = (dd_fp8 - dd_bf16).abs().max().item<double>() / dd_bf16.abs().max().item<double>();
    std::printf("FP8 base (%s layers, %s backward) vs bf16, mid-size model: gradient cosine %.5f, d_theta - d_ref max rel %.3g\n",
                simu::lora::fp8_scope_name(scope).c_str(), simu::models::fp8_backward_name(mode).c_str(), cos, dd_err);
    EXPECT_GT(cos, 0.95);
    // Loose: policy and reference activations are rounded to the e4m3 grid independently, which puts
    // noise of the order of sqrt(step x adapter effect) on their difference (docs/training.md).
    EXPECT_LT(dd_err, 0.5);
  }
  st::set_policy_fp8_base(*policy, false, Fp8Backward::kFp8, "test");
  auto [again, g_again] = evaluate(*policy, in);
  EXPECT_TRUE(torch::equal(again.loss, bf16.loss));
  // cuDNN's attention backward accumulates dQ with fp32 atomics in a varying order, so the two bf16 backwards
  // differ where a sum lands on the other side of a bf16 rounding: at most one bf16 step (2^-8 relative) per
  // element, far below it in norm (0.79e-3 to 1.0e-3 in five runs on an H100). An FP8 state left behind would show
  // as a difference of the order of the FP8 rows above (cosine 0.999: several 1e-2).
  const double again_rel = (g_again - g_bf16).norm().item<double>() / g_bf16.norm().item<double>();
  std::printf("bf16 again after FP8 off: gradient relative difference %.3g (attention backward's atomics)\n", again_rel);
  EXPECT_LT(again_rel, 1.0 / 256);
}
