// AdamW, clipping and the schedule: fixture parity (official torch.optim.AdamW step) and plain math.
#include <cmath>

#include "data/safetensors.h"
#include "common/error.h"
#include "fmdpo_fixture.h"
#include "flow_rounding.h"
#include "test_util.h"
#include "training/optim.h"

using namespace simu::training;

// Warm-up then constant / cosine, checked against the closed forms.
TEST(Schedule, WarmupConstantAndCosine) {
  OptimConfig c;
  c.lr = 1e-5;
  c.warmup_steps = 300;
  // Values up to lr = 1e-5 from at most 8 float64 operations (a cosine included): absolute.
  const double tol = 1e-5 * simu::testing::gamma(8, simu::testing::kFp64Unit);
  EXPECT_NEAR(learning_rate(c, 0, 1500), 1e-5 / 300, tol);
  EXPECT_NEAR(learning_rate(c, 149, 1500), 1e-5 * 150 / 300, tol);
  EXPECT_NEAR(learning_rate(c, 299, 1500), 1e-5, tol);
  EXPECT_NEAR(learning_rate(c, 1499, 1500), 1e-5, tol);
  c.schedule = "cosine";
  c.min_lr_ratio = 0.1;
  EXPECT_NEAR(learning_rate(c, 300, 1500), 1e-5, tol);
  EXPECT_NEAR(learning_rate(c, 1499, 1500), 1e-6, tol);
  // Midpoint of the cosine: halfway between lr and the floor.
  EXPECT_NEAR(learning_rate(c, 300 + 599, 1500), 0.5 * (1e-5 + 1e-6) + 0.5 * 0.9e-5 * std::cos(M_PI * 599.0 / 1199.0),
              tol);
}

// fmdpo_small_io: grad norm before clipping and parameters after clip_grad_norm(1.0) + one AdamW step.
TEST(AdamW, MatchesFixtureClippedStep) {
  auto io = simu::testing::fmdpo_fixture();
  std::vector<std::pair<std::string, torch::Tensor>> params;
  for (auto& [k, v] : io) {
    if (k.rfind("before.", 0) != 0) continue;
    const std::string name = k.substr(7);
    auto p = v.clone().set_requires_grad(true);
    p.mutable_grad() = io.at("grad." + name).clone();
    params.emplace_back(name, p);
  }
  size_t fixture_params = 0;
  for (const auto& [k, v] : io) fixture_params += k.rfind("after_adamw.", 0) == 0;
  ASSERT_EQ(params.size(), fixture_params);
  // The same gradients: the norms differ by the official fp32 norm's rounding (per-tensor sums of
  // squares, then the norm of the norms: gamma(largest tensor + tensors + 4)); ours is float64.
  double largest = 0;
  for (const auto& [name, p] : params) largest = std::max(largest, static_cast<double>(p.numel()));
  const double norm_tol = simu::testing::gamma(largest + static_cast<double>(params.size()) + 4);
  const double norm = simu::testing::fmdpo_fixture_clipped_adamw_step(params);
  const double want = io.at("out.grad_norm_before_clip").item<double>();
  EXPECT_LE(std::abs(norm - want) / want, norm_tol) << norm << " vs " << want;
  const double lr = 1e-3, eps = 1e-8, coef = std::min(1.0, 1.0 / (want + 1e-6));
  double worst = 0, update_tol = 0;
  for (auto& [name, p] : params) {
    const auto& after = io.at("after_adamw." + name);
    const auto& before = io.at("before." + name);
    // The clipped gradient within coef norm_tol |g| elementwise (the clipping coefficient's error).
    const auto g = io.at("grad." + name).to(torch::kFloat64) * coef;
    const auto bound = simu::testing::adamw_first_step_bound(g, g.abs() * norm_tol, before, lr, eps);
    EXPECT_TRUE(simu::testing::within_bound(p, after, bound, name));
    // The step itself (after - before) must match too, not just the (large) parameters: relative to
    // the largest step (~lr), the bound's largest value.
    worst = std::max(worst, simu::testing::rel_err(p.detach() - before, after - before));
    update_tol = std::max(update_tol, bound.max().item<double>() / (after - before).abs().max().item<double>());
  }
  EXPECT_LE(worst, update_tol) << "max rel err of the update";
  std::printf("grad norm rel err %.3g, max update rel err %.3g\n", std::abs(norm - want) / want, worst);
}

// Saving and restoring the state continues exactly like an uninterrupted optimizer.
TEST(AdamW, StateRoundTripContinuesExactly) {
  OptimConfig c;
  c.lr = 1e-2;
  auto make = [] {
    torch::manual_seed(3);
    return std::vector<std::pair<std::string, torch::Tensor>>{{"a", torch::randn({4, 3}).set_requires_grad(true)},
                                                              {"b", torch::randn({5}).set_requires_grad(true)}};
  };
  auto grads = [](AdamW& o, int k) {
    torch::manual_seed(100 + k);
    for (auto& t : o.tensors()) t.mutable_grad() = torch::randn_like(t);
  };
  auto p1 = make();
  AdamW o1(p1, c);
  for (int k = 0; k < 5; ++k) { grads(o1, k); o1.step(1e-2); }
  auto p2 = make();
  AdamW o2(p2, c);
  for (int k = 0; k < 3; ++k) { grads(o2, k); o2.step(1e-2); }
  auto state = o2.state_dict();
  EXPECT_EQ(state.at("a.step").item<int64_t>(), 3);
  auto p3 = make();
  {
    torch::NoGradGuard ng;
    for (size_t i = 0; i < p3.size(); ++i) p3[i].second.copy_(p2[i].second);
  }
  AdamW o3(p3, c);
  o3.load_state_dict(state, "test");
  for (int k = 3; k < 5; ++k) { grads(o3, k); o3.step(1e-2); }
  for (size_t i = 0; i < p1.size(); ++i) EXPECT_TRUE(torch::equal(p1[i].second, p3[i].second)) << p1[i].first;
  // A mismatched state is an error naming the parameter.
  state["a.exp_avg"] = torch::zeros({2});
  try {
    o3.load_state_dict(state, "ckpt/optimizer.safetensors");
    FAIL() << "no error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("a: state shape"), std::string::npos) << e.what();
  }
}
