// Tests the model a program runs when given no weights (resample/default_model.h): the model folder's
// manifest is read strictly (key and file named), the shipped model replaces the config only when
// nothing contradicts it (no weights, no --random-weights, default configs), the preprocessing choice
// ("model", a preset, a file), and, where weights/miniature_cpu is present, that the shipped folder
// loads into a Resampler whose embedder reads the preprocessing the folder names.
#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include "common/error.h"
#include "common/fs.h"
#include "common/source_dir.h"
#include "pipeline/resample/default_model.h"
#include "pipeline/resample/resampler.h"
#include "test_files.h"

namespace sr = simu::resample;

namespace {

void write(const std::string& path, const std::string& text) {
  std::ofstream(path) << text;
}

// A model folder with placeholder files (the loader checks names and existence, not contents).
std::string fake_folder(const std::string& name, const std::string& files_json) {
  const auto dir = simu::testing::temp_dir(name);
  for (const char* f : {"g.yaml", "w.safetensors", "e.json", "d.json", "d.safetensors"}) write(dir + "/" + f, "x");
  write(dir + "/p.yaml", "preset: released\nimage_size: 56\npointmap_size: 32\n");
  write(dir + "/manifest.json", R"({"name": "fake", "description": "a test folder", "files": )" + files_json + "}");
  return dir;
}

const std::string kFiles =
    R"({"generator_config": "g.yaml", "generator_weights": "w.safetensors", "embedder_config": "e.json",
        "embedder_weights": "w.safetensors", "decoder_config": "d.json", "decoder_weights": "d.safetensors",
        "preprocess": "p.yaml"})";

// Sets SIMU_DEFAULT_MODEL for one scope.
struct DefaultModelEnv {
  explicit DefaultModelEnv(const std::string& dir) { ::setenv("SIMU_DEFAULT_MODEL", dir.c_str(), 1); }
  ~DefaultModelEnv() { ::unsetenv("SIMU_DEFAULT_MODEL"); }
};

}  // namespace

// A manifest without a key, or naming a file that is not there, is refused naming the manifest and key.
TEST(ModelFolder, RefusesMissingKeysAndFiles) {
  const auto no_key = fake_folder("mf_nokey", R"({"generator_config": "g.yaml"})");
  const auto e1 = simu::testing::error_of([&] { sr::ModelFolder::load(no_key); });
  EXPECT_NE(e1.find(no_key + "/manifest.json"), std::string::npos) << e1;
  EXPECT_NE(e1.find("files.generator_weights"), std::string::npos) << e1;
  const auto gone = fake_folder("mf_gone", kFiles);
  simu::fs::remove_tree(gone + "/d.safetensors");
  const auto e2 = simu::testing::error_of([&] { sr::ModelFolder::load(gone); });
  EXPECT_NE(e2.find("files.decoder_weights"), std::string::npos) << e2;
  EXPECT_NE(e2.find("not found"), std::string::npos) << e2;
}

// The shipped folder fills a config with no weights and default configs; anything the user chose wins.
TEST(ShippedModel, AppliesOnlyWhenNothingContradicts) {
  const auto dir = fake_folder("mf_apply", kFiles);
  DefaultModelEnv env(dir);
  sr::ResamplerConfig c;
  const std::string note = sr::apply_shipped_model(c);
  EXPECT_NE(note.find("not SAM 3D"), std::string::npos) << note;
  EXPECT_EQ(c.generator_weights, dir + "/w.safetensors");
  EXPECT_EQ(c.embedder_weights, dir + "/w.safetensors");
  EXPECT_EQ(c.decoder_weights, dir + "/d.safetensors");
  EXPECT_EQ(c.generator_config, dir + "/g.yaml");
  EXPECT_EQ(c.decoder_config, dir + "/d.json");
  EXPECT_EQ(c.embedder_config, dir + "/e.json");
  EXPECT_EQ(c.preprocess, dir + "/p.yaml");
  // Applied once: a second call changes nothing.
  const auto before = c.generator_config;
  EXPECT_TRUE(sr::apply_shipped_model(c).empty());
  EXPECT_EQ(c.generator_config, before);
  // --random-weights, any weight file, another config or a generator override: left as they were.
  sr::ResamplerConfig r;
  r.random_weights = true;
  EXPECT_TRUE(sr::apply_shipped_model(r).empty());
  EXPECT_TRUE(r.generator_weights.empty());
  sr::ResamplerConfig w;
  w.decoder_weights = "mine.safetensors";
  EXPECT_TRUE(sr::apply_shipped_model(w).empty());
  EXPECT_TRUE(w.generator_weights.empty());
  sr::ResamplerConfig g;
  g.generator_config = "mine.yaml";
  EXPECT_TRUE(sr::apply_shipped_model(g).empty());
  EXPECT_EQ(g.generator_config, "mine.yaml");
  sr::ResamplerConfig o;
  o.generator_overrides = {"generator.cfg_strength=3"};
  EXPECT_TRUE(sr::apply_shipped_model(o).empty());
  // A preprocessing the user chose is kept.
  sr::ResamplerConfig p;
  p.preprocess = "default";
  sr::apply_shipped_model(p);
  EXPECT_EQ(p.preprocess, "default");
  // No folder there: nothing applied (the missing-weights error of the caller follows).
  DefaultModelEnv none(dir + "/absent");
  sr::ResamplerConfig n;
  EXPECT_TRUE(sr::apply_shipped_model(n).empty());
  EXPECT_TRUE(n.generator_weights.empty());
  simu::fs::remove_tree(dir);
}

// "model" is the config's preprocessing (released when empty); presets by name; a YAML file by path.
TEST(ShippedModel, PreprocessChoice) {
  const auto released = simu::data::PreprocessConfig::preset_named("released");
  sr::ResamplerConfig c;
  EXPECT_EQ(sr::preprocess_choice("model", c).image_size, released.image_size);
  EXPECT_EQ(sr::preprocess_choice("", c).box_size_factor, released.box_size_factor);
  EXPECT_EQ(sr::preprocess_choice("default", c).preset, "default");
  const auto dir = fake_folder("mf_pre", kFiles);
  c.preprocess = dir + "/p.yaml";
  EXPECT_EQ(sr::preprocess_choice("model", c).image_size, 56);
  EXPECT_EQ(sr::preprocess_choice("model", c).pointmap_size, 32);
  EXPECT_EQ(sr::preprocess_choice("released", c).image_size, released.image_size);
  const auto e = simu::testing::error_of([&] { sr::preprocess_choice("nonsense", c); });
  EXPECT_NE(e.find("nonsense"), std::string::npos) << e;
  write(dir + "/bad.yaml", "image_size: 56\nimage_sise: 3\n");
  const auto e2 = simu::testing::error_of([&] { sr::preprocess_choice(dir + "/bad.yaml", c); });
  EXPECT_NE(e2.find("image_sise"), std::string::npos) << e2;
  simu::fs::remove_tree(dir);
}

// The shipped folder itself (when the checkout has it): its manifest holds, and a Resampler made from a
// default config loads it, says so, and its embedder reads the folder's preprocessing sizes.
TEST(ShippedModel, TheShippedFolderLoads) {
  const std::string dir = simu::source_dir() + "/weights/miniature_cpu";
  if (!std::filesystem::exists(dir + "/manifest.json")) GTEST_SKIP() << dir << " is not in this checkout";
  const auto m = sr::ModelFolder::load(dir);
  sr::ResamplerConfig c;
  c.device = "cpu";
  sr::Resampler rs(c);
  EXPECT_NE(rs.shipped_model_note().find("not SAM 3D"), std::string::npos);
  EXPECT_TRUE(rs.random_weights_banner().empty());
  EXPECT_EQ(rs.config().generator_weights, m.generator_weights);
  ASSERT_TRUE(rs.embedder());
  // The preprocessing makes the inputs at the sizes the embedder reads (its config's input sizes).
  const auto pre = sr::preprocess_choice("model", rs.config());
  const auto e = nlohmann::json::parse(simu::fs::read_file(m.embedder_config));
  EXPECT_EQ(pre.image_size, e.at("dino_image_input_size").get<int>());
  EXPECT_EQ(pre.pointmap_size, e.at("pointpatch").at("input_size").get<int>());
}
