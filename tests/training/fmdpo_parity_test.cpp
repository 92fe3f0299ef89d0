// Parity with the official FM-DPO step (fixtures/fmdpo_small_io.safetensors): the small Stage-1
// generator with the random PEFT adapter lora_small: per-member losses, per-pair terms, loss, every
// LoRA gradient, the grad norm before clipping and the parameters after one clipped AdamW step.
#include <cmath>
#include <cstring>

#include "data/safetensors.h"
#include "fmdpo_fixture.h"
#include "common/error.h"
#include "flow_rounding.h"
#include "models/generator.h"
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
  const double beta = io.at("in.beta").item<double>();
  auto terms = fmdpo_terms(*policy, in, beta);
  // The losses: the port's and the official, two fp32 evaluations (flow_rounding.h).
  const auto& cfg = simu::models::GeneratorConfig::from_official_file(simu::testing::fixture("ss_generator_small.json"));
  const double fwd = simu::testing::flow_forward_bound(cfg.backbone, in.cond.size(1));
  const double loss_tol = simu::testing::fm_loss_bound(fwd, in.x_pos[0].numel());
  EXPECT_TRUE(simu::testing::close(terms.loss_pos_policy, io.at("out.loss_pos_policy"), loss_tol, "loss_pos_policy"));
  EXPECT_TRUE(simu::testing::close(terms.loss_neg_policy, io.at("out.loss_neg_policy"), loss_tol, "loss_neg_policy"));
  EXPECT_TRUE(simu::testing::close(terms.loss_pos_ref, io.at("out.loss_pos_ref"), loss_tol, "loss_pos_ref"));
  EXPECT_TRUE(simu::testing::close(terms.loss_neg_ref, io.at("out.loss_neg_ref"), loss_tol, "loss_neg_ref"));
  // The four losses meet in a difference: an absolute bound on the per-pair terms, relative to their
  // largest; the weighted mean adds B roundings.
  const double max_loss = torch::stack({terms.loss_pos_policy, terms.loss_neg_policy, terms.loss_pos_ref, terms.loss_neg_ref})
                              .abs()
                              .max()
                              .item<double>();
  const double max_pp = io.at("out.per_pair").abs().max().item<double>();
  const double pp_abs = simu::testing::dpo_per_pair_abs_bound(beta, loss_tol, max_loss, max_pp);
  EXPECT_TRUE(simu::testing::close(terms.per_pair, io.at("out.per_pair"), pp_abs / max_pp, "per_pair"));
  const double dpo_loss_tol = pp_abs / max_pp + simu::testing::gamma(static_cast<double>(terms.per_pair.numel()) + 1);
  EXPECT_TRUE(simu::testing::close(terms.loss, io.at("out.loss"), dpo_loss_tol, "loss"));
  std::printf("rel err: loss %.3g per_pair %.3g\n", simu::testing::rel_err(terms.loss, io.at("out.loss")),
              simu::testing::rel_err(terms.per_pair, io.at("out.per_pair")));
  // The members' gradients apart (c_b = w_b sigmoid(beta/2 (d_theta - d_ref)_b) beta / (2B), held
  // constant): their difference can cancel (flow_rounding.h dpo_grad_bound).
  auto params = policy->adapter_parameters();
  std::vector<torch::Tensor> leaves;
  for (auto& [name, p] : params) leaves.push_back(p);
  const auto c = (in.w * torch::sigmoid(beta / 2 * (terms.d_theta - terms.d_ref)) * (beta / 2) / in.w.numel()).detach();
  const auto g_pos = torch::autograd::grad({(c * terms.loss_pos_policy).sum()}, leaves, {}, /*retain_graph=*/true);
  const auto g_neg = torch::autograd::grad({(c * terms.loss_neg_policy).sum()}, leaves, {}, /*retain_graph=*/true);
  // A member's gradient: the forward, the backward and the sum over the batch's 2B x tokens rows.
  const double member_tol =
      simu::testing::flow_gradient_bound(cfg.backbone, in.cond.size(1), 2 * in.x_pos.size(0) * in.x_pos.size(1)) + loss_tol;
  terms.loss.backward();
  // PEFT file names (no adapter name) -> the fixture's parameter names (adapter "default").
  auto fixture_name = [](std::string n) {
    for (const char* ab : {".lora_A", ".lora_B"}) {
      auto pos = n.find(std::string(ab) + ".weight");
      if (pos != std::string::npos) n.replace(pos, std::strlen(ab) + 7, std::string(ab) + ".default.weight");
    }
    return n;
  };
  size_t fixture_grads = 0;
  for (const auto& [k, v] : io) fixture_grads += k.rfind("grad.", 0) == 0;
  ASSERT_EQ(params.size(), fixture_grads);
  double worst = 0;
  std::vector<double> grad_tol(params.size());
  for (size_t i = 0; i < params.size(); ++i) {
    auto& [name, p] = params[i];
    const std::string key = "grad." + fixture_name(name);
    ASSERT_TRUE(io.count(key)) << key;
    ASSERT_TRUE(p.grad().defined()) << name;
    const double g_max = io.at(key).abs().max().item<double>();
    grad_tol[i] = simu::testing::dpo_grad_bound(member_tol, pp_abs, g_pos[i].abs().max().item<double>(),
                                                g_neg[i].abs().max().item<double>(), g_max);
    EXPECT_TRUE(simu::testing::close(p.grad(), io.at(key), grad_tol[i], key));
    worst = std::max(worst, simu::testing::rel_err(p.grad(), io.at(key)));
  }
  std::printf("max LoRA grad rel err %.3g\n", worst);
  // The norm of gradients each within grad_tol (times its largest value) of the fixture's: their
  // difference's norm, relative; plus the official fp32 norm's own rounding (per-tensor sums of
  // squares, then the norm of the norms: gamma(largest tensor + tensors + 4)).
  double dev2 = 0, largest = 0;
  for (size_t i = 0; i < params.size(); ++i) {
    const auto& want = io.at("grad." + fixture_name(params[i].first));
    const double d = grad_tol[i] * want.abs().max().item<double>();
    dev2 += d * d * static_cast<double>(want.numel());
    largest = std::max(largest, static_cast<double>(want.numel()));
  }
  const double want_norm = io.at("out.grad_norm_before_clip").item<double>();
  const double norm_tol = std::sqrt(dev2) / want_norm + simu::testing::gamma(largest + static_cast<double>(params.size()) + 4);
  const double norm = simu::testing::fmdpo_fixture_clipped_adamw_step(params);
  EXPECT_LE(std::abs(norm - want_norm) / want_norm, norm_tol) << norm << " vs " << want_norm;
  // After one clipped AdamW step (lr 1e-3, eps 1e-8, the fixture's settings): the clipped gradient is
  // known to within coef (grad_tol |g|max + norm_tol |g|), elementwise (flow_rounding.h).
  const double coef = std::min(1.0, 1.0 / (want_norm + 1e-6));
  for (size_t i = 0; i < params.size(); ++i) {
    const auto& [name, p] = params[i];
    const auto fixture = fixture_name(name);
    const auto g = io.at("grad." + fixture).to(torch::kFloat64) * coef;
    const auto dg = coef * (grad_tol[i] * io.at("grad." + fixture).abs().max().item<double>() +
                            norm_tol * io.at("grad." + fixture).to(torch::kFloat64).abs());
    const auto bound = simu::testing::adamw_first_step_bound(g, dg, io.at("before." + fixture), 1e-3, 1e-8);
    EXPECT_TRUE(simu::testing::within_bound(p, io.at("after_adamw." + fixture), bound, name));
  }
}
