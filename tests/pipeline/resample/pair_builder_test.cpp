// build_pairs (resample/pair_builder.h) on generated image pairs with the small fixture generator and
// the small demo embedder: the cache validates, holds the right kinds/weights/shapes, its condition
// tokens and latents equal what the embedder / generator give when called directly on the record's
// files, bad records are reported with their manifest line and skipped, a second run resumes, and the
// trainer trains on the result.
#include <ATen/CPUGeneratorImpl.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "common/error.h"
#include "common/fs.h"
#include "data/pair_cache.h"
#include "data/preprocess.h"
#include "data/safetensors.h"
#include "models/cond_embedder.h"
#include "pipeline/resample/pair_builder.h"
#include "flow_rounding.h"
#include "test_util.h"
#include "training/generator_policy.h"
#include "training/trainer.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

using namespace simu::physics;
using namespace simu::resample;

namespace {

constexpr int H = 40, W = 48;

// The demo's small embedder (configs/demo_embedder_small.json) with the image ViT at 70 px instead of
// 518 (5x5 patches, like the mask ViT) so the test takes seconds; written once per process.
std::string embedder_config() {
  static const std::string path = [] {
    auto j = nlohmann::json::parse(simu::fs::read_file(simu::testing::source_dir() + "/configs/demo_embedder_small.json"));
    j["dino_image_input_size"] = 70;
    const std::string p = simu::testing::temp_dir("pair_builder_cfg") + "/embedder.json";
    simu::fs::atomic_write(p, j.dump(1));
    return p;
  }();
  return path;
}

ResamplerConfig small_models(const std::string& embedder_weights) {
  ResamplerConfig c;
  c.generator_config = simu::testing::fixture("ss_generator_small.json");
  c.generator_weights = simu::testing::fixture("ss_generator_small.safetensors");
  c.decoder_config = simu::testing::fixture("ss_decoder_small.json");
  c.decoder_weights = simu::testing::fixture("ss_decoder_small.safetensors");
  c.embedder_config = embedder_config();
  c.embedder_weights = embedder_weights;
  c.random_weights = embedder_weights.empty();
  c.device = "cpu";
  c.steps = 2;  // official defaults otherwise (rescale_t 3, CFG 7 on [0, 500])
  c.num_samples = 1;
  return c;
}

#ifdef SIMU_HAVE_OPENCV
// Float images [H, W, 3] in [0, 1] (RGB) and masks [H, W] in {0, 1} as 8-bit PNGs.
void write_rgb(const std::string& path, const torch::Tensor& rgb) {
  auto bgr = (rgb.flip({2}) * 255).round().clamp(0, 255).to(torch::kUInt8).contiguous();
  cv::Mat m(H, W, CV_8UC3, bgr.data_ptr<uint8_t>());
  ASSERT_TRUE(cv::imwrite(path, m)) << path;
}
void write_mask(const std::string& path, const torch::Tensor& mask) {
  auto u8 = (mask * 255).to(torch::kUInt8).contiguous();
  cv::Mat m(static_cast<int>(mask.size(0)), static_cast<int>(mask.size(1)), CV_8UC1, u8.data_ptr<uint8_t>());
  ASSERT_TRUE(cv::imwrite(path, m)) << path;
}
// Axis-aligned box mask [y0, y1) x [x0, x1).
torch::Tensor box(int y0, int y1, int x0, int x1) {
  auto m = torch::zeros({H, W});
  m.slice(0, y0, y1).slice(1, x0, x1).fill_(1);
  return m;
}
// Pastes a colour with a little texture into img where mask is set.
torch::Tensor paint(const torch::Tensor& img, const torch::Tensor& mask, std::vector<float> colour, int seed) {
  auto g = at::make_generator<at::CPUGeneratorImpl>(seed);
  auto tex = torch::rand({H, W, 3}, g) * 0.2 + torch::tensor(colour).view({1, 1, 3}) * 0.8;
  return torch::where(mask.unsqueeze(2) > 0, tex, img);
}
torch::Tensor background(int seed) {
  auto g = at::make_generator<at::CPUGeneratorImpl>(seed);
  return torch::rand({H, W, 3}, g) * 0.3 + 0.3;
}

// An occlusion-completion pair i: target box, a second box occluding its lower part.
void write_occlusion_pair(const std::string& dir, int i) {
  const auto target = box(8 + i, 32 + i, 10 + 2 * i, 30 + 2 * i);
  const auto occluder = box(22 + i, 40, 4, 40);
  const auto bg = background(100 + i);
  const auto full = paint(bg, target, {0.9f, 0.2f, 0.1f}, 200 + i);
  const auto occluded = paint(full, occluder, {0.1f, 0.3f, 0.9f}, 300 + i);
  const std::string p = fmt::format("{}/occ{}_", dir, i);
  write_rgb(p + "image.png", occluded);
  write_mask(p + "modal.png", target * (1 - occluder));
  write_rgb(p + "edited.png", full);
  write_mask(p + "full.png", target);
}
// A clean-preservation pair i: one unoccluded box; the corrupted mask drops its right half.
void write_clean_pair(const std::string& dir, int i) {
  const auto object = box(6 + i, 30 + i, 8 + i, 36 + i);
  const auto img = paint(background(400 + i), object, {0.2f, 0.8f, 0.3f}, 500 + i);
  const std::string p = fmt::format("{}/clean{}_", dir, i);
  write_rgb(p + "image.png", img);
  write_mask(p + "mask.png", object);
  write_mask(p + "corrupted.png", object * box(0, H, 0, 22 + i));
}
std::string occ_line(const std::string& id, int i, const std::string& extra = "") {
  return fmt::format(R"({{"id": "{}", "kind": "occlusion_completion", "image": "occ{}_image.png", "mask": "occ{}_modal.png", "full_image": "occ{}_edited.png", "full_mask": "occ{}_full.png"{}}})",
                     id, i, i, i, i, extra);
}
std::string clean_line(const std::string& id, int i, const std::string& mask = "") {
  return fmt::format(R"({{"id": "{}", "kind": "clean_preservation", "image": "clean{}_image.png", "mask": "{}", "corrupted_mask": "clean{}_corrupted.png"}})",
                     id, i, mask.empty() ? fmt::format("clean{}_mask.png", i) : mask, i);
}
#endif

// The independent definition of the default point map: pinhole, 60 deg horizontal FOV, plane z = 1,
// PyTorch3D axes (x left, y up).
torch::Tensor plane_pointmap(int h, int w) {
  auto pm = torch::empty({3, h, w});
  const double f = (w / 2.0) / std::tan(M_PI / 6);
  for (int v = 0; v < h; ++v)
    for (int u = 0; u < w; ++u) {
      pm[0][v][u] = -((u + 0.5) - w / 2.0) / f;
      pm[1][v][u] = -((v + 0.5) - h / 2.0) / f;
      pm[2][v][u] = 1.0;
    }
  return pm;
}

}  // namespace

TEST(PairBuilder, DefaultPointmapIsTheDocumentedPlane) {
  // Both in float64 (a handful of operations on values <= 1), each rounded once to fp32.
  EXPECT_TRUE(simu::testing::close(default_pointmap(7, 10), plane_pointmap(7, 10), simu::testing::two_paths(1) +
                                       simu::testing::gamma(8, simu::testing::kFp64Unit), "default point map"));
  // Left of the image is +x (PyTorch3D: x left), top is +y.
  const auto pm = default_pointmap(7, 10);
  EXPECT_GT(pm[0][3][0].item<float>(), 0);
  EXPECT_GT(pm[1][0][5].item<float>(), 0);
}

TEST(PairBuilder, ManifestLineParsing) {
  const auto r = parse_manifest_line(
      R"({"id": "a", "kind": "occlusion_completion", "image": "i.png", "mask": "/abs/m.png", "full_image": "f.png", "full_mask": "fm.png"})",
      "/data/set");
  EXPECT_EQ(r.id, "a");
  EXPECT_EQ(r.kind, simu::data::PairKind::OcclusionCompletion);
  EXPECT_FLOAT_EQ(r.weight, 1.0f);
  EXPECT_EQ(r.image, "/data/set/i.png");
  EXPECT_EQ(r.mask, "/abs/m.png");
  const auto c = parse_manifest_line(
      R"({"id": "b", "kind": "clean_preservation", "image": "i.png", "mask": "m.png", "corrupted_mask": "c.png", "weight": 0.5})",
      "");
  EXPECT_FLOAT_EQ(c.weight, 0.5f);
  EXPECT_EQ(c.corrupted_mask, "c.png");
  // Errors say what is wrong.
  auto error_of = [](const std::string& line) {
    try {
      parse_manifest_line(line, "");
    } catch (const simu::Error& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(error_of("{nope").find("not valid JSON"), std::string::npos);
  EXPECT_NE(error_of(R"({"id": "x", "kind": "other"})").find("'kind' must be"), std::string::npos);
  EXPECT_NE(error_of(R"({"id": "x", "kind": "clean_preservation", "image": "i", "mask": "m"})").find("corrupted_mask"),
            std::string::npos);
  EXPECT_NE(error_of(R"({"id": "x", "kind": "clean_preservation", "imgae": "i"})").find("unknown key 'imgae'"),
            std::string::npos);
  EXPECT_NE(error_of(R"({"id": "x", "kind": "clean_preservation", "image": "i", "mask": "m", "corrupted_mask": "c", "weight": -1})")
                .find("weight"),
            std::string::npos);
}

// A whole manifest: comments, blank lines, CRLF, a bad line and a duplicate id become issues with
// their line numbers; good records keep theirs.
TEST(PairBuilder, ManifestParsingKeepsLineNumbers) {
  const std::string ok = R"({"id": "a", "kind": "clean_preservation", "image": "i.png", "mask": "m.png", "corrupted_mask": "c.png"})";
  const std::string text = "# comment\r\n" + ok + "\r\n\n  \t\n{nope\n" + ok + "\n" +
                           R"({"id": "b", "kind": "clean_preservation", "image": "i.png", "mask": "m.png", "corrupted_mask": "c.png"})";
  const auto m = parse_manifest(text, "/d");
  EXPECT_EQ(m.records, 4);
  ASSERT_EQ(m.pairs.size(), 2u);
  EXPECT_EQ(m.pairs[0].line, 2);
  EXPECT_EQ(m.pairs[0].image, "/d/i.png");
  EXPECT_EQ(m.pairs[1].line, 7);
  ASSERT_EQ(m.issues.size(), 2u);
  EXPECT_EQ(m.issues[0].line, 5);
  EXPECT_NE(m.issues[0].message.find("not valid JSON"), std::string::npos);
  EXPECT_EQ(m.issues[1].line, 6);
  // A weight that is finite as a double but not as the cache's float32.
  const auto big = parse_manifest(R"({"id": "w", "kind": "clean_preservation", "image": "i", "mask": "m", "corrupted_mask": "c", "weight": 1e300})", "");
  ASSERT_EQ(big.issues.size(), 1u);
  EXPECT_NE(big.issues[0].message.find("'weight' must be finite"), std::string::npos);
  EXPECT_NE(m.issues[1].message.find("duplicate id (first on line 2)"), std::string::npos);
}

TEST(PairBuilder, BuildsValidatesResumesAndTrains) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "the test writes its image pairs as PNGs, which needs OpenCV (built with SIMU_WITH_OPENCV=OFF)";
#else
  const std::string dir = simu::testing::temp_dir("pair_builder");
  // Embedder weights: the demo config's random init, saved so the builder and the test load the same.
  const std::string emb_weights = dir + "/embedder.safetensors";
  {
    torch::manual_seed(3);
    simu::models::CondEmbedder emb(simu::models::CondEmbedderConfig::load(embedder_config()));
    std::map<std::string, torch::Tensor> tensors;
    for (const auto& p : emb->named_parameters()) tensors[p.key()] = p.value().detach().clone();
    for (const auto& b : emb->named_buffers()) tensors[b.key()] = b.value().detach().clone();
    simu::data::save_safetensors(emb_weights, tensors);
  }
  // Images: two occlusion pairs, three clean pairs; a tilted-plane point map for occ-0.
  for (int i = 0; i < 2; ++i) write_occlusion_pair(dir, i);
  for (int i = 0; i < 3; ++i) write_clean_pair(dir, i);
  write_mask(dir + "/small_mask.png", torch::ones({20, 20}));
  write_mask(dir + "/empty_mask.png", torch::zeros({H, W}));
  auto tilted = plane_pointmap(H, W);
  tilted[2] += tilted[0] * 0.5 + 0.3;  // depth varies across the image
  simu::data::save_safetensors(dir + "/occ0_points.safetensors",
                               std::map<std::string, torch::Tensor>{{"pointmap", tilted.permute({1, 2, 0}).contiguous()}});
  // Manifest: good records, bad ones (missing file, size mismatch, empty mask, bad JSON, duplicate id).
  const std::vector<std::string> lines = {
      "# generated by pair_builder_test",                                                     // 1
      occ_line("occ-0", 0, R"(, "pointmap": "occ0_points.safetensors")"),                     // 2
      clean_line("clean-0", 0),                                                               // 3
      occ_line("occ-1", 1),                                                                   // 4
      "",                                                                                     // 5
      R"({"id": "missing", "kind": "occlusion_completion", "image": "nope.png", "mask": "occ0_modal.png", "full_image": "occ0_edited.png", "full_mask": "occ0_full.png"})",  // 6
      clean_line("size-mismatch", 0, "small_mask.png"),                                       // 7
      clean_line("empty-mask", 1, "empty_mask.png"),                                          // 8
      clean_line("clean-1", 1),                                                               // 9
      "{not json",                                                                            // 10
      clean_line("occ-0", 1),                                                                 // 11 duplicate id
  };
  const std::string manifest = dir + "/manifest.jsonl";
  {
    std::ofstream f(manifest);
    for (const auto& l : lines) f << l << "\n";
  }
  PairBuilderConfig cfg;
  cfg.resampler = small_models(emb_weights);
  cfg.out = dir + "/pairs.h5";
  cfg.dtype = torch::kFloat32;
  cfg.batch = 3;
  cfg.seed = 5;
  cfg.commit_every = 2;
  Resampler rs(cfg.resampler);
  std::vector<std::pair<int64_t, int64_t>> progress_calls;
  auto progress = [&](int64_t d, int64_t t) { progress_calls.push_back({d, t}); };

  // First run: 4 pairs written, 5 bad records reported with their lines.
  const auto rep = build_pairs(manifest, cfg, rs, progress);
  EXPECT_EQ(rep.records, 9);
  EXPECT_EQ(rep.written, 4);
  EXPECT_EQ(rep.skipped_existing, 0);
  EXPECT_EQ(rep.cache_size, 4);
  EXPECT_FALSE(rep.interrupted);
  ASSERT_EQ(rep.issues.size(), 5u);
  const std::vector<std::pair<int64_t, std::string>> want_issues = {
      {6, "file not found"}, {7, "is 20x20"}, {8, "is empty"}, {10, "not valid JSON"}, {11, "duplicate id (first on line 2)"}};
  for (size_t i = 0; i < want_issues.size(); ++i) {
    EXPECT_EQ(rep.issues[i].line, want_issues[i].first);
    EXPECT_NE(rep.issues[i].message.find(want_issues[i].second), std::string::npos) << rep.issues[i].message;
  }
  ASSERT_FALSE(progress_calls.empty());
  EXPECT_EQ(progress_calls.back(), (std::pair<int64_t, int64_t>{9, 9}));

  // The same validation as `pairs validate`, counts, kinds, weights, shapes.
  const auto info = simu::data::validate_cache(cfg.out);
  const int64_t L = rs.embedder()->num_tokens();
  EXPECT_EQ(info.size, 4);
  EXPECT_EQ(info.counts[0], 2);
  EXPECT_EQ(info.counts[1], 2);
  const auto& shape = rs.generator()->config().backbone.latent("shape");
  EXPECT_EQ(info.latent_shape, (std::vector<int64_t>{shape.tokens(), shape.in_channels}));
  EXPECT_EQ(info.cond_shape, (std::vector<int64_t>{L, rs.generator()->config().backbone.cond_channels}));
  EXPECT_EQ(info.cond_mode, "tokens");
  EXPECT_EQ(info.latent_dtype, "float32");
  const auto reader = simu::data::PairCacheReader::open(cfg.out);
  std::map<std::string, simu::data::PairRecord> by_id;
  for (int64_t i = 0; i < reader.size(); ++i) {
    auto r = reader.read(i);
    by_id[r.id] = r;
  }
  ASSERT_EQ(by_id.size(), 4u);
  for (const char* id : {"occ-0", "occ-1"}) {
    EXPECT_EQ(by_id.at(id).kind, simu::data::PairKind::OcclusionCompletion);
    EXPECT_FLOAT_EQ(by_id.at(id).weight, 1.0f);
  }
  for (const char* id : {"clean-0", "clean-1"}) {
    EXPECT_EQ(by_id.at(id).kind, simu::data::PairKind::CleanPreservation);
    EXPECT_FLOAT_EQ(by_id.at(id).weight, 0.1f);
  }

  // Independent path: read the files, official preprocessing, an embedder loaded separately.
  auto emb = simu::models::load_cond_embedder(embedder_config(), emb_weights, "auto", torch::kCPU);
  auto embed = [&](const std::string& image, const std::string& mask, const torch::Tensor& pointmap,
                   const std::string& crop_mask = "") {
    torch::NoGradGuard no_grad;
    const auto rgb = simu::data::read_image_rgb(dir + "/" + image);
    const auto m = simu::data::read_mask(dir + "/" + mask);
    const auto crop = crop_mask.empty() ? torch::Tensor() : simu::data::read_mask(dir + "/" + crop_mask);
    return emb->forward(simu::data::prepare_condition_inputs(rgb, m, pointmap, {}, crop).tensors)[0];  // [L, C]
  };
  const auto plane = plane_pointmap(H, W);
  // occ-0: c = (I, M, I_M', D) with its point map file; differs from the plain occluded input.
  const auto c_occ = embed("occ0_image.png", "occ0_modal.png", tilted, "occ0_full.png");
  const auto c_occluded = embed("occ0_image.png", "occ0_modal.png", tilted);
  const auto c_edited = embed("occ0_edited.png", "occ0_full.png", tilted);
  // The builder's batched embedder and this one: two fp32 evaluations (flow_rounding.h).
  const double cond_tol = simu::testing::two_paths(
      simu::testing::embedder_chain(simu::models::CondEmbedderConfig::load(embedder_config())));
  EXPECT_TRUE(simu::testing::close(by_id.at("occ-0").cond, c_occ, cond_tol, "occ-0 stored condition"));
  EXPECT_GT(simu::testing::rel_err(c_occluded, c_occ), cond_tol) << "the crop box must come from the full mask";
  // occ-1 and clean-1: default point map; clean pairs store the clean input's condition.
  EXPECT_TRUE(simu::testing::close(by_id.at("occ-1").cond,
                                   embed("occ1_image.png", "occ1_modal.png", plane, "occ1_full.png"), cond_tol,
                                   "occ-1 stored condition"));
  const auto c_clean = embed("clean1_image.png", "clean1_mask.png", plane);
  const auto c_corrupt = embed("clean1_image.png", "clean1_corrupted.png", plane);
  EXPECT_TRUE(simu::testing::close(by_id.at("clean-1").cond, c_clean, cond_tol, "clean-1 stored condition"));

  // Latents: Stage 1 on each side from the pair's noise (x- = occluded / corrupted, x+ = edited / clean).
  auto sample = [&](const torch::Tensor& cond, const std::string& id) {
    auto g = at::make_generator<at::CPUGeneratorImpl>(pair_noise_seed(cfg.seed, id));
    const auto x0 = rs.generator()->noise(1, g, torch::kCPU);
    return rs.generator()->sample(cond.unsqueeze(0), x0, rs.sample_options()).at("shape")[0];
  };
  // Conditions within cond_tol move the samples by as much (first order, gain ~1 through normalised
  // layers), plus two runs of the guided sampler (batched in the builder, one here).
  const double lat_tol = cond_tol + simu::testing::flow_sample_bound(rs.generator()->config().backbone, L,
                                                                    rs.sample_options().cfg_strength);
  EXPECT_TRUE(simu::testing::close(by_id.at("occ-0").latent_neg, sample(c_occluded, "occ-0"), lat_tol, "occ-0 x-"));
  EXPECT_TRUE(simu::testing::close(by_id.at("occ-0").latent_pos, sample(c_edited, "occ-0"), lat_tol, "occ-0 x+"));
  EXPECT_TRUE(simu::testing::close(by_id.at("clean-1").latent_pos, sample(c_clean, "clean-1"), lat_tol, "clean-1 x+"));
  EXPECT_TRUE(simu::testing::close(by_id.at("clean-1").latent_neg, sample(c_corrupt, "clean-1"), lat_tol, "clean-1 x-"));

  // Second run: resumes, writes nothing, leaves the file as it was; bad records reported again.
  const std::string bytes_before = simu::fs::read_file(cfg.out);
  const auto rep2 = build_pairs(manifest, cfg, rs);
  EXPECT_EQ(rep2.written, 0);
  EXPECT_EQ(rep2.skipped_existing, 4);
  EXPECT_EQ(rep2.issues.size(), 5u);
  EXPECT_EQ(rep2.cache_size, 4);
  EXPECT_TRUE(simu::fs::read_file(cfg.out) == bytes_before) << "a run with nothing new rewrote the cache";
  // A manifest with one more record: only that one is built and appended.
  {
    std::ofstream f(manifest, std::ios::app);
    f << clean_line("clean-2", 2) << "\n";
  }
  const auto rep3 = build_pairs(manifest, cfg, rs);
  EXPECT_EQ(rep3.written, 1);
  EXPECT_EQ(rep3.skipped_existing, 4);
  EXPECT_EQ(rep3.cache_size, 5);
  const auto info3 = simu::data::validate_cache(cfg.out);
  EXPECT_EQ(info3.counts[1], 3);
  // Appending leaves the stored record's bytes as they were: bit for bit.
  EXPECT_TRUE(simu::testing::close(simu::data::PairCacheReader::open(cfg.out).read(0).cond, reader.read(0).cond, 0,
                                   "resumed record 0 unchanged"));
  // Nothing temporary left behind.
  for (const auto& e : std::filesystem::directory_iterator(dir))
    EXPECT_EQ(e.path().filename().string().find("pairs.h5.tmp"), std::string::npos) << e.path();

  // The trainer trains on it: small generator + fresh LoRA, two steps over the built cache.
  using namespace simu::training;
  auto tcfg = TrainConfig::load(simu::testing::source_dir() + "/configs/tiny.yaml",
                                {"model.config=" + simu::testing::fixture("ss_generator_small.json"),
                                 "model.weights=" + simu::testing::fixture("ss_generator_small.safetensors"),
                                 "data.cache=" + cfg.out, "data.global_batch=2", "data.micro_batch=1",
                                 "train.steps=2", "run.out_dir=" + dir + "/train", "run.progress=false"});
  auto policy = make_generator_policy(tcfg, torch::kCPU);
  auto comm = Communicator::create(DistEnv{}, torch::kCPU, std::chrono::milliseconds(60000));
  Trainer trainer(tcfg, *policy, pair_cache_source(cfg.out, 2), *comm, torch::kCPU);
  for (int s = 0; s < 2; ++s) {
    const auto m = trainer.step();
    EXPECT_TRUE(std::isfinite(m.loss) && m.loss > 0) << "step " << s << " loss " << m.loss;
    EXPECT_TRUE(std::isfinite(m.grad_norm)) << "step " << s;
  }
  EXPECT_EQ(trainer.steps_done(), 2);
#endif
}
