// Tests common/random.h: splitmix64 against the SplitMix64 generator's published first outputs.
#include <gtest/gtest.h>

#include "common/random.h"

TEST(SplitMix64, MatchesTheReferenceGenerator) {
  // SplitMix64 from state 0 (state += golden gamma, then the finalizer): first three outputs.
  uint64_t state = 0;
  const uint64_t want[3] = {0xE220A8397B1DCDAFULL, 0x6E789E6AA1B965F4ULL, 0x06C45D188009454FULL};
  for (uint64_t w : want) {
    EXPECT_EQ(simu::splitmix64(state), w);
    state += 0x9E3779B97F4A7C15ULL;
  }
}
