// Step caching for Stage-1 sampling (step_cache.h): options, the Newton extrapolation, the schedule.
#include "models/step_cache.h"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "common/error.h"

namespace simu::models {

void StepCacheOptions::validate(const std::string& where) const {
  SIMU_CHECK(interval >= 1, "{}interval must be >= 1 (1 = a full evaluation every step), got {}", where, interval);
  SIMU_CHECK(order >= 0 && order <= 2, "{}order must be 0, 1 or 2 (shape extrapolation degree in t), got {}", where,
             order);
  SIMU_CHECK(warmup >= 1, "{}warmup must be >= 1 (the first step is always a full evaluation), got {}", where, warmup);
  SIMU_CHECK(tail >= 0, "{}tail must be >= 0, got {}", where, tail);
  SIMU_CHECK(pose_momentum >= 0 && pose_momentum <= 1, "{}pose_momentum must be in [0, 1], got {}", where,
             pose_momentum);
  SIMU_CHECK(tolerance >= 0 && std::isfinite(tolerance), "{}tolerance must be >= 0 (0 = off), got {}", where, tolerance);
}

std::string StepCacheOptions::describe() const {
  if (!enabled) return "off";
  return fmt::format("a full evaluation at least every {} steps (warmup {}, tail {}{}), shape extrapolated to order {}, "
                     "pose momentum {}",
                     interval, warmup, tail,
                     tolerance > 0 ? fmt::format(", refresh above relative error {}", tolerance) : std::string(), order,
                     pose_momentum);
}

int StepCacheStats::full_steps() const { return static_cast<int>(std::count(full.begin(), full.end(), true)); }

torch::Tensor newton_extrapolate(const std::vector<double>& ts, const std::vector<torch::Tensor>& vs, double t) {
  SIMU_CHECK(!ts.empty() && ts.size() == vs.size(), "newton_extrapolate: {} times for {} values", ts.size(), vs.size());
  const size_t m = ts.size() - 1;
  // Divided differences in place: c[i] = f[t_{i-j} .. t_i] after pass j; c[j] = f[t_0 .. t_j] at the end.
  std::vector<torch::Tensor> c;
  for (const auto& v : vs) c.push_back(v.to(torch::kFloat32));
  for (size_t j = 1; j <= m; ++j)
    for (size_t i = m; i >= j; --i) {
      const double h = ts[i] - ts[i - j];
      SIMU_CHECK(h != 0, "newton_extrapolate: repeated time {}", ts[i]);
      c[i] = (c[i] - c[i - 1]) / h;
    }
  // Horner: p(t) = c0 + (t - t0)(c1 + (t - t1)(c2 + ...)).
  torch::Tensor p = c[m];
  for (size_t j = m; j-- > 0;) p = c[j] + (t - ts[j]) * p;
  return p;
}

StepCache::StepCache(const StepCacheOptions& options, int steps, std::set<std::string> extrapolated)
    : o_(options), steps_(steps), extrapolated_(std::move(extrapolated)) {
  stats_.full.assign(steps, false);
  stats_.guided.assign(steps, false);
  stats_.error.assign(steps, -1.0);
}

bool StepCache::need_full(int i, bool guided) {
  stats_.guided.at(i) = guided;
  const bool full = !o_.enabled || i < o_.warmup || i >= steps_ - o_.tail || history_.empty() || guided != regime_ ||
                    refresh_next_ || i - last_full_ >= o_.interval;
  stats_.full.at(i) = full;
  if (full && guided != regime_) history_.clear();  // the guided velocity jumps at the interval's edge
  regime_ = guided;
  return full;
}

void StepCache::record(int i, double t, const std::map<std::string, torch::Tensor>& v) {
  refresh_next_ = false;
  if (o_.tolerance > 0 && !history_.empty() && i - last_full_ > 1) {
    // After cheap steps: what a cheap step would have predicted here, against the evaluation.
    const auto pred = predict(t);
    double worst = 0;
    for (const auto& [k, vk] : v) {
      const auto ref = vk.to(torch::kFloat32);
      const double n = ref.norm().item<double>();
      worst = std::max(worst, (pred.at(k) - ref).norm().item<double>() / std::max(n, 1e-12));
    }
    stats_.error.at(i) = worst;
    refresh_next_ = worst > o_.tolerance;
  }
  Entry e{t, {}};
  for (const auto& [k, vk] : v) e.v[k] = vk.to(torch::kFloat32);
  history_.push_back(std::move(e));
  const size_t keep = static_cast<size_t>(std::max(o_.order, 1) + 1);
  if (history_.size() > keep) history_.erase(history_.begin(), history_.end() - keep);
  last_full_ = i;
}

std::map<std::string, torch::Tensor> StepCache::predict(double t) const {
  SIMU_CHECK(!history_.empty(), "step cache: no full evaluation to predict from");
  const size_t n = history_.size();
  const auto& a = history_.back();
  std::map<std::string, torch::Tensor> out;
  for (const auto& [k, va] : a.v) {
    if (extrapolated_.count(k)) {
      // Shape: Newton polynomial through the last min(order, n - 1) + 1 full evaluations.
      const size_t use = std::min(static_cast<size_t>(o_.order), n - 1) + 1;
      std::vector<double> ts;
      std::vector<torch::Tensor> vs;
      for (size_t j = n - use; j < n; ++j) ts.push_back(history_[j].t), vs.push_back(history_[j].v.at(k));
      out[k] = newton_extrapolate(ts, vs, t);
    } else if (n >= 2 && o_.pose_momentum > 0) {
      // Pose: anchored at the last full velocity, moved along the damped last trend.
      const auto& b = history_[n - 2];
      out[k] = va + (o_.pose_momentum * (t - a.t) / (a.t - b.t)) * (va - b.v.at(k));
    } else {
      out[k] = va;
    }
  }
  return out;
}

}  // namespace simu::models
