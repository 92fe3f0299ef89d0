// Pose encoding: the inverse of decode_pose. decode(encode(pose)) gives the pose back and
// encode(decode(z)) the latents back for every convention; a hand-computed case; bad inputs.
#include <cmath>

#include "common/error.h"
#include "models/pose.h"
#include "test_util.h"

using namespace simu::models;

namespace {

const std::vector<std::string> kConventions = {"ScaleShiftInvariant", "ScaleShiftInvariantWTranslationScale",
                                               "ApparentSize", "default"};
// The official ROTATION_6D statistics, written out (as pose_test.cpp).
const double kMean[6] = {-0.06366084883674913, 0.008438224692279752, 0.00017084786438302483,
                         0.0007126610473540038, -0.0030916726538816417, 0.5166093753457688};
const double kStd[6] = {0.6656971967514863, 0.6787012271867754, 0.30345010594844524,
                        0.4394504420678794, 0.39817973931717104, 0.6176286868761914};

// Decoded quantities pass through at most ~16 float32 roundings (the latent's own, de-normalisation,
// exp with its argument's rounding amplified by |arg| <= 5, Gram-Schmidt, the scene scale and shift),
// each <= 2^-24 relative to magnitudes <= 2x the tensor's largest entry: 32 x 2^-24 ~ 1.9e-6.
constexpr double kPoseTol = 32.0 / (1 << 24);
// Latents from a decoded pose: the decode's <= 32 roundings on the rotation columns (entries <= 1) are
// divided by the 6-D std (>= 0.30: x3.3), plus the latent's own rounding on |z| <= 5: ~111 x 2^-24
// ~ 6.6e-6 absolute; the other latents stay below ~12 roundings (a shift of 1.3 subtracted back from
// translations >= 0.12 away from it). Bound: 1e-5.
constexpr double kLatentTol = 1e-5;

PoseDecodeOptions options(const std::string& convention) {
  PoseDecodeOptions o;
  o.convention = convention;
  o.scene_scale = 0.7;
  o.scene_shift = {0.1, -0.2, 1.3};
  return o;
}

// Random proper rotations [B, 3, 3] from normalised Gaussian quaternions (textbook formula, float64).
torch::Tensor random_rotations(int64_t B, torch::Generator& g) {
  auto q = torch::randn({B, 4}, g, torch::kFloat64);
  q = q / q.norm(2, -1, true);
  const auto w = q.select(1, 0), x = q.select(1, 1), y = q.select(1, 2), z = q.select(1, 3);
  return torch::stack({1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                       2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                       2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}, 1)
      .reshape({B, 3, 3});
}

double max_abs_diff(const torch::Tensor& a, const torch::Tensor& b) {
  return (a.to(torch::kFloat64) - b.to(torch::kFloat64)).abs().max().item<double>();
}

}  // namespace

// Objects of 2-60 cm, 1-4 m in front of the camera, any rotation: decode(encode(p)) == p.
TEST(PoseEncoding, DecodeOfEncodeGivesThePoseBack) {
  const int64_t B = 64;
  auto g = at::detail::createCPUGenerator(41);
  InstancePose p;
  p.rotation = random_rotations(B, g);
  p.translation = torch::cat({torch::rand({B, 2}, g, torch::kFloat64) * 2 - 1, 1 + 3 * torch::rand({B, 1}, g, torch::kFloat64)}, 1);
  p.scale = torch::exp(std::log(0.02) + std::log(30.0) * torch::rand({B, 3}, g, torch::kFloat64));  // [0.02, 0.6]
  for (const auto& conv : kConventions) {
    const auto o = options(conv);
    const auto z = encode_pose(p, o);
    ASSERT_EQ(z.at("6drotation_normalized").sizes(), (std::vector<int64_t>{B, 6})) << conv;
    ASSERT_EQ(z.at("translation_scale").sizes(), (std::vector<int64_t>{B, 1})) << conv;
    const auto d = decode_pose(z, o);
    EXPECT_TRUE(simu::testing::close(d.rotation, p.rotation, kPoseTol, conv + " rotation"));
    EXPECT_TRUE(simu::testing::close(d.translation, p.translation, kPoseTol, conv + " translation"));
    EXPECT_TRUE(simu::testing::close(d.scale_per_axis, p.scale, kPoseTol, conv + " scale"));
    // Per object too: the smallest scale (2 cm against a 60 cm maximum) keeps its relative accuracy.
    const double worst = ((d.scale_per_axis.to(torch::kFloat64) - p.scale) / p.scale).abs().max().item<double>();
    EXPECT_LT(worst, kPoseTol) << conv;
  }
  // An isotropic scale [B, 1] encodes as the same scale on the three axes.
  InstancePose iso = p;
  iso.scale = p.scale.narrow(1, 0, 1);
  const auto zi = encode_pose(iso, options("ScaleShiftInvariant"));
  EXPECT_TRUE(torch::equal(zi.at("scale").select(1, 0), zi.at("scale").select(1, 2)));
}

// Latents in the decoder's valid range (6-D = two orthonormal columns standardised; a unit translation
// where the convention carries its length in translation_scale; translation_scale 0 where the
// convention ignores it): encode(decode(z)) == z.
TEST(PoseEncoding, EncodeOfDecodeGivesTheLatentsBack) {
  const int64_t B = 64;
  auto g = at::detail::createCPUGenerator(42);
  // Orthonormal column pairs by Gram-Schmidt in float64, standardised with the written-out statistics.
  auto a = torch::randn({B, 3}, g, torch::kFloat64), c = torch::randn({B, 3}, g, torch::kFloat64);
  const auto c1 = a / a.norm(2, -1, true);
  auto c2 = c - (c * c1).sum(-1, true) * c1;
  c2 = c2 / c2.norm(2, -1, true);
  const auto mean = torch::tensor(std::vector<double>(kMean, kMean + 6), torch::kFloat64);
  const auto stdv = torch::tensor(std::vector<double>(kStd, kStd + 6), torch::kFloat64);
  const auto rot = ((torch::cat({c1, c2}, 1) - mean) / stdv).to(torch::kFloat32);
  for (const auto& conv : kConventions) {
    const bool unit = conv == "ScaleShiftInvariantWTranslationScale" || conv == "ApparentSize";
    auto t = torch::randn({B, 3}, g, torch::kFloat64);
    if (unit) t = t / t.norm(2, -1, true);
    std::map<std::string, torch::Tensor> z = {
        {"6drotation_normalized", rot},
        {"scale", (torch::randn({B, 3}, g, torch::kFloat64) - 1).to(torch::kFloat32)},
        {"translation", t.to(torch::kFloat32)},
        {"translation_scale", unit ? (0.5 * torch::randn({B, 1}, g, torch::kFloat64)).to(torch::kFloat32)
                                   : torch::zeros({B, 1})}};
    const auto o = options(conv);
    const auto d = decode_pose(z, o);
    const auto back = encode_pose({d.rotation, d.translation, d.scale_per_axis}, o);
    for (const auto& [name, want] : z) EXPECT_LE(max_abs_diff(back.at(name), want), kLatentTol) << conv << " " << name;
  }
}

// A case by hand: identity rotation, 2 m ahead, scale (0.1, 0.2, 0.3), scene scale 2 and shift (0, 0, 1):
// d = (t - shift) / 2 = (0, 0, 0.5).
TEST(PoseEncoding, HandComputedCase) {
  InstancePose p{torch::eye(3).unsqueeze(0), torch::tensor({{0.0f, 0.0f, 2.0f}}), torch::tensor({{0.1f, 0.2f, 0.3f}})};
  PoseDecodeOptions o;
  o.scene_scale = 2;
  o.scene_shift = {0, 0, 1};
  std::vector<double> rot6d(6);
  const double raw[6] = {1, 0, 0, 0, 1, 0};  // the first two columns of the identity
  for (int i = 0; i < 6; ++i) rot6d[i] = (raw[i] - kMean[i]) / kStd[i];
  const auto log_s = [](double a, double b, double c) { return torch::tensor({{std::log(a), std::log(b), std::log(c)}}); };
  struct Want {
    std::string conv;
    torch::Tensor scale, translation, translation_scale;
  };
  const std::vector<Want> cases = {
      {"ScaleShiftInvariant", log_s(0.05, 0.1, 0.15), torch::tensor({{0.0, 0.0, 0.5}}), torch::zeros({1, 1})},
      {"ScaleShiftInvariantWTranslationScale", log_s(0.05, 0.1, 0.15), torch::tensor({{0.0, 0.0, 1.0}}),
       torch::full({1, 1}, std::log(0.5))},
      // t_rel = t / 2 = (0, 0, 1), |t_rel| = 1: s_tilde = s / 2.
      {"ApparentSize", log_s(0.05, 0.1, 0.15), torch::tensor({{0.0, 0.0, 1.0}}), torch::zeros({1, 1})},
      {"default", log_s(0.1, 0.2, 0.3), torch::tensor({{0.0, 0.0, 2.0}}), torch::zeros({1, 1})}};
  for (const auto& w : cases) {
    o.convention = w.conv;
    const auto z = encode_pose(p, o);
    // One float32 rounding of each latent (magnitudes <= 3.3): 2 x 2^-24 x 3.3 < 4e-7.
    EXPECT_LE(max_abs_diff(z.at("6drotation_normalized"), torch::tensor(rot6d).unsqueeze(0)), 4e-7) << w.conv;
    EXPECT_LE(max_abs_diff(z.at("scale"), w.scale), 4e-7) << w.conv;
    EXPECT_LE(max_abs_diff(z.at("translation"), w.translation), 4e-7) << w.conv;
    EXPECT_LE(max_abs_diff(z.at("translation_scale"), w.translation_scale), 4e-7) << w.conv;
  }
}

// Inputs no decoding can give back are errors naming the batch entry; unknown conventions too.
TEST(PoseEncoding, RejectsWhatTheDecoderCannotGive) {
  const auto eye = torch::eye(3).unsqueeze(0).repeat({2, 1, 1});
  const auto t = torch::tensor({{0.0f, 0.0f, 2.0f}, {0.0f, 0.0f, 2.0f}});
  const auto s = torch::full({2, 3}, 0.1f);
  auto reflected = eye.clone();
  reflected[1][0][0] = -1;  // det -1
  auto stretched = eye.clone();
  stretched[1] *= 1.01;  // not orthonormal
  auto bad_scale = s.clone();
  bad_scale[1][2] = 0;
  for (const auto& [pose, what] : std::vector<std::pair<InstancePose, std::string>>{
           {{reflected, t, s}, "rotation 1"}, {{stretched, t, s}, "rotation 1"}, {{eye, t, bad_scale}, "scale 1"}}) {
    const auto msg = simu::testing::error_of([&] { encode_pose(pose, {}); });
    EXPECT_NE(msg.find(what), std::string::npos) << msg;
  }
  PoseDecodeOptions o;
  o.convention = "DisparitySpace";
  EXPECT_NE(simu::testing::error_of([&] { encode_pose({eye, t, s}, o); }).find("DisparitySpace"), std::string::npos);
  EXPECT_THROW(encode_pose({eye, t.narrow(0, 0, 1), s}, {}), simu::Error);
}
