// Shape-latent targets of Stage-1 pretraining: the frozen encoder's posterior mean laid out as the
// flow model's shape tokens (token (x k + y) k + z = grid cell [x, y, z], what models::shape_tokens_to_grid
// undoes for the decoder), the random linear stand-in, and the checks against the flow model's latent.
#include "common/source_dir.h"
#include "models/ss_decoder.h"
#include "models/ss_encoder.h"
#include "test_util.h"
#include "training/stage1_targets.h"

using namespace simu::training;

namespace {

const std::string kEncoder = simu::source_dir() + "/tests/testdata/models/ss_encoder_small";

simu::models::LatentSpec shape_spec(int64_t channels, int64_t resolution) {
  simu::models::LatentSpec s;
  s.name = "shape";
  s.in_channels = channels;
  s.pos_embedder = "shape";
  s.resolution = resolution;
  return s;
}

}  // namespace

// The fixture encoder (8 channels, 16^3 -> 4^3): targets are its posterior mean, token by token.
TEST(Stage1Targets, EncoderPosteriorMeanAsShapeTokens) {
  TargetsConfig c;
  c.kind = "encoder";
  c.encoder_config = kEncoder + ".json";
  c.encoder_weights = kEncoder + ".safetensors";
  const auto targets = make_shape_targets(c, shape_spec(8, 4), 16, torch::kCPU, "t.yaml");
  torch::manual_seed(3);
  const auto occ = (torch::rand({2, 16, 16, 16}) < 0.3).to(torch::kByte);
  torch::NoGradGuard ng;
  const auto tokens = targets(occ);  // [2, 64, 8]
  ASSERT_EQ(tokens.sizes(), (std::vector<int64_t>{2, 64, 8}));
  EXPECT_FALSE(tokens.requires_grad());
  auto enc = simu::models::load_ss_encoder(c.encoder_config, c.encoder_weights, torch::kCPU);
  const auto mean = enc->posterior(occ.to(torch::kFloat32).unsqueeze(1)).first;  // [2, 8, 4, 4, 4]
  for (int64_t x = 0; x < 4; ++x)
    for (int64_t y = 0; y < 4; ++y)
      for (int64_t z = 0; z < 4; ++z)
        ASSERT_TRUE(torch::equal(tokens.select(1, (x * 4 + y) * 4 + z), mean.select(4, z).select(3, y).select(2, x)))
            << x << " " << y << " " << z;
  // The decoder's reshape undoes it.
  EXPECT_TRUE(torch::equal(simu::models::shape_tokens_to_grid(tokens), mean));
}

// The stand-in: a fixed linear map (same seed, same map; linear in occupancy - 0.5), shaped as the latent.
TEST(Stage1Targets, RandomLinearIsFixedAndLinear) {
  const auto a = random_linear_targets(shape_spec(4, 2), 8, 5, torch::kCPU);
  const auto b = random_linear_targets(shape_spec(4, 2), 8, 5, torch::kCPU);
  torch::manual_seed(4);
  const auto o1 = (torch::rand({1, 8, 8, 8}) < 0.5).to(torch::kByte), o2 = (torch::rand({1, 8, 8, 8}) < 0.5).to(torch::kByte);
  EXPECT_EQ(a(o1).sizes(), (std::vector<int64_t>{1, 8, 4}));
  EXPECT_TRUE(torch::equal(a(o1), b(o1)));
  const auto half = torch::full({1, 8, 8, 8}, 0.5);  // occupancy 0.5 maps to 0
  EXPECT_EQ(a(half).abs().max().item<float>(), 0.0f);
  // f(o1) + f(o2) = f(o1 + o2 - 0.5) for a linear map of o - 0.5 (fp32: sums of 64 products).
  EXPECT_TRUE(simu::testing::close(a(o1) + a(o2), a(o1.to(torch::kFloat32) + o2.to(torch::kFloat32) - 0.5), 1e-5));
}

// An encoder whose latent does not fit the flow model's shape latent or the cache's grid is refused,
// naming the config file and the shapes.
TEST(Stage1Targets, MismatchedEncoderIsRefused) {
  TargetsConfig c;
  c.kind = "encoder";
  c.encoder_config = kEncoder + ".json";
  c.encoder_weights = kEncoder + ".safetensors";
  for (const auto& [spec, R] : {std::pair{shape_spec(8, 8), int64_t{16}}, std::pair{shape_spec(4, 4), int64_t{16}},
                                std::pair{shape_spec(8, 4), int64_t{32}}}) {
    try {
      make_shape_targets(c, spec, R, torch::kCPU, "t.yaml");
      ADD_FAILURE() << "accepted a shape latent [" << spec.in_channels << ", " << spec.resolution << "^3] at R " << R;
    } catch (const simu::Error& e) {
      EXPECT_NE(std::string(e.what()).find("t.yaml: targets.encoder_config"), std::string::npos) << e.what();
    }
  }
}
