// The real files, strictly: checkpoints in the layout of the released SAM 3D Objects Stage-1 files at
// the released dimensions (tests/models/make_official_checkpoint.py, written with PyTorch: a
// Lightning-style ss_generator.ckpt with every _base_models.generator.* and
// _base_models.condition_embedder.* key, a plain ss_decoder.ckpt; names checked against the small
// models the official code wrote), converted by scripts/convert_checkpoint.py, then loaded into the
// three modules strictly: zero missing or unexpected keys, every tensor of the files used once.
// The tensors are stride-0 zeros, so the .ckpt files are small and the safetensors files sparse.
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "common/error.h"
#include "common/fs.h"
#include "data/safetensors.h"
#include "models/cond_embedder.h"
#include "models/generator.h"
#include "models/ss_decoder.h"
#include "models/weights.h"
#include "test_util.h"

namespace sm = simu::models;

namespace {

std::string released_yaml() { return simu::testing::source_dir() + "/tests/testdata/models/ss_generator_released.yaml"; }

// Runs a command, returns its exit code; output goes to `log`.
int run(const std::string& cmd, const std::string& log) {
  return WEXITSTATUS(std::system((cmd + " > " + log + " 2>&1").c_str()));
}
std::string slurp(const std::string& path) {
  std::stringstream s;
  s << std::ifstream(path).rdbuf();
  return s.str();
}

int64_t count_prefix(const simu::data::SafeTensorsFile& f, const std::string& prefix) {
  int64_t n = 0;
  for (const auto& k : f.keys()) n += k.rfind(prefix, 0) == 0;
  return n;
}

}  // namespace

TEST(OfficialCheckpoint, ReleasedLayoutConvertsAndLoadsStrictly) {
  const auto dir = simu::testing::temp_dir("official_ckpt");
  const std::string py = simu::testing::python_exe();
  const auto src = simu::testing::source_dir();
  // 1. The official-layout checkpoints (names checked against the official small fixtures).
  ASSERT_EQ(run(py + " " + src + "/tests/models/make_official_checkpoint.py " + dir + " --check-against " +
                    simu::testing::shared_dir() + "/fixtures",
                dir + "/make.log"),
            0)
      << slurp(dir + "/make.log");
  // 2. Conversion, as checkpoints/README.md says.
  for (const char* name : {"ss_generator", "ss_decoder"}) {
    const std::string cmd = py + " " + src + "/scripts/convert_checkpoint.py " + dir + "/" + name + ".ckpt " + dir +
                            "/" + name + ".safetensors";
    ASSERT_EQ(run(cmd, dir + "/convert.log"), 0) << slurp(dir + "/convert.log");
  }
  const auto gf = simu::data::SafeTensorsFile::open(dir + "/ss_generator.safetensors");
  const int64_t n_gen = count_prefix(gf, "_base_models.generator.");
  const int64_t n_emb = count_prefix(gf, "_base_models.condition_embedder.");
  EXPECT_EQ(n_gen + n_emb, static_cast<int64_t>(gf.keys().size())) << "keys outside the two components";
  EXPECT_EQ(n_gen, 945);  // 8 time embedders + 25 latent mapping + 24 blocks x 38
  EXPECT_EQ(n_emb, 722);  // 2 x ViT-L (8 + 24 x 14) + PointPatchEmbed 18 + 3 projections x 5 + idx_emb
  EXPECT_EQ(gf.info("_base_models.generator.reverse_fn.backbone.blocks.23.mlp.shape.mlp.0.weight").shape,
            (std::vector<int64_t>{4096, 1024}));

  // 3. Generator: strict load (an error lists every missing / unexpected / mismatched key), every
  //    module tensor loaded from the file and every file tensor of the prefix used.
  {
    auto g = sm::load_generator(released_yaml(), dir + "/ss_generator.safetensors", torch::kCPU);
    const auto sd = sm::state_dict(*g);
    EXPECT_EQ(static_cast<int64_t>(sd.size()), n_gen);
    EXPECT_EQ(g->config().backbone.num_blocks, 24);
    EXPECT_EQ(g->config().backbone.model_channels, 1024);
    for (const auto& [k, v] : sd) EXPECT_EQ(v.abs().max().item<float>(), 0.f) << k << " not from the file";
  }
  // 4. Condition embedder from the same yaml and file (prefix found automatically): 7,528 tokens of
  //    1,024 channels per object = 4 x (1 + 37^2) DINO tokens + 2 x 32^2 point-patch tokens.
  {
    auto e = sm::load_cond_embedder(released_yaml(), dir + "/ss_generator.safetensors", "auto", torch::kCPU);
    EXPECT_EQ(static_cast<int64_t>(sm::state_dict(*e).size()), n_emb);
    EXPECT_EQ(e->num_tokens(), 4 * 1370 + 2 * 1024);
    EXPECT_EQ(e->num_tokens(), 7528);
    EXPECT_EQ(e->embed_dims(), 1024);
  }
  // 5. Decoder: a plain state dict, strictly.
  const auto df = simu::data::SafeTensorsFile::open(dir + "/ss_decoder.safetensors");
  {
    auto d = sm::load_ss_decoder(src + "/configs/ss_decoder.yaml", dir + "/ss_decoder.safetensors");
    EXPECT_EQ(sm::state_dict(*d).size(), df.keys().size());
    EXPECT_EQ(df.keys().size(), 74u);
  }
  // 6. A config that does not match the weights: one error naming the keys, got versus expected.
  try {
    sm::SparseStructureDecoder d(sm::SSDecoderConfig::load(src + "/configs/ss_decoder.yaml",
                                                           {"num_res_blocks_middle=3", "channels=[512,128,16]"}));
    sm::LoadOptions lo;
    lo.source = dir + "/ss_decoder.safetensors";
    sm::load_safetensors_into(*d, lo.source, lo);
    FAIL() << "expected a mismatch error";
  } catch (const simu::Error& err) {
    const std::string m = err.what();
    EXPECT_NE(m.find("middle_block.2.conv1.weight"), std::string::npos) << m;  // missing in the file
    EXPECT_NE(m.find("out_layer.2.weight"), std::string::npos) << m;          // shape mismatch
    EXPECT_NE(m.find("ss_decoder.safetensors"), std::string::npos) << m;
  }
  simu::fs::remove_tree(dir);
}
