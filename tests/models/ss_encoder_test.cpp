// Sparse-structure encoder: parity with the official module (fixture made by
// scripts/fixtures/make_encoder.py, committed in tests/testdata/models/), the posterior sample with a
// given noise, the config readers, and the official layer structure (layer-norm residual blocks).
#include <fstream>

#include "common/error.h"
#include "data/safetensors.h"
#include "models/ss_encoder.h"
#include "models/weights.h"
#include "test_util.h"

using namespace simu::models;

namespace {
std::string data(const std::string& name) { return simu::testing::source_dir() + "/tests/testdata/models/" + name; }
SparseStructureEncoder small_encoder() {
  return load_ss_encoder(data("ss_encoder_small.json"), data("ss_encoder_small.safetensors"));
}
// The fixture README's float32 tolerance (max |a-b| / max|b|). The port runs the same convolutions in
// another summation order: each output sums <= 27 * 16 = 432 products, a relative rounding of about
// sqrt(432) * 2^-24 ~ 1.2e-6 per layer; nine layers deep with norms re-scaling in between stays
// below ~1.1e-5, ten times under the bound.
constexpr double kTol = 1e-4;
}  // namespace

// io.in -> mean, logvar (no sampling) and the posterior sample with the official draw io.noise.
TEST(SSEncoder, MatchesOfficialFixture) {
  auto enc = small_encoder();
  auto file = simu::data::SafeTensorsFile::open(data("ss_encoder_small.safetensors"));
  const auto in = file.get("io.in").clone(), noise = file.get("io.noise").clone();
  torch::NoGradGuard ng;
  const auto plain = enc->forward(in);
  EXPECT_TRUE(simu::testing::close(plain.mean, file.get("io.mean"), kTol, "io.mean"));
  EXPECT_TRUE(simu::testing::close(plain.logvar, file.get("io.logvar"), kTol, "io.logvar"));
  EXPECT_TRUE(torch::equal(plain.z, plain.mean)) << "without sampling z is the mean";
  const auto sampled = enc->forward(in, /*sample_posterior=*/true, noise);
  EXPECT_TRUE(simu::testing::close(sampled.z, file.get("io.z"), kTol, "io.z"));
  std::printf("ss_encoder_small rel err: mean %.3g logvar %.3g z %.3g\n",
              simu::testing::rel_err(plain.mean, file.get("io.mean")),
              simu::testing::rel_err(plain.logvar, file.get("io.logvar")),
              simu::testing::rel_err(sampled.z, file.get("io.z")));
  // The latent grid is the input's divided by the two down-samplings.
  EXPECT_EQ(plain.mean.sizes(), (std::vector<int64_t>{2, 8, 4, 4, 4}));
}

// Without a given noise the sample draws from the default generator (as randn_like), so two draws differ
// and the same seed repeats one; the sample's spread around the mean is exp(logvar / 2).
TEST(SSEncoder, SampleDrawsFromTheDefaultGenerator) {
  auto enc = small_encoder();
  auto file = simu::data::SafeTensorsFile::open(data("ss_encoder_small.safetensors"));
  const auto in = file.get("io.in").clone();
  torch::NoGradGuard ng;
  torch::manual_seed(3);
  const auto a = enc->forward(in, true);
  const auto b = enc->forward(in, true);
  torch::manual_seed(3);
  const auto c = enc->forward(in, true);
  EXPECT_FALSE(torch::equal(a.z, b.z));
  EXPECT_TRUE(torch::equal(a.z, c.z));
  // (z - mean) / std is the standard-normal draw itself: over 4,096 elements its mean is within 5
  // standard errors (5 / 64 ~ 0.08) of 0 and its variance within 5 x sqrt(2/4096) ~ 0.11 of 1.
  const auto u = (a.z - a.mean) / torch::exp(0.5 * a.logvar);
  EXPECT_NEAR(u.mean().item<double>(), 0.0, 0.08);
  EXPECT_NEAR(u.var().item<double>(), 1.0, 0.11);
  EXPECT_THROW(enc->forward(in, true, torch::zeros({1, 8, 4, 4, 4})), simu::Error);
}

// The TdfyWrapper's flags: encode() samples and keeps mean/logvar by the config; the plain class does not.
TEST(SSEncoder, WrapperFlagsFollowTheConfig) {
  const auto dir = simu::testing::temp_dir("ss_encoder_yaml");
  {
    std::ofstream f(dir + "/wrapper.yaml");
    f << "_target_: sam3d_objects.model.backbone.tdfy_dit.models.sparse_structure_vae.SparseStructureEncoderTdfyWrapper\n"
         "in_channels: 1\nlatent_channels: 8\nnum_res_blocks: 2\nnum_res_blocks_middle: 2\n"
         "channels: [32, 128, 512]\npretrained_ckpt_path: x.ckpt\n";
  }
  const auto wrapper = SSEncoderConfig::load(dir + "/wrapper.yaml");
  EXPECT_TRUE(wrapper.sample_posterior);
  EXPECT_TRUE(wrapper.return_raw);
  EXPECT_EQ(wrapper.downsample_factor(), 4);
  EXPECT_EQ(wrapper.channels, (std::vector<int64_t>{32, 128, 512}));
  const auto plain = SSEncoderConfig::load(data("ss_encoder_small.json"));
  EXPECT_FALSE(plain.sample_posterior);
  EXPECT_FALSE(plain.return_raw);
  // encode() with the plain config: z = mean, no mean/logvar returned.
  SparseStructureEncoder enc(plain);
  torch::NoGradGuard ng;
  const auto out = enc->encode(torch::ones({1, 1, 8, 8, 8}));
  EXPECT_TRUE(out.z.defined());
  EXPECT_FALSE(out.mean.defined());
  // Overrides with the wrapper flags: a sample (differs from the mean) with mean and logvar.
  auto sampling = SSEncoderConfig::load(data("ss_encoder_small.json"), {"sample_posterior=true", "return_raw=true"});
  SparseStructureEncoder enc2(sampling);
  const auto out2 = enc2->encode(torch::ones({1, 1, 8, 8, 8}));
  ASSERT_TRUE(out2.mean.defined());
  EXPECT_FALSE(torch::equal(out2.z, out2.mean));
  // Unknown keys, a wrong class and a group head too narrow for 32 groups are errors naming the file.
  for (const auto& [name, text] : std::vector<std::pair<std::string, std::string>>{
           {"typo.yaml", "channels: [8]\nnum_res_block: 1\n"},
           {"class.yaml", "_target_: x.SparseStructureDecoder\nchannels: [8]\n"},
           {"group.yaml", "channels: [8, 16]\nnorm_type: group\n"}}) {
    {
      std::ofstream f(dir + "/" + name);
      f << text;
    }
    const auto msg = simu::testing::error_of([&] { SSEncoderConfig::load(dir + "/" + name); });
    EXPECT_NE(msg.find(name), std::string::npos) << name << ": " << msg;
  }
}

// The official constructor builds ResBlock3d(ch, ch) without norm_type, so every residual block uses
// ChannelLayerNorm32 and only the output head follows norm_type: with "group", the head is a GroupNorm32
// and the blocks keep layer norms (the official state dict has the same keys either way).
TEST(SSEncoder, ResidualBlocksUseLayerNormWhateverTheHead) {
  SSEncoderConfig cfg;
  cfg.channels = {8, 32};
  cfg.num_res_blocks = 1;
  cfg.num_res_blocks_middle = 1;
  cfg.norm_type = "group";
  SparseStructureEncoder enc(cfg);
  int res_norms = 0;
  for (const auto& m : enc->named_modules()) {
    if (auto* n = m.value()->as<ChannelNorm32Impl>()) {
      const bool head = m.key() == "out_layer.0";
      EXPECT_EQ(n->group, head) << m.key();
      res_norms += head ? 0 : 1;
    }
  }
  EXPECT_EQ(res_norms, 6);  // blocks.0, blocks.2, middle_block.0: norm1 and norm2 each
}

// Strict loading names the offending keys; the module tree's names are the official ones.
TEST(SSEncoder, StrictLoadReportsMismatch) {
  SSEncoderConfig cfg = SSEncoderConfig::load(data("ss_encoder_small.json"));
  cfg.channels = {8, 16, 32};  // the last level's blocks no longer fit
  SparseStructureEncoder enc(cfg);
  LoadOptions opt;
  opt.ignore_prefixes = {"io."};
  const auto msg = simu::testing::error_of([&] { load_safetensors_into(*enc, data("ss_encoder_small.safetensors"), opt); });
  EXPECT_NE(msg.find("blocks.3.conv.weight"), std::string::npos) << msg;
  EXPECT_NE(msg.find("middle_block.0.conv1.weight"), std::string::npos) << msg;
}

// The KL term against its closed form for two univariate cases: N(0, 1) has none; N(1, e) has
// 0.5 * (1 + e - 1 - 1) = 0.5 * (e - 1).
TEST(SSEncoder, KlToStandardNormal) {
  const auto kl = kl_to_standard_normal(torch::tensor({0.0f, 1.0f}), torch::tensor({0.0f, 1.0f}));
  EXPECT_EQ(kl[0].item<float>(), 0.0f);
  // float32 exp and three additions on values <= e: 4 roundings of 2^-24 relative on magnitudes <= 3.
  EXPECT_NEAR(kl[1].item<double>(), 0.5 * (std::exp(1.0) - 1.0), 4 * 3 * 6e-8);
}
