// Summary statistics of per-object scores and paired bootstrap confidence intervals (eval_lift's
// aggregates and its base-vs-adapter deltas). Values that are not finite (NaN: a metric undefined
// for an object, e.g. the rotation error of a failed lift) are left out of every statistic.
//
//   auto ci = simu::stats::paired_bootstrap_delta(base_iou, tuned_iou, simu::stats::mean_finite, 10000, seed);
//   ci.estimate; ci.lo; ci.hi;   // stat(tuned) - stat(base) and its 95% percentile interval
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

namespace simu::stats {

// Mean / median of the finite values; NaN when there is none.
double mean_finite(const std::vector<double>& values);
double median_finite(const std::vector<double>& values);
// Number of finite values.
int64_t count_finite(const std::vector<double>& values);

// Quantile q in [0, 1] of the finite values, linear between order statistics (Hyndman & Fan type 7,
// numpy's default): position q (n - 1) in the sorted values. NaN when there is none.
double quantile(std::vector<double> values, double q);

// A statistic of one sample (mean_finite, median_finite, ...).
using Statistic = std::function<double(const std::vector<double>&)>;

struct Interval {
  double estimate = 0;  // the statistic's difference on the data itself
  double lo = 0, hi = 0;  // the percentile interval
  int resamples = 0;    // resamples whose difference was defined (finite)
};

// Paired percentile bootstrap of stat(b) - stat(a): a[i] and b[i] belong to the same unit (one object
// under two models), so each resample draws n unit indices with replacement and takes both values of
// each drawn unit. Indices come from a SplitMix64 stream seeded with `seed` (the same interval on
// every machine). lo / hi are the (1 - level) / 2 and (1 + level) / 2 quantiles of the resampled
// differences; resamples whose difference is not finite (a median over no finite value) are left out.
// Throws simu::Error when the sizes differ, a or b is empty, resamples < 1 or level is not in (0, 1).
Interval paired_bootstrap_delta(const std::vector<double>& a, const std::vector<double>& b, const Statistic& stat,
                                int resamples, uint64_t seed, double level = 0.95);

}  // namespace simu::stats
