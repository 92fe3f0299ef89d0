// Pose decoding: Gram-Schmidt 6-D rotation, conventions, quaternions, against independent math.
#include <cmath>

#include "common/error.h"
#include "models/pose.h"
#include "test_util.h"

using namespace simu::models;

namespace {
// Normalised 6-D input whose de-normalised value is `raw` (official statistics written out here).
torch::Tensor normalized_6d(std::vector<double> raw) {
  const double mean[6] = {-0.06366084883674913, 0.008438224692279752, 0.00017084786438302483,
                          0.0007126610473540038, -0.0030916726538816417, 0.5166093753457688};
  const double std_[6] = {0.6656971967514863, 0.6787012271867754, 0.30345010594844524,
                          0.4394504420678794, 0.39817973931717104, 0.6176286868761914};
  std::vector<double> v(6);
  for (int i = 0; i < 6; ++i) v[i] = (raw[i] - mean[i]) / std_[i];
  return torch::tensor(v, torch::kFloat64).to(torch::kFloat32);
}
// Rotation matrix of a unit quaternion (w, x, y, z), textbook formula.
torch::Tensor quat_to_matrix(double w, double x, double y, double z) {
  const double n = std::sqrt(w * w + x * x + y * y + z * z);
  w /= n, x /= n, y /= n, z /= n;
  return torch::tensor({1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)},
                       torch::kFloat64)
      .reshape({3, 3})
      .to(torch::kFloat32);
}
// Gram-Schmidt on de-normalised fp32 inputs: de-normalise (2 roundings), two norms and divisions (5
// each), the projection (5), the cross product (3): ~20 fp32 roundings in series, on vectors at 45
// degrees or more (b2's error is the projection's over |a2| sin(angle) <= sqrt 2 of it).
const double kGramSchmidt = simu::testing::gamma(20) * std::sqrt(2.0);
}  // namespace

// Known inputs give the known matrices: identity, and a1=(1,1,0), a2=(0,0,5) -> columns
// b1=(1,1,0)/sqrt2, b2=(0,0,1), b3=b1 x b2=(1,-1,0)/sqrt2.
TEST(Pose, KnownSixDGivesKnownMatrix) {
  auto eye = rotation_6d_normalized_to_matrix(normalized_6d({1, 0, 0, 0, 1, 0}));
  EXPECT_TRUE(simu::testing::close(eye, torch::eye(3), kGramSchmidt, "identity"));
  auto r = rotation_6d_normalized_to_matrix(normalized_6d({1, 1, 0, 0, 0, 5}));
  const double h = 1.0 / std::sqrt(2.0);
  auto want = torch::tensor({h, 0.0, h, h, 0.0, -h, 0.0, 1.0, 0.0}, torch::kFloat64).reshape({3, 3});
  EXPECT_TRUE(simu::testing::close(r, want, kGramSchmidt, "gram-schmidt"));
}

// Random 6-D inputs always give proper rotations (orthonormal, det +1).
TEST(Pose, RandomSixDIsProperRotation) {
  torch::manual_seed(0);
  auto x = torch::randn({64, 6}) * 3;
  auto r = rotation_6d_normalized_to_matrix(x);
  // b2's error is the projection's over |a2| sin(angle between a1 and a2): the smallest sine of these
  // draws (de-normalised in float64) times ~20 fp32 roundings, plus the 3-term product R^T R.
  auto raw = x.to(torch::kFloat64) * rotation_6d_std().to(torch::kFloat64) + rotation_6d_mean().to(torch::kFloat64);
  auto a1 = raw.narrow(1, 0, 3), a2 = raw.narrow(1, 3, 3);
  const double sin_min = (torch::linalg_cross(a1, a2).norm(2, {1}) / (a1.norm(2, {1}) * a2.norm(2, {1}))).min().item<double>();
  const double tol = simu::testing::gamma(20) / sin_min + simu::testing::gamma(3);
  auto rtr = torch::matmul(r.transpose(-1, -2), r);
  EXPECT_TRUE(simu::testing::close(rtr, torch::eye(3).expand({64, 3, 3}), tol, "R^T R"));
  // det = b3 . (b1 x b2) with b3 = b1 x b2: |b3|^2 - 1, twice the orthonormality error (float64 det).
  auto det = torch::linalg_det(r.to(torch::kFloat64));
  EXPECT_LT((det - 1).abs().max().item<double>(), 3 * tol);
}

// Encode -> decode round trip on rotations built from quaternions; quaternion extraction agrees (up to sign).
TEST(Pose, SixDRoundTripAndQuaternion) {
  const std::vector<std::array<double, 4>> qs = {{1, 0, 0, 0}, {0.3, -0.5, 0.7, 0.1}, {0.01, 0.9, 0.2, -0.4},
                                                 {-0.2, 0.1, -0.1, 0.95}, {0, 0, 1, 0}};
  for (const auto& q : qs) {
    auto R = quat_to_matrix(q[0], q[1], q[2], q[3]);
    auto back = rotation_6d_normalized_to_matrix(matrix_to_rotation_6d_normalized(R));
    // Normalise (2 roundings) then Gram-Schmidt on orthonormal columns (sin 1).
    EXPECT_TRUE(simu::testing::close(back, R, kGramSchmidt + simu::testing::gamma(2), "round trip"));
    auto got = matrix_to_quaternion(R);
    const double n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    const double sign = q[0] < 0 ? -1.0 : 1.0;  // standardised to w >= 0
    auto want = torch::tensor({q[0], q[1], q[2], q[3]}, torch::kFloat64) * (sign / n);
    // R rounded to fp32 (1), the diagonal sums and sqrt (4), the off-diagonal differences (1), the
    // division by 2 |q_i| >= 1 of the largest component (1): ~7 fp32 roundings of values <= 2.
    const double tol = 2 * simu::testing::gamma(7);
    if (q[0] == 0) {  // w = 0: either sign is a valid answer
      if ((got.to(torch::kFloat64) + want).abs().max().item<double>() <= tol) want = -want;
    }
    EXPECT_TRUE(simu::testing::close(got, want, tol, "quaternion"));
  }
}

// Conventions: translation / scale follow the official formulas (written out independently here).
TEST(Pose, ConventionsScaleAndTranslation) {
  std::map<std::string, torch::Tensor> lat;
  lat["6drotation_normalized"] = normalized_6d({0, 1, 0, -1, 0, 0}).reshape({1, 1, 6});  // 90 deg about z
  lat["scale"] = torch::tensor({std::log(2.0), std::log(4.0), std::log(3.0)}).reshape({1, 1, 3});
  lat["translation"] = torch::tensor({0.3f, -0.4f, 1.2f}).reshape({1, 1, 3});
  lat["translation_scale"] = torch::tensor({std::log(2.5)}).reshape({1, 1, 1});

  PoseDecodeOptions ssi;
  ssi.scene_scale = 2.0;
  ssi.scene_shift = {0.1, 0.2, 3.0};
  auto p = decode_pose(lat, ssi);
  // The inputs and expected values rounded to fp32 (2 roundings), then exp / mean / scale / shift (<= 5).
  const double kConvention = simu::testing::gamma(7);
  EXPECT_TRUE(simu::testing::close(p.translation, torch::tensor({{0.7f, -0.6f, 5.4f}}), kConvention, "ssi t"));
  EXPECT_TRUE(simu::testing::close(p.scale_per_axis, torch::tensor({{4.f, 8.f, 6.f}}), kConvention, "ssi s axes"));
  EXPECT_TRUE(simu::testing::close(p.scale, torch::tensor({{6.f, 6.f, 6.f}}), kConvention, "ssi s mean"));
  // Official R has columns (0,1,0), (-1,0,0), (0,0,1); the column-vector rotation is its transpose.
  auto R = torch::tensor({{0.f, -1.f, 0.f}, {1.f, 0.f, 0.f}, {0.f, 0.f, 1.f}});
  EXPECT_TRUE(simu::testing::close(p.rotation_official[0], R, kGramSchmidt, "R official"));
  EXPECT_TRUE(simu::testing::close(p.rotation[0], R.t(), kGramSchmidt, "R column"));
  // apply_pose equals the column form rotation @ (s p) + t; by hand: (1,0,0) -> (0,-6,0) + t.
  auto pts = torch::tensor({{1.f, 0.f, 0.f}, {0.f, 2.f, -1.f}});
  auto moved = apply_pose(p, 0, pts);
  auto want = torch::matmul(R.t(), (pts * 6.f).t()).t() + p.translation;
  // The same 3-term products and sums in another order: two paths of 5 roundings.
  EXPECT_TRUE(simu::testing::close(moved, want, simu::testing::two_paths(5), "apply"));
  // By hand: the rotation's and the convention's error on values up to |(0, -6.6, 0)|, absolute.
  const double by_hand = 6.6 * (kGramSchmidt + kConvention);
  EXPECT_NEAR(moved[0][0].item<float>(), 0.7f, by_hand);
  EXPECT_NEAR(moved[0][1].item<float>(), -6.6f, by_hand);
  EXPECT_NEAR(moved[0][2].item<float>(), 5.4f, by_hand);

  PoseDecodeOptions wts = ssi;
  wts.convention = "ScaleShiftInvariantWTranslationScale";
  auto q = decode_pose(lat, wts);
  const double n = std::sqrt(0.09 + 0.16 + 1.44);
  EXPECT_TRUE(simu::testing::close(
      q.translation,
      torch::tensor({{0.3 / n * 2.5 * 2 + 0.1, -0.4 / n * 2.5 * 2 + 0.2, 1.2 / n * 2.5 * 2 + 3.0}}, torch::kFloat64),
      kConvention + simu::testing::gamma(5), "wts t"));  // + the 3-term norm and the division

  PoseDecodeOptions app = ssi;
  app.convention = "ApparentSize";
  auto a = decode_pose(lat, app);
  EXPECT_TRUE(simu::testing::close(a.translation, torch::tensor({{0.3 * 5, -0.4 * 5, 1.2 * 5}}, torch::kFloat64),
                                   kConvention, "apparent t"));
  EXPECT_TRUE(simu::testing::close(a.scale, torch::full({1, 3}, 3.0 * 5), kConvention, "apparent s"));

  PoseDecodeOptions def;
  def.convention = "default";
  auto d = decode_pose(lat, def);
  // The translation is passed through unchanged: bitwise.
  EXPECT_TRUE(torch::equal(d.translation, torch::tensor({{0.3f, -0.4f, 1.2f}})));
  EXPECT_TRUE(simu::testing::close(d.scale, torch::full({1, 3}, 3.0), kConvention, "default s"));

  // A missing latent is named.
  lat.erase("translation_scale");
  try {
    decode_pose(lat, app);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("translation_scale"), std::string::npos);
  }
}
