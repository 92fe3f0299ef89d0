// Tests the model a program runs when given no weights (resample/default_model.h): the model folder's
// manifest is read strictly (key and file named), the shipped model replaces the config only when
// nothing contradicts it (no weights, no --random-weights, default configs), the preprocessing choice
// ("model", a preset, a file), and, where weights/miniature_cpu is present, that the shipped folder
// loads into a Resampler whose embedder reads the preprocessing the folder names.
#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include "common/error.h"
#include "common/fs.h"
#include "common/source_dir.h"
#include "pipeline/resample/default_model.h"
#include "pipeline/resample/lift.h"
#include "pipeline/resample/resampler.h"
#include "pipeline/world/scene.h"
#include "pipeline/world/shapes.h"
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

// The manifest's optional mesh.surface_offset_voxels reaches the config through the shipped model (0
// without it), unless the user set an offset; a value that is not a number in [0, 2] is refused by key.
TEST(ModelFolder, SurfaceOffset) {
  const auto plain = fake_folder("mf_off0", kFiles);
  EXPECT_EQ(sr::ModelFolder::load(plain).surface_offset, 0.0);
  const auto dir = fake_folder("mf_off", kFiles);
  write(dir + "/manifest.json", R"({"name": "fake", "files": )" + kFiles + R"(, "mesh": {"surface_offset_voxels": 0.5}})");
  EXPECT_EQ(sr::ModelFolder::load(dir).surface_offset, 0.5);
  {
    DefaultModelEnv env(dir);
    sr::ResamplerConfig c;
    EXPECT_TRUE(std::isnan(c.surface_offset));
    sr::apply_shipped_model(c);
    EXPECT_EQ(c.surface_offset, 0.5);
    sr::ResamplerConfig mine;
    mine.surface_offset = 0.0;
    sr::apply_shipped_model(mine);
    EXPECT_EQ(mine.surface_offset, 0.0);
  }
  for (const char* bad : {R"("half")", "3.0", "-0.1"}) {
    write(dir + "/manifest.json", R"({"name": "fake", "files": )" + kFiles + R"(, "mesh": {"surface_offset_voxels": )" + bad + "}}");
    const auto e = simu::testing::error_of([&] { sr::ModelFolder::load(dir); });
    EXPECT_NE(e.find("surface_offset_voxels"), std::string::npos) << bad << ": " << e;
  }
  simu::fs::remove_tree(plain);
  simu::fs::remove_tree(dir);
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

// The folder's resampling adapter (files.resample_adapter) is taken only where a program asks for it
// (shipped_resample_adapter) and gave no adapter of its own; a folder naming one that is not a PEFT
// folder is refused naming the key.
TEST(ShippedModel, ResampleAdapterOnlyWhereAsked) {
  const auto dir = fake_folder("mf_adapter", R"({"generator_config": "g.yaml", "generator_weights": "w.safetensors",
      "embedder_config": "e.json", "embedder_weights": "w.safetensors", "decoder_config": "d.json",
      "decoder_weights": "d.safetensors", "preprocess": "p.yaml", "resample_adapter": "adapter"})");
  std::filesystem::create_directories(dir + "/adapter");
  const auto e = simu::testing::error_of([&] { sr::ModelFolder::load(dir); });
  EXPECT_NE(e.find("files.resample_adapter"), std::string::npos) << e;
  write(dir + "/adapter/adapter_config.json", "{}");
  DefaultModelEnv env(dir);
  // Not asked (lift, eval_lift, build_pairs): the base model alone.
  sr::ResamplerConfig base;
  sr::apply_shipped_model(base);
  EXPECT_TRUE(base.adapter_dir.empty());
  EXPECT_FALSE(base.adapter_resample_only);
  // Asked (probe --resample, reconstruct): the adapter, for resampling only, and the note says so.
  sr::ResamplerConfig asked;
  asked.shipped_resample_adapter = true;
  const auto note = sr::apply_shipped_model(asked);
  EXPECT_EQ(asked.adapter_dir, dir + "/adapter");
  EXPECT_TRUE(asked.adapter_resample_only);
  EXPECT_NE(note.find("FM-DPO adapter"), std::string::npos) << note;
  // The user's own adapter wins and applies everywhere.
  sr::ResamplerConfig own;
  own.shipped_resample_adapter = true;
  own.adapter_dir = "mine";
  sr::apply_shipped_model(own);
  EXPECT_EQ(own.adapter_dir, "mine");
  EXPECT_FALSE(own.adapter_resample_only);
  simu::fs::remove_tree(dir);
}

// With the shipped folder's adapter for resampling only: a first lift equals the base model's lift
// bit for bit (the adapter is off), a resampling call (LiftOptions::resampling) does not (it is on),
// and after the first lift the adapter is on again.
TEST(ShippedModel, ResampleAdapterIsOffInTheFirstLift) {
  const std::string dir = simu::source_dir() + "/weights/miniature_cpu";
  if (!std::filesystem::exists(dir + "/manifest.json")) GTEST_SKIP() << dir << " is not in this checkout";
  if (sr::ModelFolder::load(dir).resample_adapter.empty()) GTEST_SKIP() << dir << " ships no resampling adapter";
  // One shape-world test scene, its first two objects.
  simu::world::SceneConfig sc;
  uint64_t seed = 0;
  while (simu::world::scene_split_of(seed) != simu::world::Split::Test) ++seed;
  const auto scene = simu::world::make_scene(sc, seed, simu::world::Split::Test);
  ASSERT_GE(scene.objects.size(), 2u);
  const int H = scene.camera.height, W = scene.camera.width;
  sr::LiftInputs in;
  in.rgb = torch::from_blob(const_cast<uint8_t*>(scene.rgb.data()), {H, W, 3}, torch::kUInt8)
               .permute({2, 0, 1}).to(torch::kFloat32).div(255.0).contiguous();
  in.pointmap = torch::from_blob(const_cast<float*>(scene.pointmap.xyz.data()), {H, W, 3}, torch::kFloat32).clone();
  in.camera = scene.camera;
  for (int k = 0; k < 2; ++k) {
    const auto& m = scene.objects[k].modal;
    in.objects.push_back({"obj" + std::to_string(k),
                          torch::from_blob(const_cast<uint8_t*>(m.data.data()), {m.height, m.width}, torch::kUInt8)
                              .to(torch::kFloat32),
                          {}, ""});
  }
  sr::ResamplerConfig c;
  c.device = "cpu";
  sr::Resampler base(c);
  c.shipped_resample_adapter = true;
  sr::Resampler tuned(c);
  ASSERT_TRUE(tuned.adapter_resample_only());
  EXPECT_FALSE(base.has_adapter());
  sr::LiftOptions lo;
  lo.seed = 3;
  const auto a = sr::lift_objects(base, in, lo), b = sr::lift_objects(tuned, in, lo);
  lo.resampling = true;
  const auto r = sr::lift_objects(tuned, in, lo);
  for (size_t k = 0; k < 2; ++k) {
    ASSERT_TRUE(a.objects[k].ok && b.objects[k].ok && r.objects[k].ok) << a.objects[k].error << b.objects[k].error;
    const auto& la = a.objects[k].samples[0].latents.at("shape");
    EXPECT_TRUE(torch::equal(la, b.objects[k].samples[0].latents.at("shape"))) << "first lift, object " << k;
    EXPECT_FALSE(torch::equal(la, r.objects[k].samples[0].latents.at("shape"))) << "resampling, object " << k;
  }
  // The first lift switched it back on: a second resampling call repeats the first.
  const auto r2 = sr::lift_objects(tuned, in, lo);
  EXPECT_TRUE(torch::equal(r.objects[0].samples[0].latents.at("shape"), r2.objects[0].samples[0].latents.at("shape")));
}
