// Per-block activation checkpointing on the small Stage-1 fixture generator (fp32 CPU): the FM-DPO
// losses and every LoRA gradient equal those of the plain forward/backward, each MOT block runs as its
// own checkpointed segment, and with LoRA dropout > 0 the recompute replays the forward's masks.
#include <ATen/CPUGeneratorImpl.h>

#include <functional>
#include <set>
#include <unordered_set>

#include "data/safetensors.h"
#include "fmdpo_fixture.h"
#include "flow_rounding.h"
#include "models/generator.h"
#include "test_util.h"
#include "training/generator_policy.h"

using namespace simu::training;

namespace {

// The fixture's FM-DPO inputs.
FmdpoInputs fixture_inputs() { return simu::testing::fmdpo_fixture_inputs(simu::testing::fmdpo_fixture()); }

// Number of checkpointed segments (CheckpointFunction nodes) in the graph behind t.
int count_segments(const torch::Tensor& t) {
  std::unordered_set<torch::autograd::Node*> seen;
  std::function<int(const std::shared_ptr<torch::autograd::Node>&)> walk = [&](const auto& node) -> int {
    if (!node || !seen.insert(node.get()).second) return 0;
    int n = node->name().find("CheckpointFunction") != std::string::npos ? 1 : 0;
    for (const auto& e : node->next_edges()) n += walk(e.function);
    return n;
  };
  return walk(t.grad_fn());
}

struct Result {
  FmdpoTerms terms;
  std::vector<torch::Tensor> grads;
  int segments = 0;
};

// One FM-DPO forward + backward from a fixed RNG state; grads cleared first.
Result run(PolicyModel& policy, const FmdpoInputs& in, bool checkpoint, uint64_t seed) {
  for (auto& [n, p] : policy.adapter_parameters()) p.mutable_grad() = torch::Tensor();
  torch::manual_seed(seed);
  Result r;
  r.terms = fmdpo_terms(policy, in, 500.0, checkpoint);
  r.segments = count_segments(r.terms.loss);
  r.terms.loss.backward();
  for (auto& [n, p] : policy.adapter_parameters()) {
    EXPECT_TRUE(p.grad().defined()) << n;
    r.grads.push_back(p.grad().clone());
  }
  return r;
}

// Compares two runs bit for bit: losses, per-pair terms and every gradient. A checkpointed segment
// evaluates the same operations on the same inputs as the plain forward (first under no-grad, again in
// the backward's recompute, from the same RNG state), so by design nothing differs, not even rounding.
void expect_same(const Result& a, const Result& b, PolicyModel& policy) {
  EXPECT_TRUE(torch::equal(a.terms.loss_pos_policy, b.terms.loss_pos_policy)) << "loss_pos_policy";
  EXPECT_TRUE(torch::equal(a.terms.loss_neg_policy, b.terms.loss_neg_policy)) << "loss_neg_policy";
  EXPECT_TRUE(torch::equal(a.terms.per_pair, b.terms.per_pair)) << "per_pair";
  EXPECT_TRUE(torch::equal(a.terms.loss, b.terms.loss)) << "loss";
  auto names = policy.adapter_parameters();
  ASSERT_EQ(a.grads.size(), b.grads.size());
  for (size_t i = 0; i < a.grads.size(); ++i)
    EXPECT_TRUE(torch::equal(a.grads[i], b.grads[i])) << names[i].first << ": rel err "
                                                       << simu::testing::rel_err(a.grads[i], b.grads[i]);
}

// The fixture generator's MOT blocks (ss_generator_small.json).
int64_t fixture_blocks() {
  return simu::models::GeneratorConfig::from_official_file(simu::testing::fixture("ss_generator_small.json"))
      .backbone.num_blocks;
}

}  // namespace

// The fixture's trained adapter (dropout 0): checkpointed == plain, one segment per block.
TEST(BlockCheckpointing, SameLossesAndLoraGradsAsPlain) {
  auto policy = make_generator_policy(simu::testing::fixture("ss_generator_small.json"),
                                      simu::testing::fixture("ss_generator_small.safetensors"), YAML::Node(),
                                      simu::testing::fixture("lora_small"), torch::kCPU);
  const auto in = fixture_inputs();
  auto plain = run(*policy, in, false, 1);
  auto ckpt = run(*policy, in, true, 1);
  EXPECT_EQ(plain.segments, 0);
  EXPECT_EQ(ckpt.segments, fixture_blocks()) << "expected one checkpointed segment per MOT block";
  ASSERT_EQ(ckpt.grads.size(), policy->adapter_parameters().size());
  expect_same(ckpt, plain, *policy);
  // Switched off after the policy forward: a plain run afterwards records no segment.
  EXPECT_EQ(run(*policy, in, false, 1).segments, 0);
  // Gradients accumulate across calls like plain ones (two backward passes = twice the gradient).
  for (auto& [n, p] : policy->adapter_parameters()) p.mutable_grad() = torch::Tensor();
  fmdpo_terms(*policy, in, 500.0, true).loss.backward();
  fmdpo_terms(*policy, in, 500.0, true).loss.backward();
  // g + g for the same g: exactly 2 g.
  auto params = policy->adapter_parameters();
  for (size_t i = 0; i < params.size(); ++i)
    EXPECT_TRUE(torch::equal(params[i].second.grad(), plain.grads[i] * 2)) << params[i].first << " x2";
}

// LoRA dropout 0.3 (fresh adapters, randomized so that every gradient is non-trivial): the backward
// recompute replays the forward's dropout masks (same RNG state), so gradients equal the plain run
// from the same seed, and the generator ends where the plain run leaves it.
TEST(BlockCheckpointing, DropoutMasksReplayedInRecompute) {
  YAML::Node lora = YAML::Load("{r: 4, alpha: 8, dropout: 0.3}");
  auto policy = make_generator_policy(simu::testing::fixture("ss_generator_small.json"),
                                      simu::testing::fixture("ss_generator_small.safetensors"), lora, "", torch::kCPU);
  {
    torch::NoGradGuard ng;
    auto g = at::make_generator<at::CPUGeneratorImpl>(3);
    for (auto& [n, p] : policy->adapter_parameters()) p.copy_(at::randn(p.sizes(), g) * 0.1);
  }
  const auto in = fixture_inputs();
  auto plain = run(*policy, in, false, 11);
  const double after_plain = torch::rand({1}).item<double>();
  auto ckpt = run(*policy, in, true, 11);
  const double after_ckpt = torch::rand({1}).item<double>();
  EXPECT_EQ(ckpt.segments, fixture_blocks());
  EXPECT_EQ(after_plain, after_ckpt) << "the recompute left the CPU generator elsewhere";
  expect_same(ckpt, plain, *policy);
  // The masks matter: another seed gives other gradients (so the equality above is not vacuous),
  // further apart than two fp32 evaluations of one gradient could be (flow_rounding.h).
  auto other = run(*policy, in, false, 12);
  const double grad_tol = simu::testing::flow_gradient_bound(
      simu::models::GeneratorConfig::from_official_file(simu::testing::fixture("ss_generator_small.json")).backbone,
      in.cond.size(1), 2 * in.x_pos.size(0) * in.x_pos.size(1));
  EXPECT_GT(simu::testing::rel_err(other.grads[0], plain.grads[0]), grad_tol);
}
