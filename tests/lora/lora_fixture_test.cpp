// LoRA on the small Stage-1 generator against the official fixtures: the PEFT adapter lora_small/
// imported into ss_generator_small must reproduce the FM losses of fmdpo_small_io (policy = adapter
// on, ref = adapter off) and the LoRA gradients of one FM-DPO step.
#include <fmt/format.h>

#include <set>

#include "common/fs.h"
#include "data/safetensors.h"
#include "lora/adapter_source.h"
#include "lora/lora.h"
#include "models/generator.h"
#include "flow_rounding.h"
#include "test_util.h"

#include <fstream>
#include <nlohmann/json.hpp>

namespace {

using simu::models::Generator;
using simu::models::Latents;

Generator small_generator(const std::string& weights = simu::testing::fixture("ss_generator_small.safetensors"),
                          const std::vector<std::string>& overrides = {}) {
  return simu::models::load_generator(simu::testing::fixture("ss_generator_small.json"), weights, torch::kCPU,
                                      overrides);
}

const std::map<std::string, torch::Tensor>& io() {
  static const auto m = simu::data::load_safetensors(simu::testing::fixture("fmdpo_small_io.safetensors"));
  return m;
}

// FM loss per pair, exactly as the fixture README: x_t = (1-t) eps + t x, target x - eps, the model
// gets t*1000 and d = 0, mean over tokens and channels of (pred_shape - target)^2. -> [B]
torch::Tensor fm_loss(Generator& gen, const torch::Tensor& x, const torch::Tensor& eps) {
  const auto& m = io();
  auto t = m.at("in.t");                                         // [B]
  auto tb = t.view({-1, 1, 1});
  Latents latents;
  latents["shape"] = (1 - tb) * eps + tb * x;                    // [B, 64, 8]
  for (const auto& [k, v] : m)
    if (k.rfind("in.pose.", 0) == 0) latents[k.substr(8)] = v;  // pose latents, fed as given
  auto d = torch::zeros_like(t);
  auto pred = gen->backbone()->forward(latents, t * 1000, m.at("in.cond"), d);
  return (pred.at("shape") - (x - eps)).pow(2).mean({1, 2});     // [B]
}

struct Losses {
  torch::Tensor pos, neg;
};
Losses losses(Generator& gen) {
  torch::NoGradGuard ng;
  const auto& m = io();
  return {fm_loss(gen, m.at("in.x_pos"), m.at("in.eps_pos")), fm_loss(gen, m.at("in.x_neg"), m.at("in.eps_neg"))};
}

// Two fp32 evaluations of a member's FM loss on the fixture (flow_rounding.h): one forward on the
// fixture's condition (the adapter's path, C + r terms, runs beside the base product), then the mean
// over a member's elements.
double loss_bound(Generator& gen) {
  const auto& m = io();
  const double fwd = simu::testing::flow_forward_bound(gen->config().backbone, m.at("in.cond").size(1));
  return simu::testing::fm_loss_bound(fwd, m.at("in.x_pos")[0].numel());
}

// The fixture adapter's layers: its lora_A tensors (lora_small/adapter_model.safetensors).
size_t adapter_layers() {
  const auto f = simu::data::SafeTensorsFile::open(simu::testing::fixture("lora_small/adapter_model.safetensors"));
  size_t n = 0;
  for (const auto& k : f.keys()) n += k.find("lora_A.weight") != std::string::npos;
  return n;
}

// The fixture adapter's settings (lora_small/adapter_config.json).
nlohmann::json adapter_config() {
  std::ifstream in(simu::testing::fixture("lora_small/adapter_config.json"));
  return nlohmann::json::parse(in);
}

// Adapter parameters per analytic formula: r * sum(in + out) over the 5 shape projections per block.
int64_t analytic_params(int64_t r, int64_t C, int64_t Cc, int64_t blocks) {
  const int64_t per_block = (C + 3 * C) + (C + C) + (C + C) + (Cc + 2 * C) + (C + C);  // = 12C + Cc
  return r * per_block * blocks;
}

}  // namespace

TEST(LoraFixture, PeftAdapterReproducesPolicyAndReferenceLosses) {
  auto gen = small_generator();
  simu::lora::load_peft(simu::testing::fixture("lora_small"), *gen);
  EXPECT_EQ(simu::lora::lora_layers(*gen).size(), adapter_layers());
  auto policy = losses(gen);
  const double tol = loss_bound(gen);  // the port's and the official losses: two fp32 evaluations
  EXPECT_TRUE(simu::testing::close(policy.pos, io().at("out.loss_pos_policy"), tol, "loss_pos_policy"));
  EXPECT_TRUE(simu::testing::close(policy.neg, io().at("out.loss_neg_policy"), tol, "loss_neg_policy"));
  fmt::print("policy rel err pos {:.3g} neg {:.3g}\n", simu::testing::rel_err(policy.pos, io().at("out.loss_pos_policy")),
             simu::testing::rel_err(policy.neg, io().at("out.loss_neg_policy")));
  // Adapters off = the base model.
  simu::lora::set_lora_enabled(*gen, false);
  auto ref = losses(gen);
  EXPECT_TRUE(simu::testing::close(ref.pos, io().at("out.loss_pos_ref"), tol, "loss_pos_ref"));
  EXPECT_TRUE(simu::testing::close(ref.neg, io().at("out.loss_neg_ref"), tol, "loss_neg_ref"));
  // ... exactly the model without any adapter.
  auto base = small_generator();
  auto plain = losses(base);
  EXPECT_TRUE(torch::equal(ref.pos, plain.pos));
  EXPECT_TRUE(torch::equal(ref.neg, plain.neg));
  // The adapter does change the policy (the check above is not vacuous): beyond both losses' rounding.
  EXPECT_GT(simu::testing::rel_err(policy.pos, ref.pos), 2 * tol);
}

TEST(LoraFixture, GradientsOfOneFmDpoStepMatch) {
  auto gen = small_generator();
  simu::lora::load_peft(simu::testing::fixture("lora_small"), *gen);
  const auto& m = io();
  // Reference losses without gradient, adapters off.
  simu::lora::set_lora_enabled(*gen, false);
  auto ref = losses(gen);
  simu::lora::set_lora_enabled(*gen, true);
  // Policy losses with gradient into the adapters only.
  auto pos = fm_loss(gen, m.at("in.x_pos"), m.at("in.eps_pos"));
  auto neg = fm_loss(gen, m.at("in.x_neg"), m.at("in.eps_neg"));
  const double beta = m.at("in.beta").item<double>();
  auto diff = (pos - neg) - (ref.pos - ref.neg);
  auto per_pair = -torch::log_sigmoid(-beta / 2 * diff);
  auto loss = (m.at("in.w") * per_pair).mean();
  // The four losses meet in a difference: an absolute bound on the per-pair terms (flow_rounding.h),
  // relative to their largest; the weighted mean adds B roundings.
  const double loss_tol = loss_bound(gen);
  const double max_loss = torch::stack({pos, neg, ref.pos, ref.neg}).abs().max().item<double>();
  const double max_pp = m.at("out.per_pair").abs().max().item<double>();
  const double pp_abs = simu::testing::dpo_per_pair_abs_bound(beta, loss_tol, max_loss, max_pp);
  EXPECT_TRUE(simu::testing::close(per_pair, m.at("out.per_pair"), pp_abs / max_pp, "per_pair"));
  const double loss_tol_dpo = pp_abs / max_pp + simu::testing::gamma(static_cast<double>(per_pair.numel()) + 1);
  EXPECT_TRUE(simu::testing::close(loss, m.at("out.loss"), loss_tol_dpo, "loss"));
  // The members' gradients apart (c_b = w_b sigmoid(beta/2 diff_b) beta / (2B), held constant): the
  // difference of the two can cancel (flow_rounding.h dpo_grad_bound).
  const auto params = simu::lora::lora_parameters(*gen);
  std::vector<torch::Tensor> leaves;
  for (const auto& [name, p] : params) leaves.push_back(p);
  const auto c = (m.at("in.w") * torch::sigmoid(beta / 2 * diff) * (beta / 2) / diff.numel()).detach();
  const auto g_pos = torch::autograd::grad({(c * pos).sum()}, leaves, {}, /*retain_graph=*/true);
  const auto g_neg = torch::autograd::grad({(c * neg).sum()}, leaves, {}, /*retain_graph=*/true);
  // A member's gradient: the forward, the backward, and the sum over its B x tokens rows.
  const auto& x = m.at("in.x_pos");
  const double member_tol = simu::testing::flow_gradient_bound(gen->config().backbone, m.at("in.cond").size(1),
                                                               x.size(0) * x.size(1)) +
                            loss_tol;
  loss.backward();
  double worst = 0;
  for (size_t i = 0; i < params.size(); ++i) {
    const auto& [name, p] = params[i];
    const auto key = "grad." + simu::lora::peft_param_key(name);
    ASSERT_TRUE(m.count(key)) << key;
    ASSERT_TRUE(p.grad().defined()) << name;
    const double g_max = m.at(key).abs().max().item<double>();
    const double tol = simu::testing::dpo_grad_bound(member_tol, pp_abs, g_pos[i].abs().max().item<double>(),
                                                     g_neg[i].abs().max().item<double>(), g_max);
    EXPECT_TRUE(simu::testing::close(p.grad(), m.at(key), tol, key));
    worst = std::max(worst, simu::testing::rel_err(p.grad(), m.at(key)));
  }
  fmt::print("max grad rel err {:.3g}\n", worst);
  // The base model got no gradient.
  for (auto& p : gen->named_parameters())
    if (p.key().find(".lora_") == std::string::npos) EXPECT_FALSE(p.value().grad().defined()) << p.key();
}

TEST(LoraFixture, MergedEqualsUnmergedAndUnmergeRestoresBase) {
  auto gen = small_generator();
  std::map<std::string, torch::Tensor> base;
  for (auto& p : gen->named_parameters()) base[p.key()] = p.value().detach().clone();
  simu::lora::load_peft(simu::testing::fixture("lora_small"), *gen);
  auto unmerged = losses(gen);
  simu::lora::merge_lora(*gen);
  auto merged = losses(gen);
  // Merged weights against base + adapter products: two fp32 evaluations of the losses.
  EXPECT_TRUE(simu::testing::close(merged.pos, unmerged.pos, loss_bound(gen), "merged pos"));
  EXPECT_TRUE(simu::testing::close(merged.neg, unmerged.neg, loss_bound(gen), "merged neg"));
  std::map<std::string, double> merged_max;
  for (auto& p : gen->named_parameters()) merged_max[p.key()] = p.value().abs().max().item<double>();
  simu::lora::unmerge_lora(*gen);
  for (auto& p : gen->named_parameters()) {
    if (!base.count(p.key())) continue;  // lora_*
    // (W + d) - d with d = s B A: the sum's and the difference's roundings (and d's, should it be
    // recomputed in another order), of values up to |W + d| + |W|, relative to |W|.
    const auto& w = base.at(p.key());
    const double w_max = std::max(w.abs().max().item<double>(), 1e-6);
    const double tol = simu::testing::gamma(4) * (merged_max.at(p.key()) + w_max) / w_max;
    EXPECT_TRUE(simu::testing::close(p.value(), w, tol, p.key()));
  }
}

TEST(LoraFixture, ExportImportAndMergedCheckpointRoundTrip) {
  const std::string dir = simu::testing::temp_dir("lora_fixture");
  auto gen = small_generator();
  auto cfg = simu::lora::load_peft(simu::testing::fixture("lora_small"), *gen);
  auto want = losses(gen);

  // PEFT export -> import into a fresh generator: identical outputs.
  simu::lora::save_peft(dir + "/peft", *gen, cfg, "ss_generator_small fixture");
  auto again = small_generator();
  simu::lora::load_peft(dir + "/peft", *again);
  auto got = losses(again);
  EXPECT_TRUE(torch::equal(got.pos, want.pos));
  EXPECT_TRUE(torch::equal(got.neg, want.neg));

  // Merged export: exactly the official key set, and it loads strictly as a plain generator whose
  // outputs equal the adapted model's.
  simu::lora::save_merged(dir + "/merged.safetensors", *gen);
  const auto merged_file = simu::data::SafeTensorsFile::open(dir + "/merged.safetensors");
  const auto official = simu::data::SafeTensorsFile::open(simu::testing::fixture("ss_generator_small.safetensors"));
  EXPECT_EQ(std::set<std::string>(merged_file.keys().begin(), merged_file.keys().end()),
            std::set<std::string>(official.keys().begin(), official.keys().end()));
  auto merged = small_generator(dir + "/merged.safetensors");
  auto m = losses(merged);
  // The merged model and the official adapted one: two fp32 evaluations of the losses.
  EXPECT_TRUE(simu::testing::close(m.pos, io().at("out.loss_pos_policy"), loss_bound(merged), "merged checkpoint pos"));
  EXPECT_TRUE(simu::testing::close(m.neg, io().at("out.loss_neg_policy"), loss_bound(merged), "merged checkpoint neg"));

  // The same through a training-checkpoint directory (adapter.safetensors with PEFT in-memory names).
  std::map<std::string, torch::Tensor> ckpt;
  for (auto& [name, t] : simu::lora::lora_parameters(*gen)) ckpt[simu::lora::peft_param_key(name)] = t;
  simu::data::save_safetensors(dir + "/ckpt/adapter.safetensors", ckpt);
  simu::fs::atomic_write(dir + "/ckpt/train_state.json",
                         fmt::format(R"({{"step": 3, "lora": {{"r": {}, "alpha": {}}}}})", cfg.r, cfg.alpha));
  auto src = simu::lora::read_adapter_source(dir + "/ckpt");
  EXPECT_EQ(src.kind, "training-checkpoint");
  EXPECT_EQ(src.cfg.r, cfg.r);
  auto third = small_generator();
  simu::lora::apply_adapter(src, *third);
  auto t = losses(third);
  EXPECT_TRUE(torch::equal(t.pos, want.pos));
}

TEST(LoraFixture, CountsOnRealSizeBlocks) {
  // Real-size config (1024 channels, cond 1024) cut to 2 blocks so it constructs in a second on CPU:
  // 5 layers per block and r * (12 C + Cc) parameters per block. (apps/lora_report prints the full 24.)
  auto gen = simu::models::load_generator(simu::testing::source_dir() + "/configs/stage1_real.yaml", "", torch::kCPU,
                                          {"module.generator.backbone.reverse_fn.backbone.num_blocks=2"});
  simu::lora::LoraConfig cfg;  // r 64, alpha 128, default targets
  auto report = simu::lora::inject_lora(*gen, cfg);
  EXPECT_EQ(report.layers, 10);
  EXPECT_EQ(report.parameters, analytic_params(64, 1024, 1024, 2));
  EXPECT_EQ(report.paths.front(), "reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape");
}

TEST(LoraFixture, SmallCountMatchesFixtureAdapter) {
  auto gen = small_generator("");
  const auto ac = adapter_config();
  simu::lora::LoraConfig cfg;
  cfg.r = ac.at("r").get<int64_t>();
  cfg.alpha = ac.at("lora_alpha").get<double>();
  auto report = simu::lora::inject_lora(*gen, cfg);
  EXPECT_EQ(report.layers, static_cast<int64_t>(adapter_layers()));
  const auto& c = gen->config().backbone;
  EXPECT_EQ(report.parameters, analytic_params(cfg.r, c.model_channels, c.cond_channels, c.num_blocks));
  // The element count of lora_small/adapter_model.safetensors.
  const auto f = simu::data::SafeTensorsFile::open(simu::testing::fixture("lora_small/adapter_model.safetensors"));
  int64_t elements = 0;
  for (const auto& k : f.keys()) {
    int64_t n = 1;
    for (const auto d : f.info(k).shape) n *= d;
    elements += n;
  }
  EXPECT_EQ(report.parameters, elements);
}
