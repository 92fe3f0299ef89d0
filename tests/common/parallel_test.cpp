// Tests common/parallel.h: parallel_for_each visits every index exactly once whatever the thread
// count, and rethrows the first exception after all threads stopped.
#include <gtest/gtest.h>

#include <atomic>
#include <stdexcept>
#include <vector>

#include "common/parallel.h"

TEST(ParallelForEach, VisitsEveryIndexOnce) {
  for (int threads : {1, 2, 3, 16}) {
    for (int64_t n : {0, 1, 5, 100}) {
      std::vector<std::atomic<int>> seen(static_cast<size_t>(n));
      simu::parallel_for_each(n, threads, [&](int64_t i) { seen[static_cast<size_t>(i)]++; });
      for (int64_t i = 0; i < n; ++i) EXPECT_EQ(seen[static_cast<size_t>(i)].load(), 1) << "n " << n << " threads " << threads;
    }
  }
}

TEST(ParallelForEach, RethrowsTheFirstErrorAndStopsStartingIndices) {
  std::atomic<int> started{0};
  EXPECT_THROW(simu::parallel_for_each(1000, 1,
                                       [&](int64_t i) {
                                         ++started;
                                         if (i == 3) throw std::runtime_error("index 3");
                                       }),
               std::runtime_error);
  // One thread: indices 0..3 ran, nothing after the failing one.
  EXPECT_EQ(started.load(), 4);
}
