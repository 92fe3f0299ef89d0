// Sparse-structure decoder: parity with the official module (fixture), token->grid order, occupancy.
#include <fstream>
#include <map>
#include <set>
#include <tuple>

#include "common/error.h"
#include "data/safetensors.h"
#include "models/ss_decoder.h"
#include "models/weights.h"
#include "flow_rounding.h"
#include "test_util.h"

using namespace simu::models;

namespace {
SparseStructureDecoder small_decoder() {
  return load_ss_decoder(simu::testing::fixture("ss_decoder_small.json"),
                         simu::testing::fixture("ss_decoder_small.safetensors"));
}

}  // namespace

// io.in -> io.out matches the official decoder in float32.
TEST(SSDecoder, MatchesOfficialFixture) {
  auto dec = small_decoder();
  auto file = simu::data::SafeTensorsFile::open(simu::testing::fixture("ss_decoder_small.safetensors"));
  auto in = file.get("io.in").clone(), want = file.get("io.out").clone();
  torch::NoGradGuard ng;
  auto got = dec->forward(in);
  // The port and the official module: two fp32 evaluations of the decoder's chain.
  const double tol = simu::testing::two_paths(simu::testing::decoder_chain(dec->config()));
  EXPECT_TRUE(simu::testing::close(got, want, tol, "io.out"));
  std::printf("ss_decoder_small io.out rel err %.3g\n", simu::testing::rel_err(got, want));
}

// The module tree names match the fixture exactly (strict load would throw otherwise) and a wrong
// config is reported with the offending keys.
// No weights file ("") keeps the random init: the same parameters as the module built from the config
// under the same seed, and different from the fixture's loaded weights.
TEST(SSDecoder, EmptyWeightsPathKeepsTheRandomInit) {
  const auto cfg = simu::testing::fixture("ss_decoder_small.json");
  torch::manual_seed(11);
  auto random = load_ss_decoder(cfg, "");
  torch::manual_seed(11);
  SparseStructureDecoder built(SSDecoderConfig::load(cfg));
  auto loaded = small_decoder();
  const auto a = random->named_parameters(), b = built->named_parameters(), c = loaded->named_parameters();
  ASSERT_EQ(a.size(), b.size());
  bool differs_from_fixture = false;
  for (const auto& item : a) {
    EXPECT_TRUE(torch::equal(item.value(), b[item.key()])) << item.key();
    differs_from_fixture = differs_from_fixture || !torch::equal(item.value(), c[item.key()]);
  }
  EXPECT_TRUE(differs_from_fixture);
}

TEST(SSDecoder, StrictLoadReportsMismatch) {
  SSDecoderConfig cfg = SSDecoderConfig::load(simu::testing::fixture("ss_decoder_small.json"));
  cfg.channels = {32, 8};  // blocks.1.conv and later levels no longer fit
  SparseStructureDecoder dec(cfg);
  LoadOptions opt;
  opt.ignore_prefixes = {"io."};
  try {
    load_safetensors_into(*dec, simu::testing::fixture("ss_decoder_small.safetensors"), opt);
    FAIL() << "expected a shape-mismatch error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("blocks.1.conv.weight"), std::string::npos) << e.what();
  }
}

// The official YAML layout (_target_, pretrained_ckpt_path) reads into the same config; unknown keys fail.
TEST(SSDecoder, ReadsOfficialYamlLayout) {
  const auto dir = simu::testing::temp_dir("ss_decoder_yaml");
  {
    std::ofstream f(dir + "/ss_decoder.yaml");
    f << "_target_: sam3d_objects.model.backbone.tdfy_dit.models.sparse_structure_vae.SparseStructureDecoderTdfyWrapper\n"
         "out_channels: 1\nlatent_channels: 8\nnum_res_blocks: 2\nnum_res_blocks_middle: 2\n"
         "channels: [512, 128, 32]\nreshape_input_to_cube: false\npretrained_ckpt_path: x.ckpt\n";
  }
  auto cfg = SSDecoderConfig::load(dir + "/ss_decoder.yaml");
  EXPECT_EQ(cfg.channels, (std::vector<int64_t>{512, 128, 32}));
  EXPECT_EQ(cfg.num_res_blocks, 2);
  EXPECT_EQ(cfg.upsample_factor(), 4);
  EXPECT_EQ(cfg.norm_type, "layer");
  {
    std::ofstream f(dir + "/bad.yaml");
    f << "channels: [8]\nnum_res_block: 1\n";
  }
  EXPECT_THROW(SSDecoderConfig::load(dir + "/bad.yaml"), simu::Error);
}

// Token t of the shape latent lands at grid (x, y, z) with t = (x*k + y)*k + z, channel c at dim 1,
// as the official pipeline's permute(0, 2, 1).view(B, C, k, k, k); flat_to_cube agrees.
TEST(SSDecoder, TokenToGridOrder) {
  const int64_t B = 2, k = 4, C = 3, T = k * k * k;
  auto tokens = torch::arange(B * T * C, torch::kFloat32).reshape({B, T, C});
  auto grid = shape_tokens_to_grid(tokens);
  ASSERT_EQ(grid.sizes(), (std::vector<int64_t>{B, C, k, k, k}));
  auto acc = grid.accessor<float, 5>();
  for (int64_t b = 0; b < B; ++b)
    for (int64_t c = 0; c < C; ++c)
      for (int64_t x = 0; x < k; ++x)
        for (int64_t y = 0; y < k; ++y)
          for (int64_t z = 0; z < k; ++z) {
            const int64_t t = (x * k + y) * k + z;
            ASSERT_EQ(acc[b][c][x][y][z], static_cast<float>((b * T + t) * C + c));
          }
  EXPECT_TRUE(torch::equal(flat_to_cube(tokens), grid));
  EXPECT_THROW(shape_tokens_to_grid(torch::zeros({1, 10, 8})), simu::Error);
}

// Occupied coordinates equal an independent scan of the fixture logits for logit > 0.
TEST(SSDecoder, OccupancyMatchesThreshold) {
  auto file = simu::data::SafeTensorsFile::open(simu::testing::fixture("ss_decoder_small.safetensors"));
  auto logits = file.get("io.out").clone();  // [2, 1, 8, 8, 8]
  std::vector<std::array<int, 4>> expected;
  auto acc = logits.accessor<float, 5>();
  for (int b = 0; b < logits.size(0); ++b)
    for (int x = 0; x < logits.size(2); ++x)
      for (int y = 0; y < logits.size(3); ++y)
        for (int z = 0; z < logits.size(4); ++z)
          if (acc[b][0][x][y][z] > 0.f) expected.push_back({b, x, y, z});
  ASSERT_GT(expected.size(), 0u);
  ASSERT_LT(expected.size(), static_cast<size_t>(logits.numel()));
  auto coords = occupied_coords(logits);
  ASSERT_EQ(coords.scalar_type(), torch::kInt32);
  ASSERT_EQ(coords.size(0), static_cast<int64_t>(expected.size()));
  ASSERT_EQ(coords.size(1), 4);
  auto c = coords.accessor<int32_t, 2>();
  for (size_t i = 0; i < expected.size(); ++i)
    for (int j = 0; j < 4; ++j) ASSERT_EQ(c[i][j], expected[i][j]) << "row " << i << " col " << j;
}

// Pixel shuffle: input channel (c*8 + i*4 + j*2 + l) at (h, w, d) goes to (2h+i, 2w+j, 2d+l) of channel c.
TEST(SSDecoder, PixelShuffle3dLayout) {
  const int64_t B = 1, Co = 2, H = 2, W = 3, D = 2;
  auto x = torch::randn({B, Co * 8, H, W, D});
  auto y = pixel_shuffle_3d(x, 2);
  ASSERT_EQ(y.sizes(), (std::vector<int64_t>{B, Co, 2 * H, 2 * W, 2 * D}));
  auto xa = x.accessor<float, 5>();
  auto ya = y.accessor<float, 5>();
  for (int c = 0; c < Co; ++c)
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 2; ++j)
        for (int l = 0; l < 2; ++l)
          for (int h = 0; h < H; ++h)
            for (int w = 0; w < W; ++w)
              for (int d = 0; d < D; ++d)
                ASSERT_EQ(ya[0][c][2 * h + i][2 * w + j][2 * d + l], xa[0][c * 8 + i * 4 + j * 2 + l][h][w][d]);
}

// The real-size config (configs/ss_decoder.yaml) builds the TRELLIS ss_dec_conv3d_16l8 layout:
// 16^3 -> 64^3, and a size matching its released use_fp16 safetensors (147,591,972 bytes: the torso,
// middle_block + blocks, in float16 = 2 bytes, input_layer and out_layer in float32 = 4 bytes, plus a
// JSON header of a few KB).
TEST(SSDecoder, RealConfigLayout) {
  auto cfg = SSDecoderConfig::load(simu::testing::source_dir() + "/configs/ss_decoder.yaml");
  SparseStructureDecoder dec(cfg);
  int64_t params = 0, bytes = 0;
  std::map<std::string, std::vector<int64_t>> shapes;
  for (const auto& p : dec->named_parameters()) {
    params += p.value().numel();
    const bool torso = p.key().rfind("blocks.", 0) == 0 || p.key().rfind("middle_block.", 0) == 0;
    bytes += p.value().numel() * (torso ? 2 : 4);
    shapes[p.key()] = p.value().sizes().vec();
  }
  EXPECT_EQ(cfg.upsample_factor(), 4);
  EXPECT_EQ(shapes.at("blocks.2.conv.weight"), (std::vector<int64_t>{1024, 512, 3, 3, 3}));
  EXPECT_EQ(shapes.at("blocks.5.conv.weight"), (std::vector<int64_t>{256, 128, 3, 3, 3}));
  EXPECT_EQ(shapes.at("blocks.7.conv2.weight"), (std::vector<int64_t>{32, 32, 3, 3, 3}));
  EXPECT_EQ(shapes.at("out_layer.2.weight"), (std::vector<int64_t>{1, 32, 3, 3, 3}));
  EXPECT_EQ(shapes.count("blocks.8.conv1.weight"), 0u);
  std::printf("real ss decoder parameters: %ld\n", static_cast<long>(params));
  EXPECT_LT(bytes, 147591972);
  EXPECT_GT(bytes, 147591972 - 64 * 1024);
}

// The official constructor builds ResBlock3d(ch, ch) without norm_type, so every residual block uses
// ChannelLayerNorm32 and only the output head follows norm_type ("group": a GroupNorm32 head).
TEST(SSDecoder, ResidualBlocksUseLayerNormWhateverTheHead) {
  SSDecoderConfig cfg;
  cfg.channels = {32, 32};
  cfg.num_res_blocks = 1;
  cfg.num_res_blocks_middle = 1;
  cfg.norm_type = "group";
  SparseStructureDecoder dec(cfg);
  int res_norms = 0;
  for (const auto& m : dec->named_modules()) {
    if (auto* n = m.value()->as<ChannelNorm32Impl>()) {
      const bool head = m.key() == "out_layer.0";
      EXPECT_EQ(n->group, head) << m.key();
      res_norms += head ? 0 : 1;
    }
  }
  EXPECT_EQ(res_norms, 6);  // middle_block.0, blocks.0, blocks.2: norm1 and norm2 each
}
