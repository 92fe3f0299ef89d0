// Tests common/stats.h: quantiles against hand-computed type-7 values, the paired bootstrap against
// exact answers (a constant shift) and against the normal approximation of a mean's interval, its
// determinism, and how it handles undefined resamples.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "common/random.h"
#include "common/stats.h"
#include "test_files.h"

namespace ss = simu::stats;

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// n standard normal values from a fixed SplitMix64 stream (Box-Muller).
std::vector<double> normals(int n, uint64_t seed) {
  std::vector<double> out;
  uint64_t state = seed;
  auto uniform = [&] {
    const uint64_t r = simu::splitmix64(state);
    state += 0x9E3779B97F4A7C15ULL;
    return (static_cast<double>(r >> 11) + 0.5) * 0x1.0p-53;  // in (0, 1)
  };
  while (static_cast<int>(out.size()) < n) {
    const double u = uniform(), v = uniform();
    out.push_back(std::sqrt(-2 * std::log(u)) * std::cos(2 * M_PI * v));
  }
  return out;
}

}  // namespace

TEST(Stats, QuantilesMeansMedians) {
  // Type 7: position q (n - 1); {1, 2, 3, 4} at q = 0.25 is 1 + 0.75 (2 - 1) = 1.75. Exact in binary.
  EXPECT_EQ(ss::quantile({4, 1, 3, 2}, 0.25), 1.75);
  EXPECT_EQ(ss::quantile({4, 1, 3, 2}, 0.5), 2.5);
  EXPECT_EQ(ss::quantile({4, 1, 3, 2}, 1.0), 4.0);
  EXPECT_EQ(ss::median_finite({5, kNaN, 1, 3}), 3.0);
  EXPECT_EQ(ss::mean_finite({5, kNaN, 1}), 3.0);
  EXPECT_EQ(ss::count_finite({5, kNaN, INFINITY, 1}), 2);
  EXPECT_TRUE(std::isnan(ss::mean_finite({kNaN})));
  EXPECT_TRUE(std::isnan(ss::median_finite({})));
}

// b = a + c: every resample's difference of means is c (up to the rounding of two means of values
// below 10: a few ulps of 10, 1e-14), so the interval is [c, c].
TEST(Stats, BootstrapOfAConstantShiftIsThatShift) {
  const std::vector<double> a = normals(50, 3);
  std::vector<double> b = a;
  for (double& x : b) x += 0.25;
  const ss::Interval ci = ss::paired_bootstrap_delta(a, b, ss::mean_finite, 2000, 7);
  EXPECT_NEAR(ci.estimate, 0.25, 1e-14);
  EXPECT_NEAR(ci.lo, 0.25, 1e-14);
  EXPECT_NEAR(ci.hi, 0.25, 1e-14);
  EXPECT_EQ(ci.resamples, 2000);
}

// The percentile interval of a mean of n = 400 normal differences is close to the normal one,
// mean +- 1.96 s / sqrt(n). Its ends are quantiles of 10^4 resampled means: each has a Monte Carlo
// standard error of sqrt(0.025 * 0.975 / 10^4) / phi(1.96) = 0.027 bootstrap standard deviations,
// 1.4% of the half-width; the bootstrap's (n - 1) / n variance adds 0.1%. 8% (6 such errors) holds.
TEST(Stats, BootstrapMeanMatchesTheNormalInterval) {
  const int n = 400;
  const std::vector<double> d = normals(n, 11);
  const std::vector<double> zero(n, 0.0);
  const ss::Interval ci = ss::paired_bootstrap_delta(zero, d, ss::mean_finite, 10000, 5);
  double mean = 0, var = 0;
  for (double x : d) mean += x / n;
  for (double x : d) var += (x - mean) * (x - mean) / (n - 1);
  const double half = 1.96 * std::sqrt(var / n);
  EXPECT_NEAR(ci.estimate, mean, 1e-15);
  EXPECT_NEAR(ci.hi - mean, half, 0.08 * half);
  EXPECT_NEAR(mean - ci.lo, half, 0.08 * half);
  // Seeded: the same interval again, another with another seed.
  const ss::Interval again = ss::paired_bootstrap_delta(zero, d, ss::mean_finite, 10000, 5);
  EXPECT_EQ(again.lo, ci.lo);
  EXPECT_EQ(again.hi, ci.hi);
  EXPECT_NE(ss::paired_bootstrap_delta(zero, d, ss::mean_finite, 10000, 6).lo, ci.lo);
}

// A median over resampled units that are all undefined is undefined: those resamples are left out.
// Each resample of 2 units is all-NaN with probability 1/4, so 7,500 of 10^4 are kept on average
// (binomial standard deviation 43; 6 of them bound a false failure).
TEST(Stats, BootstrapDropsUndefinedResamples) {
  const ss::Interval ci = ss::paired_bootstrap_delta({kNaN, 1}, {kNaN, 2}, ss::median_finite, 10000, 1);
  EXPECT_EQ(ci.estimate, 1.0);
  EXPECT_EQ(ci.lo, 1.0);
  EXPECT_EQ(ci.hi, 1.0);
  EXPECT_NEAR(ci.resamples, 7500, 6 * 43);
  EXPECT_NE(simu::testing::error_of([] { ss::paired_bootstrap_delta({1, 2}, {1}, ss::mean_finite, 10, 0); })
                .find("must pair"),
            std::string::npos);
}
