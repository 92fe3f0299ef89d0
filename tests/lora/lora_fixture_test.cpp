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
#include "test_util.h"

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

// Adapter parameters per analytic formula: r * sum(in + out) over the 5 shape projections per block.
int64_t analytic_params(int64_t r, int64_t C, int64_t Cc, int64_t blocks) {
  const int64_t per_block = (C + 3 * C) + (C + C) + (C + C) + (Cc + 2 * C) + (C + C);  // = 12C + Cc
  return r * per_block * blocks;
}

}  // namespace

TEST(LoraFixture, PeftAdapterReproducesPolicyAndReferenceLosses) {
  auto gen = small_generator();
  simu::lora::load_peft(simu::testing::fixture("lora_small"), *gen);
  EXPECT_EQ(simu::lora::lora_layers(*gen).size(), 10u);
  auto policy = losses(gen);
  EXPECT_TRUE(simu::testing::close(policy.pos, io().at("out.loss_pos_policy"), 1e-4, "loss_pos_policy"));
  EXPECT_TRUE(simu::testing::close(policy.neg, io().at("out.loss_neg_policy"), 1e-4, "loss_neg_policy"));
  fmt::print("policy rel err pos {:.3g} neg {:.3g}\n", simu::testing::rel_err(policy.pos, io().at("out.loss_pos_policy")),
             simu::testing::rel_err(policy.neg, io().at("out.loss_neg_policy")));
  // Adapters off = the base model.
  simu::lora::set_lora_enabled(*gen, false);
  auto ref = losses(gen);
  EXPECT_TRUE(simu::testing::close(ref.pos, io().at("out.loss_pos_ref"), 1e-4, "loss_pos_ref"));
  EXPECT_TRUE(simu::testing::close(ref.neg, io().at("out.loss_neg_ref"), 1e-4, "loss_neg_ref"));
  // ... exactly the model without any adapter.
  auto base = small_generator();
  auto plain = losses(base);
  EXPECT_TRUE(torch::equal(ref.pos, plain.pos));
  EXPECT_TRUE(torch::equal(ref.neg, plain.neg));
  // The adapter does change the policy (the check above is not vacuous).
  EXPECT_GT(simu::testing::rel_err(policy.pos, ref.pos), 1e-3);
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
  EXPECT_TRUE(simu::testing::close(per_pair, m.at("out.per_pair"), 1e-4, "per_pair"));
  EXPECT_TRUE(simu::testing::close(loss, m.at("out.loss"), 1e-4, "loss"));
  loss.backward();
  double worst = 0;
  for (auto& [name, p] : simu::lora::lora_parameters(*gen)) {
    const auto key = "grad." + simu::lora::peft_param_key(name);
    ASSERT_TRUE(m.count(key)) << key;
    ASSERT_TRUE(p.grad().defined()) << name;
    EXPECT_TRUE(simu::testing::close(p.grad(), m.at(key), 1e-4, key));
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
  EXPECT_TRUE(simu::testing::close(merged.pos, unmerged.pos, 1e-5, "merged pos"));
  EXPECT_TRUE(simu::testing::close(merged.neg, unmerged.neg, 1e-5, "merged neg"));
  simu::lora::unmerge_lora(*gen);
  for (auto& p : gen->named_parameters()) {
    if (!base.count(p.key())) continue;  // lora_*
    EXPECT_TRUE(simu::testing::close(p.value(), base.at(p.key()), 1e-6, p.key()));
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
  EXPECT_TRUE(simu::testing::close(m.pos, io().at("out.loss_pos_policy"), 1e-4, "merged checkpoint pos"));
  EXPECT_TRUE(simu::testing::close(m.neg, io().at("out.loss_neg_policy"), 1e-4, "merged checkpoint neg"));

  // The same through a training-checkpoint directory (adapter.safetensors with PEFT in-memory names).
  std::map<std::string, torch::Tensor> ckpt;
  for (auto& [name, t] : simu::lora::lora_parameters(*gen)) ckpt[simu::lora::peft_param_key(name)] = t;
  simu::data::save_safetensors(dir + "/ckpt/adapter.safetensors", ckpt);
  simu::fs::atomic_write(dir + "/ckpt/train_state.json", R"({"step": 3, "lora": {"r": 4, "alpha": 8}})");
  auto src = simu::lora::read_adapter_source(dir + "/ckpt");
  EXPECT_EQ(src.kind, "training-checkpoint");
  EXPECT_EQ(src.cfg.r, 4);
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
  simu::lora::LoraConfig cfg;
  cfg.r = 4;
  cfg.alpha = 8;
  auto report = simu::lora::inject_lora(*gen, cfg);
  EXPECT_EQ(report.layers, 10);
  EXPECT_EQ(report.parameters, analytic_params(4, 64, 48, 2));
  EXPECT_EQ(report.parameters, 6528);  // element count of lora_small/adapter_model.safetensors
}
