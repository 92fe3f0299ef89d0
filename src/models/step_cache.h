// Opt-in step caching for Stage-1 sampling (issue 19), in the spirit of Fast-SAM3D's modality-aware
// step caching (arXiv 2602.05293): the flow model is evaluated in full only on some steps; on the others
// (the cheap steps) the velocity is predicted from the last full evaluations, per modality:
//   - shape (the protected stream's latents, e.g. `shape`): its velocity evolves smoothly in t and is
//     extrapolated with a finite-difference (Taylor / Newton) polynomial of degree `order` in t through
//     the last order + 1 full evaluations;
//   - pose (every other latent: `6drotation_normalized`, `scale`, `translation`, ...): its velocity is
//     volatile, so it is not extrapolated freely: it stays anchored at the last full evaluation and moves
//     along the last measured trend damped by `pose_momentum` (0 holds the last full velocity).
// CFG is unchanged: the full evaluations are the guided (batched conditional + unconditional) ones
// where CFG is active, and the prediction extrapolates the guided velocity (a linear combination of
// the two branches, so the same as extrapolating each branch). A step whose guidance state (inside or
// outside the CFG interval) differs from the last full evaluation's is always full, and the history is
// restarted there: the guided velocity jumps at the interval's edge.
//
// Cost in fidelity: the cheap steps integrate a predicted, not evaluated, velocity; the sample differs
// from full sampling with the same noise. It is opt-in (StepCacheOptions::enabled, default off: the
// sampler is then exactly the full one) and its error is measured, not assumed: tests/models/
// step_cache_test.cpp (small fixture model) and bench/bench_step_cache.cpp (decoded 64^3
// occupancy IoU and pose differences); docs/step_cache.md. Only the euler solver.
#pragma once

#include <torch/torch.h>

#include <map>
#include <set>
#include <string>
#include <vector>

namespace simu::models {

struct StepCacheOptions {
  bool enabled = false;  // off: every step is a full evaluation (the sampler as without this option)
  // A full evaluation at least every `interval` steps (1: every step, i.e. full sampling); the steps in
  // between are cheap (predicted).
  int interval = 2;
  // Shape extrapolation: 0 reuses the last full velocity, 1 linear, 2 quadratic in t (Newton divided
  // differences over the last order + 1 full evaluations of the same guidance state; fewer while the
  // history is shorter).
  int order = 1;
  int warmup = 2;  // leading steps always full (>= 1)
  int tail = 1;    // trailing steps always full (>= 0)
  // Pose latents: v = v_a + pose_momentum * (t - t_a) * (v_a - v_b) / (t_a - t_b) from the last two full
  // evaluations a (latest) and b; 0 holds v_a, 1 is a plain linear extrapolation. In [0, 1].
  double pose_momentum = 0.5;
  // Error-adaptive refresh (> 0): at each full evaluation that follows cheap steps, the prediction they
  // would have made for it is compared with it (max over latents of |pred - v| / |v|, Frobenius norms);
  // above the tolerance the next step is also full (and the interval counts from there). 0: off.
  double tolerance = 0.0;

  // Throws simu::Error naming the option (`where` prefixes the name, e.g. "--step-cache-interval" or
  // "step_cache.interval") when a value is out of range.
  void validate(const std::string& where = "step_cache.") const;
  // One line: "off" or "every 3rd step full (warmup 2, tail 1), shape order 1, pose momentum 0.5, ...".
  std::string describe() const;
};

// What a sampling with step caching did, per step (for benchmarks and tests).
struct StepCacheStats {
  std::vector<bool> full;     // step i was a full evaluation
  std::vector<bool> guided;   // step i is inside the CFG interval (a batch-2B forward when full)
  std::vector<double> error;  // per full step: the prediction's relative error (-1 where none was made)
  int full_steps() const;
};

// Newton divided-difference interpolation polynomial through (ts[j], vs[j]) (distinct times, any order)
// evaluated at t: exact for values that are a polynomial of degree < ts.size() in t (up to rounding).
// vs: same-shape tensors; the result is float32 when they are 16-bit.
torch::Tensor newton_extrapolate(const std::vector<double>& ts, const std::vector<torch::Tensor>& vs, double t);

// The schedule and the history of one sampling call.
class StepCache {
 public:
  // extrapolated: latent names that take the shape rule (the others take the pose rule).
  StepCache(const StepCacheOptions& options, int steps, std::set<std::string> extrapolated);
  // Whether step i (of `steps`, guidance state `guided`) needs a full evaluation.
  bool need_full(int i, bool guided);
  // Records the full evaluation of step i at time t (first measuring the prediction error when
  // options.tolerance > 0). v: the velocity per latent [B, T, ch].
  void record(int i, double t, const std::map<std::string, torch::Tensor>& v);
  // The predicted velocity at time t from the history (needs one full evaluation at least).
  std::map<std::string, torch::Tensor> predict(double t) const;
  const StepCacheStats& stats() const { return stats_; }

 private:
  struct Entry {
    double t;
    std::map<std::string, torch::Tensor> v;  // float32
  };
  StepCacheOptions o_;
  int steps_;
  std::set<std::string> extrapolated_;
  std::vector<Entry> history_;  // oldest first, same guidance state, at most max(order, 1) + 1 entries
  bool regime_ = false;         // guidance state of the history
  int last_full_ = -1;
  bool refresh_next_ = false;
  StepCacheStats stats_;
};

}  // namespace simu::models
