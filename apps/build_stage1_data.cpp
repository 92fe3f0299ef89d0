// build_stage1_data: the stage-1 sample cache (docs/stage1_cache.md) from world scenes. Per scene of a
// split: render (world::make_scene), corrupt the point map as a monocular estimator would (on by
// default; --clean keeps it exact), and per usable object the released preprocessing at the
// miniature's sizes (condition inputs, ObjectCentricSSI scale / shift), the filled occupancy of its
// canonical mesh, and its pose latents in SAM 3D's convention. Scenes run in parallel; samples are
// written in scene order, so a file is a function of its arguments.
//   build_stage1_data --out data/stage1.h5 --train 25000 --val 500 --threads 16
#include <ATen/Parallel.h>
#include <fmt/format.h>

#include <map>
#include <mutex>

#include "common/source_dir.h"
#include "common/cli.h"
#include "common/config.h"
#include "common/error.h"
#include "common/log.h"
#include "common/parallel.h"
#include "common/progress.h"
#include "data/preprocess.h"
#include "data/stage1_cache.h"
#include "models/pose.h"
#include "pipeline/world/corrupt.h"
#include "pipeline/world/scene.h"
#include "pipeline/world/voxelize.h"

namespace {

using namespace simu;

struct Options {
  std::string out, preprocess = simu::source_dir() + "/configs/miniature/preprocess.yaml", scene_config;
  int64_t counts[3] = {0, 0, 0};  // scenes per split
  uint64_t seed = 0;
  int resolution = 32, threads = 1;
  std::string storage = "compact";
  bool clean = false;
};

// One sample's pose latents (ScaleShiftInvariant, models::encode_pose) from its pose in the OpenCV
// camera frame (p = R (scale .* c) + t, canonical c = the official voxel frame) and the preprocessing's
// scene scale / shift. SAM 3D reads points in the PyTorch3D camera frame, D = diag(-1, -1, 1) of the
// OpenCV one: its pose is (D R, scale, D t).
std::map<std::string, torch::Tensor> pose_latents(const world::Mat3& R_cam, double size_m, const world::Vec3& t_cam,
                                                  const torch::Tensor& scene_scale, const torch::Tensor& scene_shift) {
  const world::Mat3 D = world::Vec3(-1, -1, 1).asDiagonal();
  const world::Mat3 R = D * R_cam;
  const world::Vec3 t = D * t_cam;
  models::InstancePose pose;
  pose.rotation = torch::empty({1, 3, 3}, torch::kFloat64);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) pose.rotation[0][i][j] = R(i, j);
  pose.rotation = pose.rotation.to(torch::kFloat32);
  pose.translation = torch::tensor({t.x(), t.y(), t.z()}, torch::kFloat32).unsqueeze(0);
  pose.scale = torch::full({1, 3}, size_m, torch::kFloat32);
  models::PoseDecodeOptions o;
  o.scene_scale = scene_scale[0].item<double>();
  o.scene_shift = {scene_shift[0].item<double>(), scene_shift[1].item<double>(), scene_shift[2].item<double>()};
  std::map<std::string, torch::Tensor> out;
  for (const auto& [name, v] : models::encode_pose(pose, o)) out[name] = v[0];
  return out;
}

// The samples of one scene (usable objects whose preprocessing succeeds), and how many failed.
struct SceneSamples {
  std::vector<data::Stage1Record> records;
  int failed = 0;
};

SceneSamples scene_samples(const world::SceneConfig& cfg, const world::CorruptionConfig& corruption, const Options& o,
                           const data::PreprocessConfig& pre, uint64_t seed, world::Split split) {
  const world::WorldScene s = world::make_scene(cfg, seed, split);
  const int H = s.camera.height, W = s.camera.width;
  const world::PointMap pm = o.clean ? s.pointmap : world::corrupt_pointmap(s.pointmap, corruption, seed);
  const auto rgb = torch::from_blob(const_cast<uint8_t*>(s.rgb.data()), {H, W, 3}, torch::kByte)
                       .permute({2, 0, 1})
                       .to(torch::kFloat32)
                       .div(255.0);  // [3, H, W]
  const auto xyz = torch::from_blob(const_cast<float*>(pm.xyz.data()), {H, W, 3}, torch::kFloat32).permute({2, 0, 1});
  const auto points = data::pointmap_from_opencv_camera(xyz.contiguous());  // [3, H, W], PyTorch3D camera frame
  SceneSamples out;
  for (const auto& obj : s.objects) {
    if (!obj.usable) continue;
    auto mask = torch::from_blob(const_cast<uint8_t*>(obj.modal.data.data()), {H, W}, torch::kByte).to(torch::kFloat32);
    data::ConditionInputs in;
    try {
      in = data::prepare_condition_inputs(rgb, mask, points, pre);
    } catch (const Error& e) {
      log::debug("{} {}: skipped: {}", s.name, obj.id, e.what());
      ++out.failed;
      continue;
    }
    data::Stage1Record r;
    r.id = s.name + "/" + obj.id;
    for (const auto& [name, t] : in.tensors) r.inputs[name] = t[0];
    const auto grid = world::voxelize_filled(obj.shape.mesh, o.resolution);
    r.occupancy = torch::from_blob(const_cast<uint8_t*>(grid.data()), {o.resolution, o.resolution, o.resolution}, torch::kByte).clone();
    r.pointmap_scale = in.pointmap_scale.to(torch::kFloat32);
    r.pointmap_shift = in.pointmap_shift.to(torch::kFloat32);
    r.pose = pose_latents(obj.R_cam, obj.shape.size_m, obj.t_cam, in.pointmap_scale, in.pointmap_shift);
    r.family = obj.shape.family;
    r.split = static_cast<data::SampleSplit>(static_cast<int>(split));
    r.visible_fraction = static_cast<float>(obj.visible_fraction);
    out.records.push_back(std::move(r));
  }
  return out;
}

void build(const Options& o, const std::vector<std::string>& sets) {
  world::SceneConfig cfg;
  world::CorruptionConfig corruption;
  if (!o.scene_config.empty() || !sets.empty()) {
    const YAML::Node root = o.scene_config.empty() ? config::load_text("{}", "--set", sets) : config::load_file(o.scene_config, sets);
    config::Reader r(root, o.scene_config.empty() ? "--set" : o.scene_config);
    auto sc = r.child("scene");
    cfg = world::SceneConfig::from(sc);
    auto cc = r.child("corruption");
    corruption = world::CorruptionConfig::from(cc);
    r.finish();
  }
  config::Reader pr(config::load_file(o.preprocess), o.preprocess);
  const auto pre = data::PreprocessConfig::from(pr);
  pr.finish();
  SIMU_CHECK(pre.pointmap_size > 0, "{}: pointmap_size must be set (the cache stores point maps of one size)", o.preprocess);
  // Scene seeds: the first counts[split] seeds of each split from --seed on, train then val then test.
  std::vector<std::pair<uint64_t, world::Split>> scenes;
  for (int k = 0; k < 3; ++k) {
    const auto split = static_cast<world::Split>(k);
    uint64_t seed = o.seed;
    for (int64_t n = 0; n < o.counts[k]; ++n, ++seed) {
      seed = world::next_scene_seed(split, seed);
      scenes.emplace_back(seed, split);
    }
  }
  SIMU_CHECK(!scenes.empty(), "no scenes asked for: give --train, --val and/or --test counts");
  data::Stage1CacheWriter writer(o.out, data::InputsLayout::storage_named(o.storage, pre.image_size, pre.pointmap_size),
                                 o.resolution, "ScaleShiftInvariant");
  writer.set_created_by(fmt::format("build_stage1_data --train {} --val {} --test {} --seed {} --resolution {} --storage {}{} "
                                    "--preprocess {}", o.counts[0], o.counts[1], o.counts[2], o.seed, o.resolution,
                                    o.storage, o.clean ? " --clean" : "", o.preprocess));
  if (o.threads > 1) at::set_num_threads(1);  // one torch thread per scene worker
  // Scenes in parallel; their samples are appended in scene order.
  std::mutex mu;
  std::map<int64_t, SceneSamples> finished;
  int64_t next = 0, failed = 0;
  Progress progress{"build_stage1_data", "scenes"};
  parallel_for_each(static_cast<int64_t>(scenes.size()), o.threads, [&](int64_t k) {
    auto samples = scene_samples(cfg, corruption, o, pre, scenes[k].first, scenes[k].second);
    std::lock_guard<std::mutex> lock(mu);
    finished[k] = std::move(samples);
    for (auto it = finished.find(next); it != finished.end(); it = finished.find(next)) {
      for (const auto& r : it->second.records) writer.append(r);
      failed += it->second.failed;
      finished.erase(it);
      progress(++next, static_cast<int64_t>(scenes.size()));
    }
  });
  writer.finish();
  fmt::print("wrote {} samples of {} scenes to {} ({} objects skipped: preprocessing failed)\n", writer.size(),
             scenes.size(), o.out, failed);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"build_stage1_data: the stage-1 sample cache (condition inputs, occupancy, pose latents) from world scenes"};
  Options o;
  app.add_option("--out", o.out, "the cache to write (.h5; replaced atomically when it exists)")->required();
  app.add_option("--train", o.counts[0], "train scenes")->capture_default_str();
  app.add_option("--val", o.counts[1], "validation scenes")->capture_default_str();
  app.add_option("--test", o.counts[2], "test scenes")->capture_default_str();
  app.add_option("--seed", o.seed, "first scene seed looked at (each split takes its own seeds from here)")->capture_default_str();
  app.add_option("--preprocess", o.preprocess, "preprocessing config (data::PreprocessConfig keys)")->capture_default_str();
  app.add_option("--resolution", o.resolution, "occupancy side R")->capture_default_str()->check(CLI::Range(2, 256));
  app.add_option("--storage", o.storage, "condition-input storage: compact (uint8 images, float16 point maps) | exact")
      ->capture_default_str()
      ->check(CLI::IsMember({"compact", "exact"}));
  app.add_option("--scene-config", o.scene_config, "YAML with scene: (world::SceneConfig) and corruption: sections");
  app.add_flag("--clean", o.clean, "keep the clean point maps (default: corrupted as a monocular estimator would)");
  app.add_option("--threads", o.threads, "scenes built in parallel")->capture_default_str()->check(CLI::PositiveNumber);
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    build(o, common.sets);
    return 0;
  });
}
