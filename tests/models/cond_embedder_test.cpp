// Condition embedder (DINOv2 + PointPatchEmbed + EmbedderFuser) against the official fixtures
// (cond_embedder_small*, made by the official Python modules) and against independent math.
#include <array>
#include <cmath>
#include <fstream>

#include <fmt/format.h>

#include "common/error.h"
#include "data/safetensors.h"
#include "models/cond_embedder.h"
#include "models/weights.h"
#include "flow_rounding.h"
#include "test_util.h"

#include <nlohmann/json.hpp>

namespace sm = simu::models;
using simu::testing::close;
using simu::testing::fixture;

namespace {

std::map<std::string, torch::Tensor> io() { return simu::data::load_safetensors(fixture("cond_embedder_small_io.safetensors")); }

std::map<std::string, torch::Tensor> fused_inputs(const std::map<std::string, torch::Tensor>& t) {
  std::map<std::string, torch::Tensor> in;
  for (const auto& [k, v] : t)
    if (k.rfind("in.", 0) == 0) in[k.substr(3)] = v;
  return in;
}

nlohmann::json fixture_json() {
  std::ifstream in(fixture("cond_embedder_small.json"));
  return nlohmann::json::parse(in);
}

// Two fp32 evaluations of the small embedder, from the fixture's own config (flow_rounding.h).
double embedder_bound() {
  return simu::testing::two_paths(simu::testing::embedder_chain(sm::CondEmbedderConfig::load(fixture("cond_embedder_small.json"))));
}

// Tokens of each fused kwarg in order (from the fixture's per-embedder outputs): image, rgb_image,
// mask, rgb_image_mask, pointmap, rgb_pointmap.
std::vector<int64_t> kwarg_tokens(const std::map<std::string, torch::Tensor>& t) {
  const int64_t image = t.at("out.dino_image").size(1), mask = t.at("out.dino_mask").size(1);
  const int64_t point = t.at("out.pointpatch").size(1);
  return {image, image, mask, mask, point, point};
}

// close() within embedder_bound(), plus the figure on stdout (for the record).
::testing::AssertionResult parity(const torch::Tensor& got, const torch::Tensor& want, const std::string& name) {
  if (got.sizes() == want.sizes())
    std::printf("  %s: max rel err %.3g\n", name.c_str(), simu::testing::rel_err(got, want));
  return close(got, want, embedder_bound(), name);
}

sm::CondEmbedder small() {
  return sm::load_cond_embedder(fixture("cond_embedder_small.json"), fixture("cond_embedder_small.safetensors"), "");
}

// One input of the small embedder (index: 0 image, 1 mask, 2 point map; in_key of the fixture) against
// the fixture's output out_key.
::testing::AssertionResult embeds_as_fixture(const std::map<std::string, torch::Tensor>& t, int index,
                                             const std::string& in_key, const std::string& out_key) {
  torch::NoGradGuard ng;
  return parity(small()->embed(index, t.at(in_key)), t.at(out_key), out_key);
}

}  // namespace

// Dino on a 518 input (native grid: stored position embedding).
TEST(CondEmbedder, DinoImageMatchesFixture) {
  EXPECT_TRUE(embeds_as_fixture(io(), 0, "in.image", "out.dino_image"));
}

// Dino at input_size 70 (5x5 patches): bicubic position-embedding interpolation with offset 0.1.
TEST(CondEmbedder, DinoMaskMatchesFixtureWithPosEmbedInterpolation) {
  auto t = io();
  ASSERT_EQ(t.at("in.mask").size(1), 1);  // 1 channel -> repeated to 3
  EXPECT_TRUE(embeds_as_fixture(t, 1, "in.mask", "out.dino_mask"));
}

// PointPatchEmbed with NaN (invalid) points.
TEST(CondEmbedder, PointPatchMatchesFixtureWithNaN) {
  auto t = io();
  ASSERT_TRUE(torch::isnan(t.at("in.pointmap")).any().item<bool>()) << "fixture should contain invalid points";
  EXPECT_TRUE(embeds_as_fixture(t, 2, "in.pointmap", "out.pointpatch"));
}

// The whole fuser: 6 inputs, projections, idx_emb, concatenation order.
TEST(CondEmbedder, FusedMatchesFixture) {
  torch::NoGradGuard ng;
  auto m = small();
  auto t = io();
  EXPECT_EQ(m->num_tokens(), t.at("out.fused").size(1));
  EXPECT_EQ(m->embed_dims(), t.at("out.fused").size(2));
  // Reference path (one input at a time, as upstream) and the batched-Dino fast path.
  m->batch_dino_inputs = false;
  auto ref = m->forward(fused_inputs(t));
  EXPECT_TRUE(parity(ref, t.at("out.fused"), "out.fused (one input at a time)"));
  m->batch_dino_inputs = true;
  auto fast = m->forward(fused_inputs(t));
  EXPECT_TRUE(parity(fast, t.at("out.fused"), "out.fused (batched Dino inputs)"));
  EXPECT_TRUE(close(fast, ref, embedder_bound(), "batched vs one at a time"));  // two fp32 evaluations
}

// The same model written in the official Hydra layout (ss_generator.yaml: module.condition_embedder.
// backbone) with the weights under the official checkpoint prefix next to generator keys.
TEST(CondEmbedder, OfficialLayoutAndPrefixLoadTheSameModel) {
  torch::NoGradGuard ng;
  const auto dir = simu::testing::temp_dir("cond_embedder_official");
  const auto yaml = dir + "/ss_generator.yaml";
  std::ofstream(yaml) << R"(module:
  generator: {backbone: {_target_: something.Else}}
  condition_embedder:
    backbone:
      _target_: sam3d_objects.model.backbone.dit.embedder.embedder_fuser.EmbedderFuser
      embedder_list:
        - - _target_: sam3d_objects.model.backbone.dit.embedder.dino.Dino
            dino_model: dinov2_vitl14_reg
            input_size: 518
            backbone_kwargs: {embed_dim: 64, depth: 2, num_heads: 4, interpolate_antialias: false, interpolate_offset: 0.1, pretrained: false}
          - [[image, cropped], [rgb_image, full]]
        - - _target_: sam3d_objects.model.backbone.dit.embedder.dino.Dino
            dino_model: dinov2_vitl14_reg
            input_size: 70
            freeze_backbone: true
            backbone_kwargs: {embed_dim: 64, depth: 2, num_heads: 4, interpolate_antialias: false, interpolate_offset: 0.1}
          - [[mask, cropped], [rgb_image_mask, full]]
        - - _target_: sam3d_objects.model.backbone.dit.embedder.pointmap.PointPatchEmbed
            input_size: 32
            patch_size: 8
            embed_dim: 48
            remap_output: exp
          - [[pointmap, cropped], [rgb_pointmap, full]]
      use_pos_embedding: learned
      projection_pre_norm: true
      projection_net_hidden_dim_multiplier: 4.0
      force_drop_modalities: null
)";
  // Checkpoint: embedder keys under the official prefix plus a generator key that must be skipped.
  std::map<std::string, torch::Tensor> ckpt;
  for (const auto& [k, v] : simu::data::load_safetensors(fixture("cond_embedder_small.safetensors")))
    ckpt[std::string(sm::kOfficialCondEmbedderPrefix) + k] = v;
  ckpt["_base_models.generator.reverse_fn.backbone.some.weight"] = torch::zeros({2});
  const auto weights = dir + "/ss_generator.safetensors";
  simu::data::save_safetensors(weights, ckpt, {});

  auto m = sm::load_cond_embedder(yaml, weights, "auto");
  auto t = io();
  EXPECT_TRUE(parity(m->forward(fused_inputs(t)), t.at("out.fused"), "out.fused (official layout)"));
  auto m2 = sm::load_cond_embedder(yaml, weights, sm::kOfficialCondEmbedderPrefix);
  EXPECT_TRUE(parity(m2->forward(fused_inputs(t)), t.at("out.fused"), "out.fused (explicit prefix)"));
}

// Strict loading: a missing and an unexpected key are both reported, in one error.
TEST(CondEmbedder, StrictLoadingReportsEveryMismatch) {
  auto cfg = sm::CondEmbedderConfig::load(fixture("cond_embedder_small.json"));
  sm::CondEmbedder m(cfg);
  auto state = simu::data::load_safetensors(fixture("cond_embedder_small.safetensors"));
  state.erase("module_list.0.backbone.register_tokens");
  state["module_list.2.blocks.0.attn.qkv.weight"] = torch::zeros({3, 3});
  state["module_list.9.extra"] = torch::zeros({1});
  sm::LoadOptions o;
  o.source = "test";
  try {
    sm::load_state_strict(*m, state, o);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    const std::string msg = e.what();
    EXPECT_NE(msg.find("module_list.0.backbone.register_tokens"), std::string::npos) << msg;
    EXPECT_NE(msg.find("module_list.9.extra"), std::string::npos) << msg;
    const int64_t dim = fixture_json().at("pointpatch").at("embed_dim").get<int64_t>();
    EXPECT_NE(msg.find(fmt::format("module_list.2.blocks.0.attn.qkv.weight: got [3, 3] expected [{}, {}]", 3 * dim, dim)),
              std::string::npos)
        << msg;
  }
}

// Forced modality drop: the point-map tokens become 0, everything else is unchanged.
TEST(CondEmbedder, ForceDropZeroesOnlyThoseModalities) {
  torch::NoGradGuard ng;
  auto cfg = sm::CondEmbedderConfig::load(fixture("cond_embedder_small.json"));
  cfg.force_drop_modalities = {"pointmap", "rgb_pointmap"};
  sm::CondEmbedder m(cfg);
  sm::LoadOptions o;
  sm::load_safetensors_into(*m, fixture("cond_embedder_small.safetensors"), o);
  m->eval();
  auto t = io();
  auto got = m->forward(fused_inputs(t));
  auto want = t.at("out.fused");
  // Token layout: image, rgb_image, mask, rgb_image_mask, then pointmap, rgb_pointmap (dropped).
  const auto n = kwarg_tokens(t);
  const int64_t kept = n[0] + n[1] + n[2] + n[3];
  EXPECT_TRUE(parity(got.slice(1, 0, kept), want.slice(1, 0, kept), "kept tokens"));
  EXPECT_EQ(got.slice(1, kept).abs().max().item<double>(), 0.0);
}

// A missing input names what was given and what is expected.
TEST(CondEmbedder, MissingInputIsAnError) {
  auto m = small();
  auto in = fused_inputs(io());
  in.erase("rgb_pointmap");
  try {
    torch::NoGradGuard ng;
    m->forward(in);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("'rgb_pointmap'"), std::string::npos) << e.what();
  }
}

// llama3 FeedForward hidden size: int(2h/3), optional multiplier, rounded up to multiple_of.
TEST(CondEmbedder, FeedForwardHiddenRounding) {
  EXPECT_EQ(sm::FeedForwardImpl::hidden_size(256), 256);          // 170 -> 256
  EXPECT_EQ(sm::FeedForwardImpl::hidden_size(4096), 2816);        // 2730 -> 2816
  EXPECT_EQ(sm::FeedForwardImpl::hidden_size(4096, 256, 1.3), 3584);  // int(1.3*2730)=3549 -> 3584
  EXPECT_EQ(sm::FeedForwardImpl::hidden_size(300, 64), 256);      // 200 -> 256
  // Forward = w2(silu(w1 x) * w3 x), checked against the formula.
  sm::FeedForward ff(8, 12, 5, 4);
  auto x = torch::randn({3, 8});
  auto s = torch::matmul(x, ff->w1->weight.t());
  auto want = torch::matmul(s / (1 + torch::exp(-s)) * torch::matmul(x, ff->w3->weight.t()), ff->w2->weight.t());
  // Two fp32 evaluations of an 8-term product, silu (3 roundings), a 12-term product.
  EXPECT_TRUE(close(ff->forward(x), want, simu::testing::two_paths(8 + 3 + 12), "feed forward"));
  EXPECT_EQ(ff->w1->weight.size(0), 8);  // int(24/3)=8 -> multiple of 4
}

// Every remap type against its closed form, and inverse(forward(p)) == p.
TEST(CondEmbedder, PointRemapperAllTypes) {
  auto p = torch::tensor({{0.3, -1.2, 0.7}, {2.0, 0.5, 3.0}}, torch::kFloat64);
  const double x0 = 0.3, y0 = -1.2, z0 = 0.7;
  struct Case {
    std::string type;
    std::array<double, 3> want;
  };
  const std::vector<Case> cases = {
      {"linear", {x0, y0, z0}},
      {"sinh", {std::asinh(x0), std::asinh(y0), std::asinh(z0)}},
      {"exp", {x0 / (1 + z0), y0 / (1 + z0), std::log1p(z0)}},
      {"exp_disparity", {x0 / z0, y0 / z0, std::log(z0)}},
      {"sinh_exp", {std::asinh(x0), std::asinh(y0), std::log(z0)}},
  };
  for (const auto& c : cases) {
    sm::PointRemapper r(c.type);
    auto out = r.forward(p);
    // float64, at most 3 operations (1 + z, log1p, a division) on values <= 3: 4 roundings, absolute.
    const double tol = 3 * simu::testing::gamma(4, simu::testing::kFp64Unit);
    for (int i = 0; i < 3; ++i) EXPECT_NEAR(out[0][i].item<double>(), c.want[i], tol) << c.type << " " << i;
    // Forward and inverse (sinh of asinh, exp of log: relative condition ~1 at these points): 8 roundings.
    EXPECT_TRUE(close(r.inverse(out), p, simu::testing::gamma(8, simu::testing::kFp64Unit), c.type + " inverse"));
  }
  EXPECT_THROW(sm::PointRemapper("cubic"), simu::Error);
}

// dinov2 hub entry points.
TEST(CondEmbedder, HubModelNames) {
  auto l = sm::DinoVitConfig::hub_model("dinov2_vitl14_reg");
  EXPECT_EQ(l.embed_dim, 1024);
  EXPECT_EQ(l.depth, 24);
  EXPECT_EQ(l.num_heads, 16);
  EXPECT_EQ(l.num_register_tokens, 4);
  EXPECT_TRUE(l.interpolate_antialias);
  EXPECT_EQ(l.interpolate_offset, 0.0);
  auto b = sm::DinoVitConfig::hub_model("dinov2_vitb14");
  EXPECT_EQ(b.num_register_tokens, 0);
  EXPECT_EQ(b.interpolate_offset, 0.1);
  EXPECT_THROW(sm::DinoVitConfig::hub_model("dinov2_vitg14"), simu::Error);
  EXPECT_THROW(sm::DinoVitConfig::hub_model("resnet50"), simu::Error);
}

// The shipped real-size config reads as the Stage-1 embedder: 7528 tokens x 1024 channels.
TEST(CondEmbedder, RealConfigFile) {
  auto c = sm::CondEmbedderConfig::load(simu::testing::source_dir() + "/configs/cond_embedder_sam3d_stage1.yaml");
  auto ref = sm::CondEmbedderConfig::sam3d_stage1();
  ASSERT_EQ(c.embedders.size(), 3u);
  for (size_t i = 0; i < 3; ++i) {
    EXPECT_EQ(c.embedders[i].kind, ref.embedders[i].kind);
    EXPECT_EQ(c.embedders[i].inputs, ref.embedders[i].inputs);
  }
  EXPECT_EQ(c.embedders[0].dino.vit.embed_dim, 1024);
  EXPECT_EQ(c.embedders[1].dino.vit.num_register_tokens, 4);
  EXPECT_EQ(c.embedders[2].point.embed_dim, 512);
  EXPECT_EQ(c.embedders[2].point.remap_output, "linear");
  EXPECT_EQ(c.num_tokens(), 4 * (1 + 37 * 37) + 2 * 32 * 32);
  EXPECT_EQ(ref.num_tokens(), 7528);
  EXPECT_EQ(c.embed_dims(), 1024);
}

// Typos in a config are errors naming the key.
TEST(CondEmbedder, UnknownConfigKeyIsAnError) {
  const auto dir = simu::testing::temp_dir("cond_embedder_typo");
  const auto yaml = dir + "/c.yaml";
  std::ofstream(yaml) << R"(embedder_list:
  - - {_target_: x.pointmap.PointPatchEmbed, input_size: 32, patch_size: 8, embed_dim: 48, remap_outptu: exp}
    - [[pointmap, cropped]]
)";
  try {
    sm::CondEmbedderConfig::load(yaml);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("remap_outptu"), std::string::npos) << e.what();
  }
}

// prenorm_features: plain layer norm (eps 1e-5, no affine) of the whole pre-norm sequence, registers
// included. Applying the final norm's affine to its cls + patch rows gives the fixture's normed output
// up to the eps difference (1e-5 here vs 1e-6 in the ViT's norm), bounded from the features' variance.
TEST(CondEmbedder, DinoPrenormFeatures) {
  torch::NoGradGuard ng;
  auto cfg = sm::CondEmbedderConfig::load(fixture("cond_embedder_small.json"));
  auto dcfg = cfg.embedders[0].dino;
  dcfg.prenorm_features = true;
  sm::Dino dino(dcfg);
  std::map<std::string, torch::Tensor> sub;
  for (const auto& [k, v] : simu::data::load_safetensors(fixture("cond_embedder_small.safetensors")))
    if (k.rfind("module_list.0.", 0) == 0) sub[k.substr(14)] = v;
  sm::LoadOptions o;
  sm::load_state_strict(*dino, sub, o);
  auto t = io();
  auto out = dino->forward(t.at("in.image"));
  // [cls, registers, patches]: the fixture's normed output has cls + patches.
  const auto& want = t.at("out.dino_image");
  const int64_t R = dcfg.vit.num_register_tokens;
  ASSERT_EQ(out.sizes(), torch::IntArrayRef({want.size(0), want.size(1) + R, want.size(2)}));
  EXPECT_EQ(dino->num_tokens(), want.size(1) + R);
  auto w = dino->backbone->norm->weight, b = dino->backbone->norm->bias;
  auto cls_patch = torch::cat({out.slice(1, 0, 1), out.slice(1, 1 + R)}, 1) * w + b;
  // The eps difference scales a normalised value by sqrt((v + 1e-6) / (v + 1e-5)) ~ 1 - 4.5e-6 / v
  // for a token of variance v (the smallest of the pre-norm features), on |x_hat w| up to its largest;
  // plus two fp32 evaluations of the embedder.
  const auto pre = dino->backbone->forward_features(dino->preprocess_input(t.at("in.image"))).x_prenorm;
  const double v_min = (pre - pre.mean(-1, true)).pow(2).mean(-1).min().item<double>();  // per-token variance
  const double eps_change = 1 - std::sqrt((v_min + 1e-6) / (v_min + 1e-5));
  const double scale = (cls_patch - b).abs().max().item<double>() / want.abs().max().item<double>();
  EXPECT_TRUE(close(cls_patch, want, embedder_bound() + eps_change * scale, "prenorm features + affine"));
}

// Training-time modality dropout: with dropout_prob 1 and a single configuration, the listed kwargs
// are zeroed for every sample; in eval mode nothing is dropped.
TEST(CondEmbedder, TrainingModalityDropout) {
  torch::NoGradGuard ng;
  auto cfg = sm::CondEmbedderConfig::load(fixture("cond_embedder_small.json"));
  cfg.dropout_prob = 1.0;
  cfg.drop_modalities_weight = {{{"mask", "rgb_image_mask"}, 1.0}};
  sm::CondEmbedder m(cfg);
  sm::load_safetensors_into(*m, fixture("cond_embedder_small.safetensors"), {});
  auto t = io();
  m->eval();
  EXPECT_TRUE(parity(m->forward(fused_inputs(t)), t.at("out.fused"), "eval: no dropout"));
  m->train();
  auto got = m->forward(fused_inputs(t));
  // image + rgb_image tokens, then mask + rgb_image_mask (dropped).
  const auto n = kwarg_tokens(t);
  const int64_t images = n[0] + n[1], masks = n[2] + n[3];
  EXPECT_EQ(got.slice(1, images, images + masks).abs().max().item<double>(), 0.0);
  EXPECT_TRUE(parity(got.slice(1, 0, images), t.at("out.fused").slice(1, 0, images), "kept"));
}
