// Stage-1 flow model and generator against the official fixtures (ss_generator_small, ss_generator_variant).
#include <ATen/CPUGeneratorImpl.h>
#include <fmt/format.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "common/error.h"
#include "data/safetensors.h"
#include "models/generator.h"
#include "models/weights.h"
#include "flow_rounding.h"
#include "test_util.h"

namespace {

using simu::models::Generator;
using simu::models::Latents;

struct Fixture {
  Generator gen{nullptr};
  std::map<std::string, torch::Tensor> io;
  // Two fp32 evaluations of one backbone forward on the fixture's condition (flow_rounding.h).
  double forward_bound() const {
    return simu::testing::flow_forward_bound(gen->config().backbone, io.at("in.cond").size(1));
  }
  // Two fp32 runs of the sampler with guidance strength s.
  double sample_bound(double s) const {
    return simu::testing::flow_sample_bound(gen->config().backbone, io.at("in.cond").size(1), s);
  }
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

// Compares every latent of got with io[prefix + name] within tol; prints the max relative error.
void expect_close(const Latents& got, const std::map<std::string, torch::Tensor>& io, const std::string& prefix,
                  double tol, const std::string& tag) {
  const auto want = with_prefix(io, prefix);
  ASSERT_EQ(got.size(), want.size()) << tag;
  double worst = 0;
  for (const auto& [k, w] : want) {
    ASSERT_TRUE(got.count(k)) << tag << ": missing " << k;
    EXPECT_TRUE(simu::testing::close(got.at(k), w, tol, tag + "." + k));
    worst = std::max(worst, simu::testing::rel_err(got.at(k), w));
  }
  fmt::print("[{}] max rel err {:.3g}\n", tag, worst);
}

// The fixture's official generator settings: module.generator.backbone of <name>.json.
nlohmann::json official_generator(const std::string& name) {
  std::ifstream in(simu::testing::fixture(name + ".json"));
  return nlohmann::json::parse(in).at("module").at("generator").at("backbone");
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
  // The port and the official code: two fp32 forwards (flow_rounding.h).
  expect_close(forward_fixture(f, true), f.io, "out.forward.", f.forward_bound(), "small.forward");
}

TEST(FlowModel, VariantForwardMatchesOfficial) {
  auto f = load("ss_generator_variant");
  // The port and the official code: two fp32 forwards (flow_rounding.h).
  expect_close(forward_fixture(f, false), f.io, "out.forward.", f.forward_bound(), "variant.forward");
}

TEST(FlowModel, StateDictKeysAreOfficial) {
  auto f = load("ss_generator_small");
  const auto state = simu::models::state_dict(*f.gen);
  const auto& c = f.gen->config().backbone;
  ASSERT_FALSE(c.share_groups.empty()) << "the fixture merges the pose latents into one stream";
  EXPECT_TRUE(state.count("reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape.weight"));
  EXPECT_TRUE(state.count(fmt::format("reverse_fn.backbone.blocks.{}.cross_attn.{}.to_kv.bias", c.num_blocks - 1,
                                      c.share_groups[0].first)));
  EXPECT_TRUE(state.count("reverse_fn.backbone.latent_mapping.shape.pos_emb"));
  // Same key set as the file (after the prefix).
  const auto file = simu::data::SafeTensorsFile::open(simu::testing::fixture("ss_generator_small.safetensors"));
  EXPECT_EQ(state.size(), file.keys().size());
}

TEST(Generator, SmallSampleCfgMatchesOfficial) {
  auto f = load("ss_generator_small");
  auto o = simu::models::SampleOptions::from(f.gen->config());
  // The official run's settings, read from the fixture's JSON itself (README: sample_cfg uses them).
  const auto official = official_generator("ss_generator_small");
  EXPECT_EQ(o.steps, official.at("inference_steps").get<int>());
  EXPECT_EQ(o.shortcut, !official.at("no_shortcut").get<bool>());  // no_shortcut: d = 0
  EXPECT_DOUBLE_EQ(o.cfg_strength, official.at("reverse_fn").at("strength").get<double>());
  auto y = f.gen->sample(f.io.at("in.cond"), with_prefix(f.io, "in.sample.x0."), o);
  // The port's and the official guided sampler: two fp32 runs (flow_rounding.h).
  expect_close(y, f.io, "out.sample_cfg.", f.sample_bound(o.cfg_strength), "small.sample_cfg");
}

TEST(Generator, SmallSampleShortcutMatchesOfficial) {
  auto f = load("ss_generator_small");
  auto o = simu::models::SampleOptions::from(f.gen->config());
  o.shortcut = true;
  o.cfg_strength = 0;
  auto y = f.gen->sample(f.io.at("in.cond"), with_prefix(f.io, "in.sample.x0."), o);
  // Unguided: two fp32 runs of the sampler at strength 0 (flow_rounding.h).
  expect_close(y, f.io, "out.sample_shortcut.", f.sample_bound(0), "small.sample_shortcut");
}

TEST(Generator, VariantSampleCfgMatchesOfficial) {
  auto f = load("ss_generator_variant");
  auto o = simu::models::SampleOptions::from(f.gen->config());
  EXPECT_EQ(o.steps, official_generator("ss_generator_variant").at("inference_steps").get<int>());
  auto y = f.gen->sample(f.io.at("in.cond"), with_prefix(f.io, "in.sample.x0."), o);
  // The port's and the official guided sampler: two fp32 runs (flow_rounding.h).
  expect_close(y, f.io, "out.sample_cfg.", f.sample_bound(o.cfg_strength), "variant.sample_cfg");
}

// CFG batched in one forward equals two separate forwards combined by hand: y = (1+s) y_c - s y_u.
TEST(Generator, BatchedCfgEqualsTwoForwards) {
  auto f = load("ss_generator_variant");
  torch::NoGradGuard ng;
  auto x = with_prefix(f.io, "in.latent.");
  auto cond = f.io.at("in.cond");
  const double s = 3.0, t = 700.0;
  auto guided = f.gen->reverse_fn->forward(x, t, cond, c10::nullopt, s, {300, 1000});
  const int64_t B = cond.size(0);
  auto tt = torch::full({B}, t);
  auto yc = f.gen->backbone()->forward(x, tt, cond);
  auto yu = f.gen->backbone()->forward(x, tt, cond * 0);
  // One batched forward against two of half the batch: the guided bound at strength s (flow_rounding.h).
  const double guided_tol = simu::testing::flow_guided_bound(f.gen->config().backbone, cond.size(1), s);
  for (const auto& [k, v] : guided) EXPECT_TRUE(simu::testing::close(v, (1 + s) * yc.at(k) - s * yu.at(k), guided_tol, k));
  // Outside the interval: the plain conditional velocity (t broadcast from [1] against t per row: two forwards).
  auto plain = f.gen->reverse_fn->forward(x, 100.0, cond, c10::nullopt, s, {300, 1000});
  auto yc100 = f.gen->backbone()->forward(x, torch::full({B}, 100.0), cond);
  for (const auto& [k, v] : plain) EXPECT_TRUE(simu::testing::close(v, yc100.at(k), f.forward_bound(), k));
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
    // The value bias for the zero row against attention over identical keys: two fp32 forwards.
    for (const auto& [k, v] : want) EXPECT_TRUE(simu::testing::close(got.at(k), v, f.forward_bound(), std::string(name) + "." + k));
    // Independent: the uncached forward of the zero row alone.
    Latents xu;
    for (const auto& [k, v] : x1) xu[k] = v.narrow(0, 0, 1);
    auto yu = bb->forward(xu, t, c * 0);
    for (const auto& [k, v] : yu)
      EXPECT_TRUE(simu::testing::close(got.at(k).narrow(0, 1, 1), v, f.forward_bound(), std::string(name) + ".u." + k));
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
      // Changed beyond what rounding could change (two fp32 forwards).
      if (k != "shape") pose_changed = pose_changed || simu::testing::rel_err(v, b.at(k)) > f.forward_bound();
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
    // One attention over G member rows' queries against G attentions of one: two fp32 forwards, and
    // the to_kv gradient summed over the 2B x Lc condition rows (flow_rounding.h).
    for (const auto& [k, v] : repeated)
      EXPECT_TRUE(simu::testing::close(shared.at(k).detach(), v.detach(), f.forward_bound(), std::string(name) + "." + k));
    const double grad_tol = simu::testing::flow_gradient_bound(bb->config(), cond.size(1), 2 * cond.size(0) * cond.size(1));
    EXPECT_TRUE(simu::testing::close(g_shared, g_repeated, grad_tol, std::string(name) + ".to_kv.grad"));
    EXPECT_GT(g_shared.abs().max().item<double>(), 0) << name;
    // The fixture's rows (2b) give the official forward's output.
    Latents fixture_rows;
    for (const auto& [k, v] : shared) fixture_rows[k] = v.detach().slice(0, 0, c10::nullopt, 2);
    expect_close(fixture_rows, f.io, "out.forward.", f.forward_bound(), std::string(name) + ".shared");
    // Rows that are not a multiple of the condition's (2B - 1 of them, for B > 1) are refused.
    const int64_t odd = 2 * cond.size(0) - 1;
    auto x_odd = x;
    for (auto& [k, v] : x_odd) v = v.narrow(0, 0, odd);
    if (cond.size(0) > 1)
      EXPECT_THROW(bb->forward(x_odd, t.narrow(0, 0, odd), cond,
                               with_d ? c10::optional<torch::Tensor>(d->narrow(0, 0, odd)) : d),
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
                 "out.forward.", f.forward_bound(), std::string(name) + ".shape_only");
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
  const auto file_cfg = cfg.backbone;
  cfg.backbone.num_blocks += 1;                         // one block too many -> missing keys
  cfg.backbone.cond_channels = file_cfg.cond_channels + 8;  // wrong to_kv shapes
  Generator g(cfg);
  try {
    simu::models::LoadOptions lo;
    lo.strip_prefix = "_base_models.generator.";
    simu::models::load_safetensors_into(*g, simu::testing::fixture("ss_generator_small.safetensors"), lo);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    const std::string m = e.what();
    EXPECT_NE(m.find("shape mismatches"), std::string::npos) << m;
    const int64_t kv_rows = 2 * file_cfg.model_channels;
    EXPECT_NE(m.find(fmt::format("cross_attn.shape.to_kv.weight: got [{}, {}] expected [{}, {}]", kv_rows,
                                 file_cfg.cond_channels, kv_rows, cfg.backbone.cond_channels)),
              std::string::npos)
        << m;
    EXPECT_NE(m.find("missing keys"), std::string::npos) << m;
    EXPECT_NE(m.find(fmt::format("blocks.{}.", file_cfg.num_blocks)), std::string::npos) << m;
  }
  // An unexpected key (config without the last latent, merged into the pose stream) is reported too.
  auto cfg2 = simu::models::GeneratorConfig::from_official_file(simu::testing::fixture("ss_generator_small.json"));
  const std::string dropped = cfg2.backbone.latents.back().name;
  ASSERT_FALSE(cfg2.backbone.share_groups.empty());
  ASSERT_EQ(cfg2.backbone.share_groups[0].second.back(), dropped) << "the fixture's last latent is merged last";
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
    EXPECT_NE(std::string(e.what()).find("latent_mapping." + dropped + ".pos_emb"), std::string::npos) << e.what();
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
    const auto& shape = f.gen->config().backbone.latent("shape");
    EXPECT_EQ(x0.at("shape").sizes(), (std::vector<int64_t>{2, shape.tokens(), shape.in_channels}));
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
  // logit(t) ~ N(0, 1). Standard errors at n = 20000: 1/sqrt(n) = 0.0071 for the mean, 1/sqrt(2n) =
  // 0.005 for the std; 0.03 is 4.2 and 6 of them (whatever normal kernel draws the samples).
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
  // Values <= 1 from 5 float64 operations (i / n, 1 - s, * 2, + 1, /): gamma(5) in float64, absolute.
  const double tol = simu::testing::gamma(5, simu::testing::kFp64Unit);
  for (size_t i = 0; i < want.size(); ++i) EXPECT_NEAR(grid[i], want[i], tol);
  auto rev = f.gen->time_grid(4, 1.0, true);
  EXPECT_NEAR(rev.front(), 1.0, tol);
  EXPECT_NEAR(rev.back(), 0.0, tol);
}

// The project config layout (configs/stage1_small.yaml) builds the same model as the official JSON.
TEST(FlowModel, ProjectConfigMatchesOfficialLayout) {
  auto gen = simu::models::load_generator(simu::testing::source_dir() + "/configs/stage1_small.yaml",
                                          simu::testing::fixture("ss_generator_small.safetensors"), torch::kCPU);
  Fixture f{gen, simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"))};
  // The port and the official code: two fp32 forwards (flow_rounding.h).
  expect_close(forward_fixture(f, true), f.io, "out.forward.", f.forward_bound(), "small.forward(project yaml)");
  // The sampler settings are the official JSON's.
  auto o = simu::models::SampleOptions::from(gen->config());
  const auto official = official_generator("ss_generator_small");
  EXPECT_EQ(o.steps, official.at("inference_steps").get<int>());
  EXPECT_DOUBLE_EQ(o.cfg_strength, official.at("reverse_fn").at("strength").get<double>());
  EXPECT_EQ(o.shortcut, !official.at("no_shortcut").get<bool>());
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
  // Integer-valued doubles below 2^53 summed in another order: exact, up to the division's rounding
  // and ~20 roundings of partial sums should any exceed 2^53: gamma(20) in float64.
  EXPECT_NEAR(simu::models::flow_forward_flops(c.backbone, 1, 2800) / want, 1.0,
              simu::testing::gamma(20, simu::testing::kFp64Unit));
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
    // Not bit-identical by design: the cached path gives the unconditional half the value bias (a
    // uniform softmax over identical keys, summed, in the other), projects q for the conditional rows
    // only, and batches the products differently. Two fp32 runs of the guided sampler (flow_rounding.h).
    const double tol = f.sample_bound(o.cfg_strength);
    for (const auto& [k, v] : a) EXPECT_TRUE(simu::testing::close(v, b.at(k), tol, std::string(name) + "." + k));
  }
}
