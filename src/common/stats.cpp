// Summary statistics and the paired percentile bootstrap.
#include "common/stats.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "common/error.h"
#include "common/random.h"

namespace simu::stats {

namespace {

std::vector<double> finite(const std::vector<double>& v) {
  std::vector<double> out;
  out.reserve(v.size());
  for (double x : v)
    if (std::isfinite(x)) out.push_back(x);
  return out;
}

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

}  // namespace

int64_t count_finite(const std::vector<double>& values) {
  return std::count_if(values.begin(), values.end(), [](double x) { return std::isfinite(x); });
}

double mean_finite(const std::vector<double>& values) {
  double sum = 0;
  int64_t n = 0;
  for (double x : values)
    if (std::isfinite(x)) sum += x, ++n;
  return n ? sum / static_cast<double>(n) : kNaN;
}

double quantile(std::vector<double> values, double q) {
  SIMU_CHECK(q >= 0 && q <= 1, "quantile: q = {} is not in [0, 1]", q);
  values = finite(values);
  if (values.empty()) return kNaN;
  std::sort(values.begin(), values.end());
  const double pos = q * static_cast<double>(values.size() - 1);
  const size_t i = static_cast<size_t>(std::floor(pos));
  if (i + 1 >= values.size()) return values.back();
  const double frac = pos - static_cast<double>(i);
  return values[i] + frac * (values[i + 1] - values[i]);
}

double median_finite(const std::vector<double>& values) { return quantile(values, 0.5); }

Interval paired_bootstrap_delta(const std::vector<double>& a, const std::vector<double>& b, const Statistic& stat,
                                int resamples, uint64_t seed, double level) {
  SIMU_CHECK(a.size() == b.size(), "paired bootstrap: {} and {} values (the samples must pair)", a.size(), b.size());
  SIMU_CHECK(!a.empty(), "paired bootstrap: no values");
  SIMU_CHECK(resamples >= 1, "paired bootstrap: resamples = {} must be >= 1", resamples);
  SIMU_CHECK(level > 0 && level < 1, "paired bootstrap: level = {} is not in (0, 1)", level);
  Interval r;
  r.estimate = stat(b) - stat(a);
  const size_t n = a.size();
  uint64_t state = splitmix64(seed);
  std::vector<double> ra(n), rb(n), deltas;
  deltas.reserve(static_cast<size_t>(resamples));
  for (int k = 0; k < resamples; ++k) {
    for (size_t i = 0; i < n; ++i) {
      // An index in [0, n) from the high bits of a 64-bit draw (Lemire's multiply; bias below n / 2^64).
      const uint64_t draw = splitmix64(state);
      state += 0x9E3779B97F4A7C15ULL;
      const size_t j = static_cast<size_t>((static_cast<unsigned __int128>(draw) * n) >> 64);
      ra[i] = a[j];
      rb[i] = b[j];
    }
    const double d = stat(rb) - stat(ra);
    if (std::isfinite(d)) deltas.push_back(d);
  }
  r.resamples = static_cast<int>(deltas.size());
  r.lo = quantile(deltas, (1 - level) / 2);
  r.hi = quantile(deltas, (1 + level) / 2);
  return r;
}

}  // namespace simu::stats
