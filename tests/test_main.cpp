// GoogleTest entry point shared by every suite: two intra-op threads for the torch suites
// (SIMU_TEST_TORCH; the common and physics suites link no torch).
#include <gtest/gtest.h>
#ifdef SIMU_TEST_TORCH
#include <torch/torch.h>
#endif

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
#ifdef SIMU_TEST_TORCH
  torch::set_num_threads(2);
#endif
  return RUN_ALL_TESTS();
}
