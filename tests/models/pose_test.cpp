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
}  // namespace

// Known inputs give the known matrices: identity, and a1=(1,1,0), a2=(0,0,5) -> columns
// b1=(1,1,0)/sqrt2, b2=(0,0,1), b3=b1 x b2=(1,-1,0)/sqrt2.
TEST(Pose, KnownSixDGivesKnownMatrix) {
  auto eye = rotation_6d_normalized_to_matrix(normalized_6d({1, 0, 0, 0, 1, 0}));
  EXPECT_TRUE(simu::testing::close(eye, torch::eye(3), 1e-5, "identity"));
  auto r = rotation_6d_normalized_to_matrix(normalized_6d({1, 1, 0, 0, 0, 5}));
  const double h = 1.0 / std::sqrt(2.0);
  auto want = torch::tensor({h, 0.0, h, h, 0.0, -h, 0.0, 1.0, 0.0}, torch::kFloat64).reshape({3, 3});
  EXPECT_TRUE(simu::testing::close(r, want, 1e-5, "gram-schmidt"));
}

// Random 6-D inputs always give proper rotations (orthonormal, det +1).
TEST(Pose, RandomSixDIsProperRotation) {
  torch::manual_seed(0);
  auto r = rotation_6d_normalized_to_matrix(torch::randn({64, 6}) * 3);
  auto rtr = torch::matmul(r.transpose(-1, -2), r);
  EXPECT_TRUE(simu::testing::close(rtr, torch::eye(3).expand({64, 3, 3}), 1e-5, "R^T R"));
  auto det = torch::linalg_det(r.to(torch::kFloat64));
  EXPECT_LT((det - 1).abs().max().item<double>(), 1e-5);
}

// Encode -> decode round trip on rotations built from quaternions; quaternion extraction agrees (up to sign).
TEST(Pose, SixDRoundTripAndQuaternion) {
  const std::vector<std::array<double, 4>> qs = {{1, 0, 0, 0}, {0.3, -0.5, 0.7, 0.1}, {0.01, 0.9, 0.2, -0.4},
                                                 {-0.2, 0.1, -0.1, 0.95}, {0, 0, 1, 0}};
  for (const auto& q : qs) {
    auto R = quat_to_matrix(q[0], q[1], q[2], q[3]);
    auto back = rotation_6d_normalized_to_matrix(matrix_to_rotation_6d_normalized(R));
    EXPECT_TRUE(simu::testing::close(back, R, 1e-5, "round trip"));
    auto got = matrix_to_quaternion(R);
    const double n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    const double sign = q[0] < 0 ? -1.0 : 1.0;  // standardised to w >= 0
    auto want = torch::tensor({q[0], q[1], q[2], q[3]}, torch::kFloat64) * (sign / n);
    if (q[0] == 0) {  // w = 0: either sign is a valid answer
      if ((got.to(torch::kFloat64) + want).abs().max().item<double>() < 1e-5) want = -want;
    }
    EXPECT_TRUE(simu::testing::close(got, want, 1e-5, "quaternion"));
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
  EXPECT_TRUE(simu::testing::close(p.translation, torch::tensor({{0.7f, -0.6f, 5.4f}}), 1e-5, "ssi t"));
  EXPECT_TRUE(simu::testing::close(p.scale_per_axis, torch::tensor({{4.f, 8.f, 6.f}}), 1e-5, "ssi s axes"));
  EXPECT_TRUE(simu::testing::close(p.scale, torch::tensor({{6.f, 6.f, 6.f}}), 1e-5, "ssi s mean"));
  // Official R has columns (0,1,0), (-1,0,0), (0,0,1); the column-vector rotation is its transpose.
  auto R = torch::tensor({{0.f, -1.f, 0.f}, {1.f, 0.f, 0.f}, {0.f, 0.f, 1.f}});
  EXPECT_TRUE(simu::testing::close(p.rotation_official[0], R, 1e-5, "R official"));
  EXPECT_TRUE(simu::testing::close(p.rotation[0], R.t(), 1e-5, "R column"));
  // apply_pose equals the column form rotation @ (s p) + t; by hand: (1,0,0) -> (0,-6,0) + t.
  auto pts = torch::tensor({{1.f, 0.f, 0.f}, {0.f, 2.f, -1.f}});
  auto moved = apply_pose(p, 0, pts);
  auto want = torch::matmul(R.t(), (pts * 6.f).t()).t() + p.translation;
  EXPECT_TRUE(simu::testing::close(moved, want, 1e-5, "apply"));
  EXPECT_NEAR(moved[0][0].item<float>(), 0.7f, 1e-5);
  EXPECT_NEAR(moved[0][1].item<float>(), -6.6f, 1e-5);
  EXPECT_NEAR(moved[0][2].item<float>(), 5.4f, 1e-5);

  PoseDecodeOptions wts = ssi;
  wts.convention = "ScaleShiftInvariantWTranslationScale";
  auto q = decode_pose(lat, wts);
  const double n = std::sqrt(0.09 + 0.16 + 1.44);
  EXPECT_TRUE(simu::testing::close(
      q.translation,
      torch::tensor({{0.3 / n * 2.5 * 2 + 0.1, -0.4 / n * 2.5 * 2 + 0.2, 1.2 / n * 2.5 * 2 + 3.0}}, torch::kFloat64),
      1e-5, "wts t"));

  PoseDecodeOptions app = ssi;
  app.convention = "ApparentSize";
  auto a = decode_pose(lat, app);
  EXPECT_TRUE(simu::testing::close(a.translation, torch::tensor({{0.3 * 5, -0.4 * 5, 1.2 * 5}}, torch::kFloat64),
                                   1e-5, "apparent t"));
  EXPECT_TRUE(simu::testing::close(a.scale, torch::full({1, 3}, 3.0 * 5), 1e-5, "apparent s"));

  PoseDecodeOptions def;
  def.convention = "default";
  auto d = decode_pose(lat, def);
  EXPECT_TRUE(simu::testing::close(d.translation, torch::tensor({{0.3f, -0.4f, 1.2f}}), 1e-6, "default t"));
  EXPECT_TRUE(simu::testing::close(d.scale, torch::full({1, 3}, 3.0), 1e-5, "default s"));

  // A missing latent is named.
  lat.erase("translation_scale");
  try {
    decode_pose(lat, app);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("translation_scale"), std::string::npos);
  }
}
