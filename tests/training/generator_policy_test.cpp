// generator_policy.h's FP8 frozen base switch on the CPU: train.fp8_base is refused there with an
// error naming the config key (the FP8 products need CUDA with compute capability >= 8.9), and
// switching it off is always allowed. (The GPU behaviour: generator_policy_gpu.cpp.)
#include "test_util.h"
#include "training/generator_policy.h"
#include "training/train_config.h"

TEST(GeneratorPolicy, Fp8BaseRefusedOnCpu) {
  simu::training::TrainConfig cfg;
  cfg.file = "run.yaml";
  cfg.model.config = simu::testing::fixture("ss_generator_small.json");
  cfg.train.fp8_base = true;
  try {
    simu::training::make_generator_policy(cfg, torch::kCPU);
    ADD_FAILURE() << "no error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("run.yaml: train.fp8_base"), std::string::npos) << e.what();
  }
  cfg.train.fp8_base = false;
  auto policy = simu::training::make_generator_policy(cfg, torch::kCPU);
  EXPECT_NO_THROW(simu::training::set_policy_fp8_base(*policy, false, simu::models::Fp8Backward::kFp8, "x"));
  EXPECT_THROW(simu::training::set_policy_fp8_base(*policy, true, simu::models::Fp8Backward::kFp8, "x"), simu::Error);
}
