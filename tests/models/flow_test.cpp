// Stage-1 flow model and generator against the official fixtures (ss_generator_small, ss_generator_variant).
#include <ATen/CPUGeneratorImpl.h>
#include <fmt/format.h>

#include "common/error.h"
#include "data/safetensors.h"
#include "models/generator.h"
#include "models/weights.h"
#include "test_util.h"

namespace {

using simu::models::Generator;
using simu::models::Latents;

struct Fixture {
  Generator gen{nullptr};
  std::map<std::string, torch::Tensor> io;
};

Fixture load(const std::string& name) {
  Fixture f;
  f.gen = simu::models::load_generator(simu::testing::fixture(name + ".json"),
                                       simu::testing::fixture(name + ".safetensors"), torch::kCPU);
  f.io = simu::data::load_safetensors(simu::testing::fixture(name + "_io.safetensors"));
  return f;
}

Latents with_prefix(const std::map<std::string, torch::Tensor>& io, const std::string& prefix) {
  Latents out;
  for (const auto& [k, v] : io)
    if (k.rfind(prefix, 0) == 0) out[k.substr(prefix.size())] = v;
  return out;
}

// Compares every latent of got with io[prefix + name]; prints the max relative error.
void expect_close(const Latents& got, const std::map<std::string, torch::Tensor>& io, const std::string& prefix,
                  const std::string& tag) {
  const auto want = with_prefix(io, prefix);
  ASSERT_EQ(got.size(), want.size()) << tag;
  double worst = 0;
  for (const auto& [k, w] : want) {
    ASSERT_TRUE(got.count(k)) << tag << ": missing " << k;
    EXPECT_TRUE(simu::testing::close(got.at(k), w, 1e-4, tag + "." + k));
    worst = std::max(worst, simu::testing::rel_err(got.at(k), w));
  }
  fmt::print("[{}] max rel err {:.3g}\n", tag, worst);
}

Latents forward_fixture(Fixture& f, bool with_d) {
  torch::NoGradGuard ng;
  auto x = with_prefix(f.io, "in.latent.");
  auto t = f.io.at("in.t") * 1000;
  c10::optional<torch::Tensor> d;
  if (with_d) d = f.io.at("in.d") * 1000;
  return f.gen->backbone()->forward(x, t, f.io.at("in.cond"), d);
}

}  // namespace

TEST(FlowModel, SmallForwardMatchesOfficial) {
  auto f = load("ss_generator_small");
  expect_close(forward_fixture(f, true), f.io, "out.forward.", "small.forward");
}

TEST(FlowModel, VariantForwardMatchesOfficial) {
  auto f = load("ss_generator_variant");
  expect_close(forward_fixture(f, false), f.io, "out.forward.", "variant.forward");
}

TEST(FlowModel, StateDictKeysAreOfficial) {
  auto f = load("ss_generator_small");
  const auto state = simu::models::state_dict(*f.gen);
  EXPECT_TRUE(state.count("reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape.weight"));
  EXPECT_TRUE(state.count("reverse_fn.backbone.blocks.1.cross_attn.6drotation_normalized.to_kv.bias"));
  EXPECT_TRUE(state.count("reverse_fn.backbone.latent_mapping.shape.pos_emb"));
  // Same key set as the file (after the prefix).
  const auto file = simu::data::SafeTensorsFile::open(simu::testing::fixture("ss_generator_small.safetensors"));
  EXPECT_EQ(state.size(), file.keys().size());
}

TEST(Generator, SmallSampleCfgMatchesOfficial) {
  auto f = load("ss_generator_small");
  auto o = simu::models::SampleOptions::from(f.gen->config());
  EXPECT_EQ(o.steps, 4);
  EXPECT_FALSE(o.shortcut);  // no_shortcut: d = 0
  auto y = f.gen->sample(f.io.at("in.cond"), with_prefix(f.io, "in.sample.x0."), o);
  expect_close(y, f.io, "out.sample_cfg.", "small.sample_cfg");
}

TEST(Generator, SmallSampleShortcutMatchesOfficial) {
  auto f = load("ss_generator_small");
  auto o = simu::models::SampleOptions::from(f.gen->config());
  o.shortcut = true;
  o.cfg_strength = 0;
  auto y = f.gen->sample(f.io.at("in.cond"), with_prefix(f.io, "in.sample.x0."), o);
  expect_close(y, f.io, "out.sample_shortcut.", "small.sample_shortcut");
}

TEST(Generator, VariantSampleCfgMatchesOfficial) {
  auto f = load("ss_generator_variant");
  auto o = simu::models::SampleOptions::from(f.gen->config());
  EXPECT_EQ(o.steps, 5);
  auto y = f.gen->sample(f.io.at("in.cond"), with_prefix(f.io, "in.sample.x0."), o);
  expect_close(y, f.io, "out.sample_cfg.", "variant.sample_cfg");
}

// CFG batched in one forward equals two separate forwards combined by hand: y = (1+s) y_c - s y_u.
TEST(Generator, BatchedCfgEqualsTwoForwards) {
  auto f = load("ss_generator_variant");
  torch::NoGradGuard ng;
  auto x = with_prefix(f.io, "in.latent.");
  auto cond = f.io.at("in.cond");
  const double s = 3.0, t = 700.0;
  auto guided = f.gen->reverse_fn->forward(x, t, cond, c10::nullopt, s, {300, 1000});
  auto tt = torch::full({2}, t);
  auto yc = f.gen->backbone()->forward(x, tt, cond);
  auto yu = f.gen->backbone()->forward(x, tt, cond * 0);
  for (const auto& [k, v] : guided) EXPECT_TRUE(simu::testing::close(v, (1 + s) * yc.at(k) - s * yu.at(k), 1e-5, k));
  // Outside the interval: the plain conditional velocity.
  auto plain = f.gen->reverse_fn->forward(x, 100.0, cond, c10::nullopt, s, {300, 1000});
  auto yc100 = f.gen->backbone()->forward(x, torch::full({2}, 100.0), cond);
  for (const auto& [k, v] : plain) EXPECT_TRUE(simu::testing::close(v, yc100.at(k), 1e-6, k));
}

// An all-zero condition row (CFG's unconditional half under force_zeros_cond) makes every key the
// same, so cross attention there is the value bias: a cache that skips those rows (zero_from) gives
// the forward of the full cache, and the sampler that uses it still matches the official fixture
// (SmallSampleCfgMatchesOfficial).
TEST(FlowModel, ZeroConditionRowsTakeTheValueBias) {
  for (const char* name : {"ss_generator_small", "ss_generator_variant"}) {
    auto f = load(name);
    torch::NoGradGuard ng;
    auto x1 = with_prefix(f.io, "in.latent.");
    Latents x;
    for (const auto& [k, v] : x1) x[k] = torch::cat({v.narrow(0, 0, 1), v.narrow(0, 0, 1)}, 0);
    auto c = f.io.at("in.cond").narrow(0, 0, 1);
    auto pair = torch::cat({c, c * 0}, 0);  // [2, L, Cc]
    auto t = torch::full({1}, 700.0);
    auto bb = f.gen->backbone();
    auto full = bb->condition_cache(pair);
    auto skip = bb->condition_cache(pair, 1);
    ASSERT_EQ(skip.kv[0][0].k.size(0), 1) << "the zero row's keys should not be computed";
    auto want = bb->forward(x, t, pair, c10::nullopt, &full);
    auto got = bb->forward(x, t, pair, c10::nullopt, &skip);
    for (const auto& [k, v] : want) EXPECT_TRUE(simu::testing::close(got.at(k), v, 1e-5, std::string(name) + "." + k));
    // Independent: the uncached forward of the zero row alone.
    Latents xu;
    for (const auto& [k, v] : x1) xu[k] = v.narrow(0, 0, 1);
    auto yu = bb->forward(xu, t, c * 0);
    for (const auto& [k, v] : yu) EXPECT_TRUE(simu::testing::close(got.at(k).narrow(0, 1, 1), v, 1e-5, std::string(name) + ".u." + k));
  }
}

// The shape stream never attends to pose tokens: changing every pose input leaves the shape output.
TEST(FlowModel, ShapeOutputIndependentOfPose) {
  for (const char* name : {"ss_generator_small", "ss_generator_variant"}) {
    auto f = load(name);
    const bool with_d = f.gen->config().backbone.is_shortcut_model;
    auto a = forward_fixture(f, with_d);
    for (auto& [k, v] : f.io)
      if (k.rfind("in.latent.", 0) == 0 && k != "in.latent.shape") v = torch::randn_like(v) * 5;
    auto b = forward_fixture(f, with_d);
    EXPECT_TRUE(torch::equal(a.at("shape"), b.at("shape"))) << name;
    bool pose_changed = false;
    for (const auto& [k, v] : a)
      if (k != "shape") pose_changed = pose_changed || !torch::allclose(v, b.at(k));
    EXPECT_TRUE(pose_changed) << name << ": pose outputs should depend on pose inputs";
  }
}

// FM-DPO's two members share their pair's condition: a condition of B rows for 2B token rows, pair-major
// (rows 2b and 2b + 1 over condition b), gives the forward of the condition repeated per row
// (repeat_interleave), outputs and to_kv gradients.
TEST(FlowModel, SharedConditionEqualsRepeatedCondition) {
  for (const char* name : {"ss_generator_small", "ss_generator_variant"}) {
    auto f = load(name);
    auto bb = f.gen->backbone();
    const bool with_d = f.gen->config().backbone.is_shortcut_model;
    // Row 2b: the fixture's row b; row 2b + 1: a second member of it.
    auto x = with_prefix(f.io, "in.latent.");
    for (auto& [k, v] : x) v = torch::stack({v, torch::randn_like(v)}, 1).flatten(0, 1);  // [2B, T, C]
    const auto cond = f.io.at("in.cond");                                                // [B, L, Cc]
    auto t = f.io.at("in.t").repeat_interleave(2) * 1000;
    c10::optional<torch::Tensor> d;
    if (with_d) d = f.io.at("in.d").repeat_interleave(2) * 1000;
    auto& to_kv = bb->blocks->ptr<simu::models::MOTBlockImpl>(0)->cross_attn[0]->to_kv->weight;
    to_kv.set_requires_grad(true);
    // One pass per layout: outputs, then the gradient of the shape output's sum.
    auto run = [&](const torch::Tensor& c) {
      to_kv.mutable_grad() = torch::Tensor();
      auto y = bb->forward(x, t, c, d);
      y.at("shape").sum().backward();
      return std::make_pair(y, to_kv.grad().clone());
    };
    auto [shared, g_shared] = run(cond);
    auto [repeated, g_repeated] = run(cond.repeat_interleave(2, 0));
    to_kv.set_requires_grad(false);
    ASSERT_EQ(shared.size(), repeated.size());
    for (const auto& [k, v] : repeated)
      EXPECT_TRUE(simu::testing::close(shared.at(k).detach(), v.detach(), 1e-6, std::string(name) + "." + k));
    EXPECT_TRUE(simu::testing::close(g_shared, g_repeated, 1e-6, std::string(name) + ".to_kv.grad"));
    EXPECT_GT(g_shared.abs().max().item<double>(), 0) << name;
    // The fixture's rows (2b) give the official forward's output.
    Latents fixture_rows;
    for (const auto& [k, v] : shared) fixture_rows[k] = v.detach().slice(0, 0, c10::nullopt, 2);
    expect_close(fixture_rows, f.io, "out.forward.", std::string(name) + ".shared");
    // Rows that are not a multiple of the condition's are refused, naming both counts.
    auto x3 = x;
    for (auto& [k, v] : x3) v = v.narrow(0, 0, 3);
    if (cond.size(0) == 2)
      EXPECT_THROW(bb->forward(x3, t.narrow(0, 0, 3), cond, with_d ? c10::optional<torch::Tensor>(d->narrow(0, 0, 3)) : d),
                   simu::Error);
  }
}

// Asking for the shape latent alone runs only the protected shape stream: the same shape output as
// the full forward (it never reads the pose stream), only that latent returned; a pose latent needs
// every stream; unknown names are refused.
TEST(FlowModel, OutputLatentsRunOnlyTheStreamsTheyNeed) {
  for (const char* name : {"ss_generator_small", "ss_generator_variant"}) {
    auto f = load(name);
    const bool with_d = f.gen->config().backbone.is_shortcut_model;
    auto full = forward_fixture(f, with_d);
    auto bb = f.gen->backbone();
    bb->set_output_latents({"shape"});
    auto shape_only = forward_fixture(f, with_d);
    ASSERT_EQ(shape_only.size(), 1u) << name;
    EXPECT_TRUE(torch::equal(shape_only.at("shape"), full.at("shape"))) << name;
    expect_close({{"shape", shape_only.at("shape")}}, {{"out.forward.shape", f.io.at("out.forward.shape")}},
                 "out.forward.", std::string(name) + ".shape_only");
    // A pose latent (in the unprotected stream): everything runs, the one latent comes back.
    const std::string pose = [&] {
      for (const auto& [k, v] : full)
        if (k != "shape") return k;
      return std::string();
    }();
    bb->set_output_latents({pose});
    auto pose_only = forward_fixture(f, with_d);
    ASSERT_EQ(pose_only.size(), 1u) << name;
    EXPECT_TRUE(torch::equal(pose_only.at(pose), full.at(pose))) << name;
    EXPECT_THROW(bb->set_output_latents({"no_such_latent"}), simu::Error);
    bb->set_output_latents({});
    EXPECT_EQ(forward_fixture(f, with_d).size(), full.size()) << name;
  }
}

TEST(FlowModel, StrictLoadingListsMismatches) {
  auto cfg = simu::models::GeneratorConfig::from_official_file(simu::testing::fixture("ss_generator_small.json"));
  cfg.backbone.num_blocks = 3;          // one block too many -> missing keys
  cfg.backbone.cond_channels = 40;      // wrong to_kv shapes
  Generator g(cfg);
  try {
    simu::models::LoadOptions lo;
    lo.strip_prefix = "_base_models.generator.";
    simu::models::load_safetensors_into(*g, simu::testing::fixture("ss_generator_small.safetensors"), lo);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("shape mismatches"), std::string::npos) << m;
    EXPECT_NE(m.find("cross_attn.shape.to_kv.weight: got [128, 48] expected [128, 40]"), std::string::npos) << m;
    EXPECT_NE(m.find("missing keys"), std::string::npos) << m;
    EXPECT_NE(m.find("blocks.2."), std::string::npos) << m;
  }
  // An unexpected key (config without translation_scale) is reported too.
  auto cfg2 = simu::models::GeneratorConfig::from_official_file(simu::testing::fixture("ss_generator_small.json"));
  cfg2.backbone.latents.pop_back();
  cfg2.backbone.share_groups[0].second.pop_back();
  Generator g2(cfg2);
  simu::models::LoadOptions lo;
  lo.strip_prefix = "_base_models.generator.";
  try {
    simu::models::load_safetensors_into(*g2, simu::testing::fixture("ss_generator_small.safetensors"), lo);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("unexpected keys"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("latent_mapping.translation_scale.pos_emb"), std::string::npos) << e.what();
  }
  // A pickle checkpoint path tells to convert it.
  EXPECT_THROW(simu::models::load_generator(simu::testing::fixture("ss_generator_small.json"), "x/ss_generator.ckpt",
                                            torch::kCPU),
               simu::Error);
}

TEST(Generator, SameSeedSameResult) {
  auto f = load("ss_generator_small");
  auto o = simu::models::SampleOptions::from(f.gen->config());
  o.steps = 2;
  auto run = [&](uint64_t seed) {
    auto g = at::make_generator<at::CPUGeneratorImpl>(seed);
    auto x0 = f.gen->noise(2, g, torch::kCPU);
    EXPECT_EQ(x0.at("shape").sizes(), (std::vector<int64_t>{2, 64, 8}));
    return f.gen->sample(f.io.at("in.cond"), x0, o);
  };
  auto a = run(7), b = run(7), c = run(8);
  for (const auto& [k, v] : a) EXPECT_TRUE(torch::equal(v, b.at(k))) << k;
  EXPECT_FALSE(torch::equal(a.at("shape"), c.at("shape")));
}

TEST(Generator, TrainingTimeSamplerIsLogitNormal) {
  auto g = at::make_generator<at::CPUGeneratorImpl>(3);
  auto t = simu::models::sample_training_t(20000, g);
  ASSERT_EQ(t.sizes(), (std::vector<int64_t>{20000}));
  EXPECT_GT(t.min().item<float>(), 0.0f);
  EXPECT_LT(t.max().item<float>(), 1.0f);
  // logit(t) ~ N(0, 1)
  auto logit = torch::log(t / (1 - t));
  EXPECT_NEAR(logit.mean().item<double>(), 0.0, 0.03);
  EXPECT_NEAR(logit.std().item<double>(), 1.0, 0.03);
}

TEST(Generator, TimeGridIsOfficial) {
  auto f = load("ss_generator_small");
  // rescale_t = 3, 4 steps: s/(1 + 2(1 - s)) for s = 0, .25, .5, .75, 1
  auto grid = f.gen->time_grid(4, 3.0, false);
  const std::vector<double> want = {0.0, 0.1, 0.25, 0.5, 1.0};
  ASSERT_EQ(grid.size(), want.size());
  for (size_t i = 0; i < want.size(); ++i) EXPECT_NEAR(grid[i], want[i], 1e-12);
  auto rev = f.gen->time_grid(4, 1.0, true);
  EXPECT_NEAR(rev.front(), 1.0, 1e-12);
  EXPECT_NEAR(rev.back(), 0.0, 1e-12);
}

// The project config layout (configs/stage1_small.yaml) builds the same model as the official JSON.
TEST(FlowModel, ProjectConfigMatchesOfficialLayout) {
  auto gen = simu::models::load_generator(simu::testing::source_dir() + "/configs/stage1_small.yaml",
                                          simu::testing::fixture("ss_generator_small.safetensors"), torch::kCPU);
  Fixture f{gen, simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"))};
  expect_close(forward_fixture(f, true), f.io, "out.forward.", "small.forward(project yaml)");
  auto o = simu::models::SampleOptions::from(gen->config());
  EXPECT_EQ(o.steps, 4);
  EXPECT_DOUBLE_EQ(o.cfg_strength, 7.0);
  EXPECT_FALSE(o.shortcut);
}

// The real-size config parses into the documented model (no weights built: 1.3 B parameters).
TEST(FlowModel, RealConfigDescribesTheReleasedModel) {
  auto c = simu::models::GeneratorConfig::from_official_file(simu::testing::source_dir() + "/configs/stage1_real.yaml");
  EXPECT_EQ(c.kind, "ShortCut");
  EXPECT_EQ(c.inference_steps, 25);
  EXPECT_EQ(c.backbone.model_channels, 1024);
  EXPECT_EQ(c.backbone.num_blocks, 24);
  EXPECT_EQ(c.backbone.num_heads, 16);
  EXPECT_EQ(c.backbone.cond_channels, 1024);
  EXPECT_EQ(c.backbone.latent("shape").tokens(), 4096);
  EXPECT_EQ(c.backbone.stream_names(), (std::vector<std::string>{"shape", "6drotation_normalized"}));
  // FLOPs of one sample at 2800 condition tokens, counted by hand: C = 1024, shape T = 4096 (attends to
  // itself), pose T = 4 (attends to 4100 keys), hidden 4096, 24 blocks, + io and adaLN.
  const double C = 1024, L = 2800, H = 4096;
  auto stream = [&](double T, double keys) {
    return 8 * T * C * C + 4 * T * keys * C + 4 * T * C * C + 4 * L * C * C + 4 * T * L * C + 4 * T * C * H;
  };
  const double io = 4 * C * (4096 * 8 + 6 + 3 + 3 + 1);
  const double want = 24 * (stream(4096, 4096) + stream(4, 4100)) + io + 24 * 2 * C * 6 * C;
  EXPECT_NEAR(simu::models::flow_forward_flops(c.backbone, 1, 2800) / want, 1.0, 1e-12);
}

// Reusing the condition keys/values over the steps (the default) gives the result of recomputing them.
TEST(Generator, ConditionCacheMatchesRecomputation) {
  for (const char* name : {"ss_generator_small", "ss_generator_variant"}) {
    auto f = load(name);
    auto o = simu::models::SampleOptions::from(f.gen->config());
    auto x0 = with_prefix(f.io, "in.sample.x0.");
    o.cache_condition = true;
    auto a = f.gen->sample(f.io.at("in.cond"), x0, o);
    o.cache_condition = false;
    auto b = f.gen->sample(f.io.at("in.cond"), x0, o);
    for (const auto& [k, v] : a) EXPECT_TRUE(simu::testing::close(v, b.at(k), 1e-6, std::string(name) + "." + k));
  }
}
