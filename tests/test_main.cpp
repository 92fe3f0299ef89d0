// GoogleTest entry point shared by every suite: two intra-op threads for the torch suites
// (SIMU_TEST_TORCH; the common and physics suites link no torch), or OMP_NUM_THREADS when it is set
// (torch sized its pool from it: the thread-count passes of scripts/capability_pass.sh use it).
#include <gtest/gtest.h>

#include <cstdlib>
#ifdef SIMU_TEST_TORCH
#include <torch/torch.h>
#endif

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
#ifdef SIMU_TEST_TORCH
  if (!std::getenv("OMP_NUM_THREADS")) torch::set_num_threads(2);
#endif
  return RUN_ALL_TESTS();
}
