// world: the procedural shape world of the miniature (docs/world.md).
//   world scenes --split train --count N --seed S --out DIR [--corrupt] [--targets K] [--edited]
//       writes DIR/<split>_<seed>/ per scene: image.png, labels.png, masks/, amodal/, pointmap.npy (the
//       point map `lift --pointmap` reads; corrupted with --corrupt, the clean one beside it),
//       intrinsics.json, gt.json, meshes/; with --edited also edited/<target id>/image.png (the scene
//       with that target's occluders removed).
//   world scenes --objects DIR --out OUT   one test scene per mesh file of DIR (OBJ/PLY/STL/GLB/glTF, any
//       units: normalised to the canonical convention, size read in m / cm / mm), placed first.
//   world pairs --completion N --preservation N --seed S --out DIR [--resolution R] [--clean]
//       FM-DPO preference pairs from train-split scenes (pipeline/world/pairs.h): per scene image.png and
//       pointmap.npy, per pair <object>/ with its masks, the edited image and point map (completion) or
//       the corrupted mask (preservation) and the ground truth's filled occupancy (occupancy.npy, R^3
//       uint8, the stage-1 cache's frame); DIR/manifest.jsonl for `build_pairs --filter-gt`.
//   world shapes [--count N] [--seed S]   a family x split table of N instances per family.
//   world sheet --out FILE [--per-family K] [--cell PX]   a contact sheet of every family.
#include "common/cli.h"
#include "common/config.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/parallel.h"
#include "common/progress.h"
#include "data/depth_io.h"
#include "pipeline/world/corrupt.h"
#include "pipeline/world/pairs.h"
#include "pipeline/world/scene.h"
#include "pipeline/world/scene_io.h"
#include "pipeline/world/shapes.h"
#include "pipeline/physics/overlay.h"
#include "pipeline/world/voxelize.h"

#include <fmt/format.h>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <cctype>
#include <filesystem>
#include <mutex>

using namespace simu::world;

namespace {

// `world scenes` settings.
struct ScenesOptions {
  std::string split = "train", out, config, visible, families, objects;
  int count = 10, threads = 1, targets = -1, width = 0, height = 0;
  uint64_t seed = 0;
  bool corrupt = false, edited = false, overwrite = false;
};

// Writes a point map [H, W, 3] float32 as .npy.
void write_pointmap(const std::string& path, const PointMap& p) {
  const torch::Tensor t = torch::from_blob(const_cast<float*>(p.xyz.data()), {p.height, p.width, 3}, torch::kFloat32);
  simu::data::write_npy(path, t);
}

// Parses "LO-HI" (fractions) into visible_min / visible_max.
void parse_visible(const std::string& s, SceneConfig& cfg) {
  const auto dash = s.find('-');
  try {
    if (dash == std::string::npos) throw std::invalid_argument(s);
    cfg.visible_min = std::stod(s.substr(0, dash));
    cfg.visible_max = std::stod(s.substr(dash + 1));
  } catch (const std::exception&) {
    throw simu::Error(fmt::format("--visible '{}': expected LO-HI, e.g. 0.2-0.6", s));
  }
}

// The `scene:` and `corruption:` sections of --config (YAML/JSON) with the --set edits; defaults when
// neither is given.
void read_world_config(const std::string& config, const std::vector<std::string>& sets, SceneConfig& cfg,
                       CorruptionConfig& ccfg) {
  if (config.empty() && sets.empty()) return;
  const YAML::Node root = config.empty() ? simu::config::load_text("{}", "--set", sets) : simu::config::load_file(config, sets);
  simu::config::Reader r(root, config.empty() ? "--set" : config);
  auto scene = r.child("scene");
  cfg = SceneConfig::from(scene);
  auto corruption = r.child("corruption");
  ccfg = CorruptionConfig::from(corruption);
  r.finish();
}

void run_scenes(const ScenesOptions& o, const std::vector<std::string>& sets) {
  SceneConfig cfg;
  CorruptionConfig ccfg;
  read_world_config(o.config, sets, cfg, ccfg);
  const Split split = parse_split(o.split, "--split");
  if (o.targets >= 0) cfg.targets = o.targets;
  if (!o.visible.empty()) parse_visible(o.visible, cfg);
  if (o.width > 0) cfg.width = o.width;
  if (o.height > 0) cfg.height = o.height;
  if (!o.families.empty()) {
    cfg.families.clear();
    std::string rest = o.families;
    for (size_t at; (at = rest.find(',')) != std::string::npos; rest = rest.substr(at + 1)) cfg.families.push_back(rest.substr(0, at));
    cfg.families.push_back(rest);
  }
  simu::fs::check_overwrite(o.out, o.overwrite, "--out");
  std::filesystem::create_directories(o.out);
  // External meshes (--objects): one test scene each, the mesh placed first.
  std::vector<std::string> meshes;
  if (!o.objects.empty()) {
    SIMU_CHECK(split == Split::Test, "--objects places external meshes in test scenes: use --split test (got {})", o.split);
    SIMU_CHECK(std::filesystem::is_directory(o.objects), "--objects {}: not a folder", o.objects);
    for (const auto& e : std::filesystem::directory_iterator(o.objects)) {
      std::string ext = e.path().extension().string();
      std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return char(std::tolower(c)); });
      if (e.is_regular_file() && (ext == ".obj" || ext == ".ply" || ext == ".stl" || ext == ".glb" || ext == ".gltf"))
        meshes.push_back(e.path().string());
    }
    std::sort(meshes.begin(), meshes.end());
    SIMU_CHECK(!meshes.empty(), "--objects {}: no .obj, .ply, .stl, .glb or .gltf file", o.objects);
  }
  // Scene seeds: the first `count` seeds of the split from --seed on (one per mesh with --objects).
  const int count = meshes.empty() ? o.count : int(meshes.size());
  std::vector<uint64_t> seeds;
  for (uint64_t s = o.seed; int(seeds.size()) < count; ++s) seeds.push_back(s = next_scene_seed(split, s));
  simu::Progress progress{"world scenes", "scenes"};
  std::mutex mu;
  int64_t done = 0;
  simu::parallel_for_each(int64_t(seeds.size()), o.threads, [&](int64_t k) {
    std::vector<ShapeInstance> extra;
    if (!meshes.empty()) extra.push_back(load_external_shape(meshes[size_t(k)]));
    const WorldScene s = make_scene(cfg, seeds[size_t(k)], split, extra);
    const std::string dir = o.out + "/" + (extra.empty() ? s.name : s.name + "_" + extra[0].name);
    CorruptionRecord rec;
    if (o.corrupt) {
      write_pointmap(dir + "/pointmap.npy", corrupt_pointmap(s.pointmap, ccfg, s.seed, &rec));
      write_pointmap(dir + "/pointmap_clean.npy", s.pointmap);
    } else {
      write_pointmap(dir + "/pointmap.npy", s.pointmap);
    }
    write_scene_files(s, dir, o.corrupt ? &rec : nullptr);
    if (o.edited)
      for (const auto& obj : s.objects) {
        if (!obj.target || obj.occluders.empty()) continue;
        const WorldScene e = render_without(s, obj.occluders);
        write_png(dir + "/edited/" + obj.id + "/image.png", Picture{e.camera.width, e.camera.height, e.rgb});
      }
    std::lock_guard<std::mutex> lock(mu);
    progress(++done, int64_t(seeds.size()));
  });
  fmt::print("wrote {} {} scenes to {}\n", seeds.size(), to_string(split), o.out);
}

// `world pairs` settings.
struct PairsOptions {
  std::string out, config;
  int completion = 0, preservation = 0, resolution = 16, threads = 1, targets = 1;
  uint64_t seed = 0;
  bool clean = false, overwrite = false;
};

// Preference pairs from train scenes, taken in scene-seed order until both counts are met (scenes are
// made `threads` at a time, then used in order, so the output does not depend on the thread count).
void run_pairs(const PairsOptions& o, const std::vector<std::string>& sets) {
  SIMU_CHECK(o.completion >= 0 && o.preservation >= 0 && o.completion + o.preservation > 0,
             "--completion {} / --preservation {}: ask for at least one pair", o.completion, o.preservation);
  SceneConfig cfg;
  CorruptionConfig ccfg;
  PairPlanConfig pcfg;
  read_world_config(o.config, sets, cfg, ccfg);
  // At least one occluded target per scene (the completion kind's supply).
  cfg.targets = std::max(cfg.targets, o.targets);
  pcfg.completion_min = cfg.visible_min, pcfg.completion_max = cfg.visible_max;
  simu::fs::check_overwrite(o.out, o.overwrite, "--out");
  std::filesystem::create_directories(o.out);
  struct Made {
    WorldScene scene;
    std::vector<PlannedPair> pairs;
  };
  int want[2] = {o.completion, o.preservation}, got[2] = {0, 0}, scenes_used = 0, scenes_made = 0;
  std::string manifest;
  simu::Progress progress{"world pairs", "pairs"};
  uint64_t next = o.seed;
  const int chunk = std::max(1, o.threads);
  while ((got[0] < want[0] || got[1] < want[1]) && scenes_made < 100000) {
    std::vector<uint64_t> seeds;
    for (int k = 0; k < chunk; ++k) {
      seeds.push_back(next_scene_seed(Split::Train, next));
      next = seeds.back() + 1;
    }
    std::vector<Made> made(seeds.size());
    simu::parallel_for_each(int64_t(seeds.size()), o.threads, [&](int64_t k) {
      made[size_t(k)].scene = make_scene(cfg, seeds[size_t(k)], Split::Train);
      made[size_t(k)].pairs = plan_pairs(made[size_t(k)].scene, pcfg, seeds[size_t(k)]);
    });
    scenes_made += int(seeds.size());
    for (auto& m : made) {
      const WorldScene& s = m.scene;
      const std::string sdir = s.name;
      bool used = false;
      for (auto& p : m.pairs) {
        const int kind = p.completion ? 0 : 1;
        if (got[kind] >= want[kind]) continue;
        const WorldObject& obj = s.objects[size_t(p.object)];
        const std::string odir = sdir + "/" + obj.id;
        const std::string abs = o.out + "/" + odir;
        std::filesystem::create_directories(abs);
        if (!used) {
          // The scene's image and point map (corrupted as the stage-1 cache's are, unless --clean).
          write_png(o.out + "/" + sdir + "/image.png", Picture{s.camera.width, s.camera.height, s.rgb});
          write_pointmap(o.out + "/" + sdir + "/pointmap.npy", o.clean ? s.pointmap : corrupt_pointmap(s.pointmap, ccfg, s.seed));
          used = true;
        }
        simu::physics::write_mask(abs + "/mask.png", obj.modal);
        const auto grid = voxelize_filled(obj.shape.mesh, o.resolution);
        simu::data::write_npy(abs + "/occupancy.npy",
                              torch::from_blob(const_cast<uint8_t*>(grid.data()), {o.resolution, o.resolution, o.resolution}, torch::kUInt8));
        nlohmann::json j = {{"id", odir + (p.completion ? "/completion" : "/preservation")},
                            {"kind", p.completion ? "occlusion_completion" : "clean_preservation"},
                            {"image", sdir + "/image.png"},
                            {"mask", odir + "/mask.png"},
                            {"pointmap", sdir + "/pointmap.npy"},
                            {"gt_occupancy", odir + "/occupancy.npy"}};
        if (p.completion) {
          write_png(abs + "/edited.png", Picture{p.edited.camera.width, p.edited.camera.height, p.edited.rgb});
          write_pointmap(abs + "/edited_pointmap.npy", o.clean ? p.edited.pointmap : corrupt_pointmap(p.edited.pointmap, ccfg, s.seed));
          simu::physics::write_mask(abs + "/full_mask.png", p.full_mask);
          j["full_image"] = odir + "/edited.png";
          j["full_mask"] = odir + "/full_mask.png";
          j["full_pointmap"] = odir + "/edited_pointmap.npy";
        } else {
          simu::physics::write_mask(abs + "/corrupted_mask.png", p.corrupted);
          j["corrupted_mask"] = odir + "/corrupted_mask.png";
        }
        manifest += j.dump() + "\n";
        ++got[kind];
        progress(got[0] + got[1], want[0] + want[1]);
      }
      scenes_used += used;
    }
  }
  SIMU_CHECK(got[0] >= want[0] && got[1] >= want[1], "world pairs: {} scenes gave only {} completion and {} preservation pairs",
             scenes_made, got[0], got[1]);
  simu::fs::atomic_write(o.out + "/manifest.jsonl", manifest);
  const nlohmann::json summary = {{"completion", got[0]}, {"preservation", got[1]}, {"scenes_made", scenes_made},
                                  {"scenes_used", scenes_used}, {"first_seed", o.seed}, {"last_seed", next - 1},
                                  {"resolution", o.resolution}, {"point_maps", o.clean ? "clean" : "corrupted"},
                                  {"completion_visible", {pcfg.completion_min, pcfg.completion_max}},
                                  {"full_min", pcfg.full_min}, {"preserve_min", pcfg.preserve_min}};
  simu::fs::atomic_write(o.out + "/pairs.json", summary.dump(2) + "\n");
  fmt::print("wrote {} completion + {} preservation pairs from {} of {} train scenes to {}/manifest.jsonl\n", got[0], got[1],
             scenes_used, scenes_made, o.out);
}

// A family x split table of instances seed .. seed + count - 1.
void run_shapes(int count, uint64_t seed) {
  fmt::print("{:<12} {:>7} {:>7} {:>7}  {:>13}  {}\n", "family", "train", "val", "test", "size (m)", "note");
  int total[3] = {0, 0, 0};
  for (const auto& f : families()) {
    int n[3] = {0, 0, 0};
    double lo = 1e9, hi = 0;
    bool closed = true;
    for (int k = 0; k < count; ++k) {
      const ShapeInstance s = make_shape(f, seed + uint64_t(k));
      ++n[int(s.split)];
      lo = std::min(lo, s.size_m), hi = std::max(hi, s.size_m);
      closed = closed && s.closed;
    }
    for (int i = 0; i < 3; ++i) total[i] += n[i];
    std::string note = f == held_out_family() ? "held out (test only)" : "";
    if (!closed) note += note.empty() ? "open mesh" : ", open mesh";
    fmt::print("{:<12} {:>7} {:>7} {:>7}  {:>5.3f}-{:<5.3f}  {}\n", f, n[0], n[1], n[2], lo, hi, note);
  }
  fmt::print("{:<12} {:>7} {:>7} {:>7}\n", "all", total[0], total[1], total[2]);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"The procedural shape world: scenes with ground truth for lift and training, the shape families (docs/world.md)"};
  app.require_subcommand(1);
  simu::cli::CommonOptions common;
  ScenesOptions so;
  auto* scenes = app.add_subcommand("scenes", "Write scenes of one split (image, masks, point map, intrinsics, gt.json)");
  scenes->add_option("--split", so.split, "train | val | test")->capture_default_str();
  scenes->add_option("--count", so.count, "number of scenes")->capture_default_str()->check(CLI::PositiveNumber);
  scenes->add_option("--seed", so.seed, "the first scene seed tried (seeds of other splits are skipped)")->capture_default_str();
  scenes->add_option("--out", so.out, "output folder (one subfolder per scene)")->required();
  scenes->add_flag("--overwrite", so.overwrite, "write into an existing --out folder");
  scenes->add_option("--config", so.config, "YAML/JSON with `scene:` (SceneConfig) and `corruption:` sections");
  scenes->add_flag("--corrupt", so.corrupt, "pointmap.npy corrupted like a monocular estimator (clean one in pointmap_clean.npy)");
  scenes->add_option("--targets", so.targets, "objects per scene with a visible fraction in --visible (default: config, else 0)");
  scenes->add_option("--visible", so.visible, "target visible range LO-HI (default 0.2-0.6)");
  scenes->add_option("--families", so.families, "comma-separated families (default: all of the split; the held-out one in test only)");
  scenes->add_option("--objects", so.objects, "folder of meshes: one test scene per file with it placed first (eval_lift --objects)");
  scenes->add_option("--width", so.width, "image width (default 320)");
  scenes->add_option("--height", so.height, "image height (default 240)");
  scenes->add_flag("--edited", so.edited, "also write edited/<target>/image.png: each target with its occluders removed");
  scenes->add_option("--threads", so.threads, "scenes generated in parallel")->capture_default_str()->check(CLI::PositiveNumber);
  int shape_count = 200;
  uint64_t shape_seed = 0;
  auto* shapes = app.add_subcommand("shapes", "Print a family x split table of instances");
  shapes->add_option("--count", shape_count, "instances per family")->capture_default_str()->check(CLI::PositiveNumber);
  shapes->add_option("--seed", shape_seed, "first instance seed")->capture_default_str();
  PairsOptions po;
  auto* pairs = app.add_subcommand("pairs", "Write FM-DPO preference pairs (both kinds) of train scenes and their build_pairs manifest");
  pairs->add_option("--completion", po.completion, "occlusion-completion pairs")->capture_default_str();
  pairs->add_option("--preservation", po.preservation, "clean-preservation pairs")->capture_default_str();
  pairs->add_option("--seed", po.seed, "the first scene seed tried (train seeds only)")->capture_default_str();
  pairs->add_option("--out", po.out, "output folder (manifest.jsonl, pairs.json, one subfolder per scene)")->required();
  pairs->add_flag("--overwrite", po.overwrite, "write into an existing --out folder");
  pairs->add_option("--config", po.config, "YAML/JSON with `scene:` (SceneConfig) and `corruption:` sections");
  pairs->add_option("--targets", po.targets, "occluded targets per scene (at least)")->capture_default_str();
  pairs->add_option("--resolution", po.resolution, "side R of the ground truth's occupancy: the decoder's (16: weights/miniature_cpu; 32: configs/miniature)")
      ->capture_default_str()->check(CLI::Range(2, 256));
  pairs->add_flag("--clean", po.clean, "clean point maps (default: corrupted as a monocular estimator would)");
  pairs->add_option("--threads", po.threads, "scenes made in parallel")->capture_default_str()->check(CLI::PositiveNumber);
  std::string sheet_out;
  int per_family = 6, cell = 128;
  uint64_t sheet_seed = 0;
  auto* sheet = app.add_subcommand("sheet", "Render a contact sheet PNG of every family");
  sheet->add_option("--out", sheet_out, "PNG file")->required();
  sheet->add_option("--per-family", per_family, "instances per family (columns)")->capture_default_str();
  sheet->add_option("--cell", cell, "cell size in pixels")->capture_default_str();
  sheet->add_option("--seed", sheet_seed, "first instance seed")->capture_default_str();
  return simu::cli::run(app, argc, argv, common, [&] {
    if (*scenes) {
      run_scenes(so, common.sets);
    } else if (*pairs) {
      run_pairs(po, common.sets);
    } else {
      SIMU_CHECK(common.sets.empty(), "--set {}: only `world scenes` and `world pairs` read a config", common.sets.empty() ? "" : common.sets.front());
      if (*shapes) run_shapes(shape_count, shape_seed);
      if (*sheet) {
        write_png(sheet_out, family_contact_sheet(per_family, cell, sheet_seed));
        fmt::print("wrote {}\n", sheet_out);
      }
    }
    return 0;
  });
}
