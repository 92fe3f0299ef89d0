// Parity with the official FM-DPO step (fixtures/fmdpo_small_io.safetensors): the small Stage-1
// generator with the random PEFT adapter lora_small: per-member losses, per-pair terms, loss, every
// LoRA gradient, the grad norm before clipping and the parameters after one clipped AdamW step.
#include <cstring>

#include "data/safetensors.h"
#include "fmdpo_fixture.h"
#include "common/error.h"
#include "test_util.h"
#include "training/generator_policy.h"
#include "training/optim.h"

using namespace simu::training;

TEST(FmdpoParity, MatchesOfficialStep) {
  auto io = simu::data::load_safetensors(simu::testing::fixture("fmdpo_small_io.safetensors"));
  auto policy = make_generator_policy(simu::testing::fixture("ss_generator_small.json"),
                                      simu::testing::fixture("ss_generator_small.safetensors"), YAML::Node(),
                                      simu::testing::fixture("lora_small"), torch::kCPU);
  const FmdpoInputs in = simu::testing::fmdpo_fixture_inputs(io);
  auto terms = fmdpo_terms(*policy, in, io.at("in.beta").item<double>());
  EXPECT_TRUE(simu::testing::close(terms.loss_pos_policy, io.at("out.loss_pos_policy"), 1e-4, "loss_pos_policy"));
  EXPECT_TRUE(simu::testing::close(terms.loss_neg_policy, io.at("out.loss_neg_policy"), 1e-4, "loss_neg_policy"));
  EXPECT_TRUE(simu::testing::close(terms.loss_pos_ref, io.at("out.loss_pos_ref"), 1e-4, "loss_pos_ref"));
  EXPECT_TRUE(simu::testing::close(terms.loss_neg_ref, io.at("out.loss_neg_ref"), 1e-4, "loss_neg_ref"));
  EXPECT_TRUE(simu::testing::close(terms.per_pair, io.at("out.per_pair"), 1e-4, "per_pair"));
  EXPECT_TRUE(simu::testing::close(terms.loss, io.at("out.loss"), 1e-4, "loss"));
  std::printf("rel err: loss %.3g per_pair %.3g\n", simu::testing::rel_err(terms.loss, io.at("out.loss")),
              simu::testing::rel_err(terms.per_pair, io.at("out.per_pair")));
  terms.loss.backward();
  // PEFT file names (no adapter name) -> the fixture's parameter names (adapter "default").
  auto fixture_name = [](std::string n) {
    for (const char* ab : {".lora_A", ".lora_B"}) {
      auto pos = n.find(std::string(ab) + ".weight");
      if (pos != std::string::npos) n.replace(pos, std::strlen(ab) + 7, std::string(ab) + ".default.weight");
    }
    return n;
  };
  auto params = policy->adapter_parameters();
  ASSERT_EQ(params.size(), 20u);
  double worst = 0;
  for (auto& [name, p] : params) {
    const std::string key = "grad." + fixture_name(name);
    ASSERT_TRUE(io.count(key)) << key;
    ASSERT_TRUE(p.grad().defined()) << name;
    EXPECT_TRUE(simu::testing::close(p.grad(), io.at(key), 1e-4, key));
    worst = std::max(worst, simu::testing::rel_err(p.grad(), io.at(key)));
  }
  std::printf("max LoRA grad rel err %.3g\n", worst);
  const double norm = simu::testing::fmdpo_fixture_clipped_adamw_step(params);
  const double want = io.at("out.grad_norm_before_clip").item<double>();
  EXPECT_LE(std::abs(norm - want) / want, 1e-4) << norm << " vs " << want;
  for (auto& [name, p] : params)
    EXPECT_TRUE(simu::testing::close(p, io.at("after_adamw." + fixture_name(name)), 1e-4, name));
}
