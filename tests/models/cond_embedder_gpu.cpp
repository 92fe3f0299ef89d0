// Condition embedder on CUDA: the fixture parity in fp32 (TF32 switched off) and the bf16 path
// against the fp32 reference.
#include "data/safetensors.h"
#include "models/cond_embedder.h"
#include "test_util.h"

namespace {

std::map<std::string, torch::Tensor> cuda_inputs(torch::ScalarType dt) {
  std::map<std::string, torch::Tensor> in;
  for (const auto& [k, v] : simu::data::load_safetensors(simu::testing::fixture("cond_embedder_small_io.safetensors")))
    if (k.rfind("in.", 0) == 0) in[k.substr(3)] = v.to(torch::kCUDA, dt);
  return in;
}

}  // namespace

TEST(CondEmbedderGpu, FusedMatchesFixtureOnCuda) {
  SIMU_REQUIRE_CUDA();
  torch::NoGradGuard ng;
  // Full fp32 (cuDNN convolutions default to TF32).
  const bool cudnn_tf32 = at::globalContext().allowTF32CuDNN();
  at::globalContext().setAllowTF32CuDNN(false);
  auto m = simu::models::load_cond_embedder(simu::testing::fixture("cond_embedder_small.json"),
                                            simu::testing::fixture("cond_embedder_small.safetensors"), "",
                                            torch::kCUDA);
  auto want = simu::data::load_safetensors(simu::testing::fixture("cond_embedder_small_io.safetensors")).at("out.fused");
  auto got = m->forward(cuda_inputs(torch::kFloat32)).cpu();
  at::globalContext().setAllowTF32CuDNN(cudnn_tf32);
  std::printf("  out.fused on CUDA fp32: max rel err %.3g\n", simu::testing::rel_err(got, want));
  EXPECT_TRUE(simu::testing::close(got, want, 1e-4, "out.fused (cuda fp32)"));
}

TEST(CondEmbedderGpu, Bf16CloseToFp32) {
  SIMU_REQUIRE_CUDA();
  torch::NoGradGuard ng;
  auto m = simu::models::load_cond_embedder(simu::testing::fixture("cond_embedder_small.json"),
                                            simu::testing::fixture("cond_embedder_small.safetensors"), "",
                                            torch::kCUDA);
  auto ref = m->forward(cuda_inputs(torch::kFloat32)).cpu();
  m->to(torch::kBFloat16);
  auto got = m->forward(cuda_inputs(torch::kBFloat16));
  EXPECT_EQ(got.scalar_type(), torch::kBFloat16);
  std::printf("  out.fused bf16 vs fp32 on CUDA: max rel err %.3g\n",
              simu::testing::rel_err(got.to(torch::kFloat32).cpu(), ref));
  EXPECT_TRUE(simu::testing::close(got.to(torch::kFloat32).cpu(), ref, 1e-1, "out.fused (cuda bf16 vs fp32)"));
}
