// PointPatchEmbed with points nearer than the object (normalised z <= -1), for both remaps the
// SAM 3D configs use: `linear` (the released ss_generator.yaml) and `exp` (pointmap.py's default and
// the small fixture). Expected per-point features are computed here in float64 from the remap
// formulas and the projection weights (independent math), never from the module's own output.
#include <cmath>

#include "models/point_patch_embed.h"
#include "test_util.h"

namespace sm = simu::models;

namespace {

// A small embedder: 16 x 16 input, 4 x 4 windows, 8 channels.
sm::PointPatchEmbed make(const std::string& remap, const std::string& near = "invalid") {
  torch::manual_seed(3);
  sm::PointPatchEmbedConfig c;
  c.input_size = 16;
  c.patch_size = 4;
  c.embed_dim = 8;
  c.num_heads = 2;
  c.remap_output = remap;
  c.exp_near_points = near;
  sm::PointPatchEmbed m(c);
  // Non-trivial projection (the official init uses a tiny gain).
  torch::NoGradGuard ng;
  m->point_proj->weight.normal_();
  m->point_proj->bias.normal_();
  m->eval();
  return m;
}

// Point map [1, 3, 16, 16]: z in [-3, 2] (rows 0..3 are nearer than -1), one NaN point, x and y varied.
torch::Tensor near_pointmap() {
  auto u = torch::arange(16, torch::kFloat32).view({1, 16}).expand({16, 16});
  auto v = torch::arange(16, torch::kFloat32).view({16, 1}).expand({16, 16});
  auto z = -3.0 + v * (5.0 / 15.0) + 0.01 * u;  // row 0: -3, row 3: -2, ... row 6: -1 + 0.06 - ...
  auto pm = torch::stack({0.1 * (u - 8), 0.05 * (v - 8), z}).unsqueeze(0).contiguous();
  pm[0][0][10][5] = NAN;  // a point without depth
  return pm;
}

// Independent per-point features [16, 16, D] in float64: remap by hand, W p + b, invalid token for
// non-finite points and (exp, "invalid") for z <= -1. `bound` gets the fp32 rounding bound of each
// feature (tests/tolerance.h): the remap's error in q (exp: 1 + z loses |z| / |1 + z| of u, then the
// division or log1p one more), weighted by |W|, plus the 3-term product and bias: gamma(4) of
// |W| |q| + |b|.
torch::Tensor expected_features(sm::PointPatchEmbed& m, const torch::Tensor& pm, bool exp_remap, torch::Tensor& bound) {
  const double u = simu::testing::kFp32Unit;
  const auto W = m->point_proj->weight.to(torch::kFloat64);  // [D, 3]
  const auto b = m->point_proj->bias.to(torch::kFloat64);
  const auto tok = m->invalid_xyz_token.to(torch::kFloat64);
  const int64_t D = W.size(0);
  auto out = torch::empty({16, 16, D}, torch::kFloat64);
  bound = torch::zeros({16, 16, D}, torch::kFloat64);
  auto a = pm.to(torch::kFloat64)[0];
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 16; ++x) {
      const double px = a[0][y][x].item<double>(), py = a[1][y][x].item<double>(), pz = a[2][y][x].item<double>();
      if (!std::isfinite(px + py + pz) || (exp_remap && pz <= -1.0)) {
        out[y][x] = tok;
        continue;
      }
      double q[3] = {px, py, pz}, dq[3] = {0, 0, 0};  // remapped point and its absolute fp32 error
      if (exp_remap) {
        q[0] = px / (1 + pz), q[1] = py / (1 + pz), q[2] = std::log1p(pz);
        const double lost = std::abs(pz) / std::abs(1 + pz);
        dq[0] = (lost + 2) * u * std::abs(q[0]), dq[1] = (lost + 2) * u * std::abs(q[1]);
        dq[2] = (lost + std::abs(q[2])) * u;
      }
      const auto qt = torch::tensor({q[0], q[1], q[2]}, torch::kFloat64);
      out[y][x] = torch::mv(W, qt) + b;
      bound[y][x] = torch::mv(W.abs(), torch::tensor({dq[0], dq[1], dq[2]}, torch::kFloat64)) +
                    simu::testing::gamma(4) * (torch::mv(W.abs(), qt.abs()) + b.abs());
    }
  return out;
}

// Every |got - want| within its bound.
::testing::AssertionResult within(const torch::Tensor& got, const torch::Tensor& want, const torch::Tensor& bound) {
  const auto excess = ((got.to(torch::kFloat64) - want).abs() - bound).max().item<double>();
  if (excess <= 0) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << "a feature is off by " << excess << " more than its rounding bound";
}

}  // namespace

// linear (released): near points are ordinary values, nothing is masked.
TEST(PointPatchEmbedNear, LinearRemapKeepsNearPoints) {
  torch::NoGradGuard ng;
  auto m = make("linear");
  const auto pm = near_pointmap();
  ASSERT_GT((pm.select(1, 2) <= -1).sum().item<int64_t>(), 40);
  const auto got = m->embed_points(pm)[0];
  torch::Tensor bound;
  const auto want = expected_features(m, pm, /*exp_remap=*/false, bound);
  EXPECT_TRUE(within(got, want, bound));
  // Only the NaN point took the invalid token.
  const auto tok = m->invalid_xyz_token.view({1, 1, -1});
  EXPECT_EQ((got == tok).all(-1).sum().item<int64_t>(), 1);
  const auto out = m->forward(pm);
  EXPECT_EQ(out.sizes(), torch::IntArrayRef({1, 16, 8}));
  EXPECT_TRUE(torch::isfinite(out).all().item<bool>());
}

// exp: z <= -1 has no image under log1p; such points take the invalid token, every other point is the
// official remap (x/(1+z), y/(1+z), log1p z) projected.
TEST(PointPatchEmbedNear, ExpRemapMarksOutOfDomainPointsInvalid) {
  torch::NoGradGuard ng;
  auto m = make("exp");
  const auto pm = near_pointmap();
  const auto got = m->embed_points(pm)[0];
  torch::Tensor bound;
  const auto want = expected_features(m, pm, /*exp_remap=*/true, bound);
  EXPECT_TRUE(within(got, want, bound));
  const auto out = m->forward(pm);
  EXPECT_TRUE(torch::isfinite(out).all().item<bool>()) << "near points must not poison the tokens";
  // Same tokens as with those points given as invalid (NaN) from the start: the same features
  // through the same operations, bit for bit.
  auto nan_near = pm.clone();
  nan_near.masked_fill_((pm.select(1, 2) <= -1).unsqueeze(1).expand_as(pm), NAN);
  EXPECT_TRUE(torch::equal(m->forward(nan_near), out));
  // Windows with no near point are unchanged by the handling (compare with the "nan" mode, which is
  // the official arithmetic): rows 4.. are in the domain from row 6 on; window rows 2 and 3 (y >= 8).
  auto official = make("exp", "nan");
  const auto off = official->forward(pm);  // [1, 16 windows, D]
  // (Each window is its own batch row of the same operations: bit for bit.)
  for (int w = 8; w < 16; ++w) EXPECT_TRUE(torch::equal(off[0][w], out[0][w])) << "window " << w;
}

// exp with "nan": the official arithmetic; log1p(z < -1) = NaN reaches the window tokens.
TEST(PointPatchEmbedNear, ExpRemapOfficialArithmeticGivesNaN) {
  torch::NoGradGuard ng;
  auto m = make("exp", "nan");
  const auto pm = near_pointmap();
  const auto f = m->embed_points(pm)[0];
  EXPECT_TRUE(torch::isnan(f[0][3]).any().item<bool>());  // z = -3 + 0.03
  EXPECT_FALSE(torch::isnan(f[12][3]).any().item<bool>());
  const auto out = m->forward(pm);
  EXPECT_TRUE(torch::isnan(out[0][0]).any().item<bool>());   // window with near points
  EXPECT_FALSE(torch::isnan(out[0][12]).any().item<bool>());  // window without
}
