// AdamW, clipping and the schedule: fixture parity (official torch.optim.AdamW step) and plain math.
#include <cmath>

#include "data/safetensors.h"
#include "common/error.h"
#include "fmdpo_fixture.h"
#include "test_util.h"
#include "training/optim.h"

using namespace simu::training;

// Warm-up then constant / cosine, checked against the closed forms.
TEST(Schedule, WarmupConstantAndCosine) {
  OptimConfig c;
  c.lr = 1e-5;
  c.warmup_steps = 300;
  EXPECT_NEAR(learning_rate(c, 0, 1500), 1e-5 / 300, 1e-18);
  EXPECT_NEAR(learning_rate(c, 149, 1500), 1e-5 * 150 / 300, 1e-18);
  EXPECT_NEAR(learning_rate(c, 299, 1500), 1e-5, 1e-18);
  EXPECT_NEAR(learning_rate(c, 1499, 1500), 1e-5, 1e-18);
  c.schedule = "cosine";
  c.min_lr_ratio = 0.1;
  EXPECT_NEAR(learning_rate(c, 300, 1500), 1e-5, 1e-18);
  EXPECT_NEAR(learning_rate(c, 1499, 1500), 1e-6, 1e-15);
  // Midpoint of the cosine: halfway between lr and the floor.
  EXPECT_NEAR(learning_rate(c, 300 + 599, 1500), 0.5 * (1e-5 + 1e-6) + 0.5 * 0.9e-5 * std::cos(M_PI * 599.0 / 1199.0),
              1e-15);
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
  ASSERT_EQ(params.size(), 20u);
  const double norm = simu::testing::fmdpo_fixture_clipped_adamw_step(params);
  const double want = io.at("out.grad_norm_before_clip").item<double>();
  EXPECT_LE(std::abs(norm - want) / want, 1e-5) << norm << " vs " << want;
  double worst = 0;
  for (auto& [name, p] : params) {
    const auto& after = io.at("after_adamw." + name);
    EXPECT_TRUE(simu::testing::close(p, after, 1e-4, name));
    // The step itself (after - before) must match too, not just the (large) parameters.
    const auto& before = io.at("before." + name);
    worst = std::max(worst, simu::testing::rel_err(p.detach() - before, after - before));
  }
  EXPECT_LE(worst, 1e-3) << "max rel err of the update";
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
