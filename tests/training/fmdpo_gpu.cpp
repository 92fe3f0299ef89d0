// FM-DPO on CUDA under bf16 autocast with the generator policy: the policy (graph) and reference (no
// graph) forwards run the same fused training kernels, so with fresh adapters (lora_B = 0) the two
// are the same function and d_theta equals d_ref exactly.
#include <ATen/CPUGeneratorImpl.h>

#include <fstream>

#include "models/fused_ops.h"
#include "models/generator.h"
#include "models/mlp_epilogue.h"
#include "models/precision.h"
#include "flow_mid_config.h"
#include "test_util.h"
#include "training/fmdpo.h"
#include "training/generator_policy.h"

TEST(FmdpoGpu, PolicyAndReferenceShareOneArithmetic) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled()) << "built without nvcc: no fused kernels";
  const torch::Device dev(torch::kCUDA);
  // A mid-size model the kernels support (tests/flow_mid_config.h).
  const auto path = simu::testing::mid_flow_config("fmdpo_gpu");
  torch::manual_seed(3);
  auto policy = simu::training::make_generator_policy(path, "", YAML::Node(), "", dev);
  // Shape latents of the model ([B, 512, 8]) and a condition, for 2 pairs.
  auto gen = simu::models::load_generator(path, "", torch::kCPU);
  auto rng = at::make_generator<at::CPUGeneratorImpl>(7);
  auto shape0 = gen->noise(2, rng, torch::kCPU).at("shape");
  simu::training::FmdpoInputs fin;
  fin.x_pos = torch::randn(shape0.sizes(), rng).to(dev);
  fin.x_neg = torch::randn(shape0.sizes(), rng).to(dev);
  fin.eps_pos = torch::randn(shape0.sizes(), rng).to(dev);
  fin.eps_neg = torch::randn(shape0.sizes(), rng).to(dev);
  fin.cond = torch::randn({2, 77, gen->config().backbone.cond_channels}, rng).to(dev);
  fin.t = torch::tensor({0.3f, 0.8f}).to(dev);
  fin.w = torch::tensor({1.0f, 0.1f}).to(dev);
  simu::models::Autocast ac(simu::models::Precision::kBf16);
  const auto n0 = simu::models::fused::launch_count();
  const auto m0 = simu::models::mlp_epilogue::launch_count();
  auto terms = simu::training::fmdpo_terms(*policy, fin, 500.0, false);
  // Policy forward (graph) and reference forward (none): 3 blocks x 4 kernels each, in the shape stream
  // alone (only the shape latent is scored, so the pose stream does not run: set_output_latents).
  EXPECT_EQ(simu::models::fused::launch_count() - n0, 2 * 3 * 1 * 4) << "fused training kernels did not run";
  // Both forwards also take the MLP's GELU_AUX_BIAS epilogue (mlp_epilogue.h), one per block.
  if (simu::models::mlp_epilogue::compiled())
    EXPECT_EQ(simu::models::mlp_epilogue::launch_count() - m0, 2 * 3) << "the MLP's cuBLASLt epilogue did not run";
  EXPECT_TRUE(torch::equal(terms.loss_pos_policy, terms.loss_pos_ref));
  EXPECT_TRUE(torch::equal(terms.loss_neg_policy, terms.loss_neg_ref));
  EXPECT_TRUE(torch::equal(terms.d_theta, terms.d_ref));
  // -log sigmoid(0) = log 2 for every pair.
  EXPECT_NEAR(terms.per_pair.max().item<double>(), std::log(2.0), 1e-6);
  EXPECT_NEAR(terms.per_pair.min().item<double>(), std::log(2.0), 1e-6);
  // The backward reaches every adapter (lora_B gets a gradient at lora_B = 0).
  const auto m1 = simu::models::mlp_epilogue::launch_count();
  terms.loss.backward();
  // The policy's backward: one DGELU epilogue per block.
  if (simu::models::mlp_epilogue::compiled()) EXPECT_EQ(simu::models::mlp_epilogue::launch_count() - m1, 3);
  for (auto& [name, p] : policy->adapter_parameters())
    if (name.find("lora_B") != std::string::npos) {
      ASSERT_TRUE(p.grad().defined()) << name;
      EXPECT_GT(p.grad().abs().max().item<double>(), 0.0) << name;
    }
}
