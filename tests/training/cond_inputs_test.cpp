// Training on an inputs-mode pair cache (src/training/cond_inputs.cpp): build_pairs writes a tokens-mode
// (float32) and an inputs-mode (exact storage) cache from the same records, and the trainer, running the
// frozen condition embedder inside the step for the latter, ends with bit-identical adapters on CPU; the
// compact storage (rounded inputs) gives different adapters, so the comparison can fail. build_pairs skips
// (and reports) a record whose inputs the storage refuses (a 16-bit mask). Also: a missing
// model.embedder_config, an embedder that makes other tokens than the cache's, and inputs-mode pairs
// without an embedder are errors naming the key / file.
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "common/error.h"
#include "common/fs.h"
#include "data/pair_cache.h"
#include "data/safetensors.h"
#include "models/cond_embedder.h"
#include "pipeline/resample/pair_builder.h"
#include "test_util.h"
#include "training/cond_inputs.h"
#include "training/generator_policy.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

using namespace simu::training;
using simu::testing::error_of;

namespace {

constexpr int H = 36, W = 44;

// The demo's small embedder with both ViTs at 70 px (a few seconds per build).
std::string embedder_config(const std::string& dir) {
  auto j = nlohmann::json::parse(simu::fs::read_file(simu::testing::source_dir() + "/configs/demo_embedder_small.json"));
  j["dino_image_input_size"] = 70;
  simu::fs::atomic_write(dir + "/embedder.json", j.dump(1));
  return dir + "/embedder.json";
}

// Random embedder weights, saved so that the builder and the trainer load the same ones.
std::string embedder_weights(const std::string& dir, const std::string& config) {
  torch::manual_seed(11);
  simu::models::CondEmbedder emb(simu::models::CondEmbedderConfig::load(config));
  std::map<std::string, torch::Tensor> tensors;
  for (const auto& p : emb->named_parameters()) tensors[p.key()] = p.value().detach().clone();
  for (const auto& b : emb->named_buffers()) tensors[b.key()] = b.value().detach().clone();
  simu::data::save_safetensors(dir + "/embedder.safetensors", tensors);
  return dir + "/embedder.safetensors";
}

#ifdef SIMU_HAVE_OPENCV
// An 8-bit PNG of a float image [3, H, W] in [0, 1] or a mask [H, W].
void write_png(const std::string& path, const torch::Tensor& t) {
  auto u8 = (t * 255).round().clamp(0, 255).to(torch::kUInt8);
  if (t.dim() == 3) u8 = u8.flip({0}).permute({1, 2, 0});  // RGB -> OpenCV's BGR, [H, W, 3]
  u8 = u8.contiguous();
  cv::Mat m(H, W, t.dim() == 3 ? CV_8UC3 : CV_8UC1, u8.data_ptr<uint8_t>());
  ASSERT_TRUE(cv::imwrite(path, m)) << path;
}

// Two occlusion-completion and two clean-preservation records with textured boxes; the manifest.
std::string write_manifest(const std::string& dir) {
  std::string lines;
  for (int i = 0; i < 4; ++i) {
    torch::manual_seed(100 + i);
    auto target = torch::zeros({H, W});
    target.slice(0, 6 + i, 28 + i).slice(1, 8 + 2 * i, 30 + 2 * i).fill_(1);
    auto cover = torch::zeros({H, W});
    cover.slice(0, 20 + i, H).slice(1, 4, 40).fill_(1);
    const auto bg = torch::rand({3, H, W}) * 0.3 + 0.3;
    const auto full = torch::where(target > 0, torch::rand({3, H, W}) * 0.2 + 0.7, bg);
    const std::string p = fmt::format("{}/r{}_", dir, i);
    if (i % 2 == 0) {
      write_png(p + "image.png", torch::where(cover > 0, torch::rand({3, H, W}) * 0.2, full));
      write_png(p + "mask.png", target * (1 - cover));
      write_png(p + "full.png", full);
      write_png(p + "full_mask.png", target);
      lines += fmt::format(R"({{"id": "occ{}", "kind": "occlusion_completion", "image": "r{}_image.png", "mask": "r{}_mask.png", "full_image": "r{}_full.png", "full_mask": "r{}_full_mask.png"}})",
                           i, i, i, i, i) + "\n";
    } else {
      write_png(p + "image.png", full);
      write_png(p + "mask.png", target);
      write_png(p + "bad.png", target * cover);
      lines += fmt::format(R"({{"id": "clean{}", "kind": "clean_preservation", "image": "r{}_image.png", "mask": "r{}_mask.png", "corrupted_mask": "r{}_bad.png"}})",
                           i, i, i, i) + "\n";
    }
  }
  simu::fs::atomic_write(dir + "/pairs.jsonl", lines);
  return dir + "/pairs.jsonl";
}
#endif

// Builds a cache from the manifest with the small fixture generator (2 sampling steps), float32.
simu::resample::PairBuildReport build_report(const std::string& manifest, const std::string& out,
                                             const std::string& cond_mode, const std::string& storage,
                                             const std::string& emb_cfg, const std::string& emb_w) {
  simu::resample::PairBuilderConfig cfg;
  auto& rc = cfg.resampler;
  rc.generator_config = simu::testing::fixture("ss_generator_small.json");
  rc.generator_weights = simu::testing::fixture("ss_generator_small.safetensors");
  rc.decoder_config = simu::testing::fixture("ss_decoder_small.json");
  rc.embedder_config = emb_cfg;
  rc.embedder_weights = emb_w;
  rc.device = "cpu";
  rc.steps = 2;
  cfg.preprocess.image_size = 140;  // the Dinos resize to 70 inside the embedder
  cfg.preprocess.pointmap_size = 64;
  cfg.out = out;
  cfg.dtype = torch::kFloat32;
  cfg.batch = 2;
  cfg.cond_mode = cond_mode;
  cfg.inputs_storage = storage;
  return simu::resample::build_pairs(manifest, cfg);
}
std::string build(const std::string& manifest, const std::string& out, const std::string& cond_mode,
                  const std::string& storage, const std::string& emb_cfg, const std::string& emb_w) {
  EXPECT_EQ(build_report(manifest, out, cond_mode, storage, emb_cfg, emb_w).written, 4) << out;
  return out;
}

// The tiny recipe on a cache: 3 steps, micro-batch 2; extra overrides (the embedder keys) appended.
TrainConfig tiny_config(const std::string& cache, const std::string& out_dir, std::vector<std::string> extra = {}) {
  std::vector<std::string> sets{"model.config=" + simu::testing::fixture("ss_generator_small.json"),
                                "model.weights=" + simu::testing::fixture("ss_generator_small.safetensors"),
                                "data.cache=" + cache, "data.global_batch=2", "data.micro_batch=2", "train.steps=3",
                                "run.out_dir=" + out_dir, "run.checkpoint_every=0", "run.progress=false"};
  sets.insert(sets.end(), extra.begin(), extra.end());
  return TrainConfig::load(simu::testing::source_dir() + "/configs/tiny.yaml", sets);
}

// Trains 3 steps on a cache (same seeds every time); returns the adapter tensors.
std::map<std::string, torch::Tensor> train(const TrainConfig& cfg) {
  torch::manual_seed(5);
  auto policy = make_generator_policy(cfg, torch::kCPU);
  auto comm = Communicator::create(DistEnv{}, torch::kCPU, std::chrono::milliseconds(60000));
  Trainer trainer(cfg, *policy, pair_cache_source(cfg.data.cache, 2), *comm, torch::kCPU);
  attach_condition_embedder(trainer, cfg, torch::kCPU);
  for (int s = 0; s < cfg.train.steps; ++s) trainer.step();
  return trainer.checkpoint_data().adapter;
}

bool all_equal(const std::map<std::string, torch::Tensor>& a, const std::map<std::string, torch::Tensor>& b) {
  if (a.size() != b.size()) return false;
  for (const auto& [name, t] : a)
    if (!b.count(name) || !torch::equal(t, b.at(name))) return false;
  return true;
}

}  // namespace

TEST(CondInputs, TokensAndInputsCachesTrainToIdenticalAdapters) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "needs OpenCV to write the image files";
#else
  const auto dir = simu::testing::temp_dir("cond_inputs_parity");
  const auto manifest = write_manifest(dir);
  const auto emb_cfg = embedder_config(dir);
  const auto emb_w = embedder_weights(dir, emb_cfg);
  const auto tokens = build(manifest, dir + "/tokens.h5", "tokens", "exact", emb_cfg, emb_w);
  const auto inputs = build(manifest, dir + "/inputs.h5", "inputs", "exact", emb_cfg, emb_w);
  const auto compact = build(manifest, dir + "/compact.h5", "inputs", "compact", emb_cfg, emb_w);
  ASSERT_EQ(simu::data::validate_cache(inputs).cond_mode, "inputs");
  const auto info = simu::data::PairCacheReader::open(inputs).info();
  EXPECT_EQ(info.input_size, (std::vector<int64_t>{140, 64}));
  EXPECT_EQ(info.cond_shape, simu::data::PairCacheReader::open(tokens).info().cond_shape);
  // The same latents in both caches (the condition differs only in how it is stored).
  EXPECT_TRUE(torch::equal(simu::data::PairCacheReader::open(tokens).read(2).latent_pos,
                           simu::data::PairCacheReader::open(inputs).read(2).latent_pos));
  const std::vector<std::string> emb{"model.embedder_config=" + emb_cfg, "model.embedder_weights=" + emb_w};
  const auto a_tokens = train(tiny_config(tokens, dir + "/run_tokens"));
  const auto a_inputs = train(tiny_config(inputs, dir + "/run_inputs", emb));
  const auto a_compact = train(tiny_config(compact, dir + "/run_compact", emb));
  // Training moved the adapters (B starts at zero), and both caches give the same ones bit for bit.
  double moved = 0;
  for (const auto& [name, t] : a_tokens)
    if (name.find("lora_B") != std::string::npos) moved += t.abs().sum().item<double>();
  EXPECT_GT(moved, 0);
  EXPECT_TRUE(all_equal(a_tokens, a_inputs)) << "tokens-mode and inputs-mode adapters differ";
  EXPECT_FALSE(all_equal(a_tokens, a_compact)) << "compact (rounded) inputs should change the adapters";
#endif
}

TEST(CondInputs, BuildPairsSkipsARecordTheInputsStorageRefuses) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "needs OpenCV to write the image files";
#else
  const auto dir = simu::testing::temp_dir("cond_inputs_refused");
  const auto manifest = write_manifest(dir);
  // Record 0's modal mask as a 16-bit PNG: its levels k/65535 are not 8-bit levels k/255.
  cv::Mat m16 = cv::imread(dir + "/r0_mask.png", cv::IMREAD_UNCHANGED);
  m16.convertTo(m16, CV_16U, 40000.0 / 255.0);
  ASSERT_TRUE(cv::imwrite(dir + "/r0_mask.png", m16));
  const auto emb_cfg = embedder_config(dir);
  const auto report = build_report(manifest, dir + "/inputs.h5", "inputs", "exact", emb_cfg, embedder_weights(dir, emb_cfg));
  EXPECT_EQ(report.written, 3);
  ASSERT_EQ(report.issues.size(), 1u);
  EXPECT_EQ(report.issues[0].id, "occ0");
  EXPECT_NE(report.issues[0].message.find("not an 8-bit level"), std::string::npos) << report.issues[0].message;
  EXPECT_EQ(simu::data::validate_cache(dir + "/inputs.h5").size, 3);
#endif
}

TEST(CondInputs, EmbedderConfigIsRequiredAndMustMatchTheCache) {
  const auto dir = simu::testing::temp_dir("cond_inputs_errors");
  const auto emb_cfg = embedder_config(dir);
  simu::models::CondEmbedder emb(simu::models::CondEmbedderConfig::load(emb_cfg));
  const std::vector<int64_t> tokens{emb->num_tokens(), emb->embed_dims()};
  auto layout = simu::data::InputsLayout::storage_named("exact", 28, 16);
  simu::data::make_synthetic_inputs_cache(dir + "/c.h5", 2, {64, 8}, tokens, layout, 0, torch::kFloat32);
  simu::data::make_synthetic_inputs_cache(dir + "/other.h5", 2, {64, 8}, {tokens[0] + 1, tokens[1]}, layout, 0,
                                          torch::kFloat32);
  const auto info = simu::data::PairCacheReader::open(dir + "/c.h5").info();
  // No model.embedder_config: named, with the file.
  const auto e1 = error_of([&] { load_condition_embedder(tiny_config(dir + "/c.h5", dir + "/r"), info, torch::kCPU); });
  EXPECT_NE(e1.find("'model.embedder_config' is missing"), std::string::npos) << e1;
  EXPECT_NE(e1.find("tiny.yaml"), std::string::npos) << e1;
  // An embedder that makes other tokens than the cache was built for.
  const auto other = simu::data::PairCacheReader::open(dir + "/other.h5").info();
  const auto e2 = error_of([&] {
    load_condition_embedder(tiny_config(dir + "/other.h5", dir + "/r", {"model.embedder_config=" + emb_cfg}), other,
                            torch::kCPU);
  });
  EXPECT_NE(e2.find("was built for"), std::string::npos) << e2;
  // The matching one loads (random weights: model.weights is the generator's file, so name none).
  auto ok = load_condition_embedder(
      tiny_config(dir + "/c.h5", dir + "/r", {"model.embedder_config=" + emb_cfg, "model.weights=''"}), info, torch::kCPU);
  EXPECT_EQ(ok->num_tokens(), tokens[0]);
  // Inputs-mode pairs reach a trainer without an embedder: an error naming the missing key.
  auto cfg = tiny_config(dir + "/c.h5", dir + "/r");
  torch::manual_seed(5);
  auto policy = make_generator_policy(cfg, torch::kCPU);
  auto comm = Communicator::create(DistEnv{}, torch::kCPU, std::chrono::milliseconds(60000));
  Trainer trainer(cfg, *policy, pair_cache_source(cfg.data.cache, 2), *comm, torch::kCPU);
  const auto e3 = error_of([&] { trainer.step(); });
  EXPECT_NE(e3.find("no condition embedder is loaded"), std::string::npos) << e3;
}
