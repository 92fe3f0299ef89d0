// eval_lift: choosing objects in world scenes, lifting them per depth kind and model, scoring them.
#include "pipeline/resample/eval_lift.h"

#include <fmt/format.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <limits>
#include <map>
#include <thread>
#include <tuple>
#include <type_traits>

#include "common/error.h"
#include "common/parallel.h"
#include "common/progress.h"
#include "common/random.h"
#include "pipeline/physics/pictures.h"
#include "pipeline/resample/lift.h"
#include "pipeline/world/shapes.h"
#include "pipeline/world/voxelize.h"

namespace simu::resample {

namespace {

using physics::PlacedShape;
using Clock = std::chrono::steady_clock;

double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// Seeds derived from the run's seed: one stream per purpose, mixed with the scene seed where per scene.
uint64_t derive(uint64_t seed, uint64_t purpose, uint64_t key = 0) {
  return splitmix64(splitmix64(seed ^ (purpose * 0x9E3779B97F4A7C15ULL)) ^ key);
}
enum Purpose : uint64_t { kScenes = 1, kNoise = 2, kCorruption = 3, kInstances = 4 };

// A file-name-safe version of an id.
std::string safe_name(const std::string& id) {
  std::string s;
  for (char c : id) s += (std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_' || c == '.') ? c : '_';
  return s;
}

// The scene's image and a point map as lift's inputs, with one modal mask per chosen object (and its
// amodal mask as the crop mask with amodal_crop).
LiftInputs lift_inputs(const world::WorldScene& s, const world::PointMap& pm, const std::vector<int>& chosen,
                       const std::vector<std::string>& ids, bool amodal_crop) {
  const int H = s.camera.height, W = s.camera.width;
  LiftInputs in;
  in.rgb = torch::from_blob(const_cast<uint8_t*>(s.rgb.data()), {H, W, 3}, torch::kUInt8)
               .permute({2, 0, 1})
               .to(torch::kFloat32)
               .div(255.0)
               .contiguous();
  in.pointmap = torch::from_blob(const_cast<float*>(pm.xyz.data()), {H, W, 3}, torch::kFloat32).clone();
  in.camera = s.camera;
  for (size_t k = 0; k < chosen.size(); ++k) {
    const auto& m = s.objects[chosen[k]].modal;
    LiftObjectInput o;
    o.id = ids[k];
    o.mask = torch::from_blob(const_cast<uint8_t*>(m.data.data()), {m.height, m.width}, torch::kUInt8).to(torch::kFloat32);
    if (amodal_crop) {
      const auto& a = s.objects[chosen[k]].amodal;
      o.crop_mask = torch::from_blob(const_cast<uint8_t*>(a.data.data()), {a.height, a.width}, torch::kUInt8).to(torch::kFloat32);
    }
    in.objects.push_back(o);
  }
  return in;
}

// The usable samples of a lifted object (indices into its samples, in order).
std::vector<int> usable_samples(const LiftedObject& o) {
  std::vector<int> out;
  for (size_t k = 0; k < o.samples.size(); ++k)
    if (o.samples[k].ok && k < o.scene_poses.size()) out.push_back(static_cast<int>(k));
  return out;
}

// Sample k of a lifted object placed at its scene pose.
PlacedShape placed_sample(const LiftedObject& o, int k) {
  PlacedShape out;
  out.canonical = o.samples[size_t(k)].mesh;
  out.scale = o.scene_poses[size_t(k)].scale;
  out.R = o.scene_poses[size_t(k)].R;
  out.t = o.scene_poses[size_t(k)].t;
  return out;
}


// Where the objects come from: scenes of a split (every object in range) or one given instance per
// object placed among random ones (held-out family, external meshes).
struct Source {
  world::Split split = world::Split::Test;
  bool placed = false;                           // one extra instance per object
  std::vector<std::string> files;                // external meshes (placed)
  std::map<std::string, world::ShapeInstance> loaded;
  uint64_t next_seed = 0;                        // scene seed search position
  int target = 0;                                // objects wanted
};

// The next scene seed of the split.
uint64_t take_scene_seed(Source& src) {
  const uint64_t s = world::next_scene_seed(src.split, src.next_seed);
  src.next_seed = s + 1;
  return s;
}

// The instance the k-th placed object evaluates.
world::ShapeInstance placed_instance(Source& src, const EvalLiftOptions& opt, int k) {
  if (src.files.empty()) {
    const std::string& fam = world::held_out_family();
    const uint64_t seed = world::next_instance_seed(fam, world::Split::Test, derive(opt.seed, kInstances, k) >> 2);
    return world::make_shape(fam, seed);
  }
  const std::string& file = src.files[k % src.files.size()];
  auto it = src.loaded.find(file);
  if (it == src.loaded.end()) it = src.loaded.emplace(file, world::load_external_shape(file, opt.object_size)).first;
  return it->second;
}

}  // namespace

std::vector<std::string> depth_kinds(const std::string& depth) {
  if (depth == "clean") return {"clean"};
  if (depth == "corrupted") return {"corrupted"};
  if (depth == "both") return {"clean", "corrupted"};
  fail_hint("--depth clean | corrupted | both", "--depth: unknown value '{}'", depth);
}

double occupancy_iou(const torch::Tensor& coords, const std::vector<uint8_t>& gt, int64_t R) {
  SIMU_CHECK(static_cast<int64_t>(gt.size()) == R * R * R, "occupancy_iou: a grid of {} bytes is not {}^3", gt.size(), R);
  std::vector<uint8_t> pred(gt.size(), 0);
  const auto c = coords.to(torch::kCPU, torch::kInt64).contiguous();
  const int64_t* p = c.data_ptr<int64_t>();
  for (int64_t i = 0; i < c.size(0); ++i) {
    const int64_t x = p[3 * i], y = p[3 * i + 1], z = p[3 * i + 2];
    if (x >= 0 && y >= 0 && z >= 0 && x < R && y < R && z < R) pred[size_t((x * R + y) * R + z)] = 1;
  }
  int64_t inter = 0, uni = 0;
  for (size_t i = 0; i < gt.size(); ++i) inter += pred[i] && gt[i], uni += pred[i] || gt[i];
  return uni == 0 ? 1.0 : double(inter) / double(uni);
}

void check_shape_grid(int64_t R, int64_t S) {
  SIMU_CHECK(S >= 1 && S <= R && R % S == 0,
             "--shape-grid {}: a model's grid side {} is not a multiple of it (choose a divisor of every compared "
             "model's decoder grid)", S, R);
}

torch::Tensor pool_coords(const torch::Tensor& coords, int64_t R, int64_t S) {
  check_shape_grid(R, S);
  const auto c = coords.to(torch::kCPU, torch::kInt64);
  if (S == R || c.size(0) == 0) return c;
  return std::get<0>(at::unique_dim(torch::floor_divide(c, R / S), 0));
}

namespace {
// "A<sep>B" (the separator searched from position `from`), both parts numbers of type T with nothing
// else; throws otherwise (the callers turn it into an error naming their flag).
template <class T>
std::pair<T, T> two_numbers(const std::string& text, char sep, size_t from) {
  const auto at = text.find(sep, from);
  SIMU_CHECK(at != std::string::npos, "no separator");
  const auto one = [](const std::string& part) {
    size_t used = 0;
    T v;
    if constexpr (std::is_integral_v<T>) v = std::stoi(part, &used);
    else v = std::stod(part, &used);
    SIMU_CHECK(used == part.size(), "trailing text");
    return v;
  };
  return {one(text.substr(0, at)), one(text.substr(at + 1))};
}
}  // namespace

std::pair<int, int> parse_shard(const std::string& text) {
  int i = -1, n = 0;
  try {
    std::tie(i, n) = two_numbers<int>(text, '/', 0);
  } catch (const std::exception&) {
    fail_hint("e.g. --shard 0/4 (the first of four)", "--shard '{}': expected I/N", text);
  }
  SIMU_CHECK(n >= 1 && i >= 0 && i < n, "--shard '{}': need 0 <= I < N", text);
  return {i, n};
}

std::pair<double, double> parse_visible_range(const std::string& text) {
  double lo = 0, hi = 0;
  try {
    std::tie(lo, hi) = two_numbers<double>(text, '-', 1);
  } catch (const std::exception&) {
    fail_hint("e.g. --visible 40-70 (percent) or --visible 0.4-0.7", "--visible '{}': expected LO-HI", text);
  }
  if (lo > 1 || hi > 1) lo /= 100, hi /= 100;
  SIMU_CHECK(lo >= 0 && hi <= 1 && lo <= hi, "--visible '{}': need 0 <= LO <= HI <= 1 (or 100 in percent)", text);
  return {lo, hi};
}

const std::vector<std::string>& visibility_buckets() {
  static const std::vector<std::string> b{"unoccluded", "70-100%", "40-70%", "<40%"};
  return b;
}

std::string visibility_bucket(double v) {
  if (v >= 0.999) return "unoccluded";
  if (v >= 0.7) return "70-100%";
  if (v >= 0.4) return "40-70%";
  return "<40%";
}

std::vector<std::string> list_mesh_files(const std::string& dir) {
  namespace fs = std::filesystem;
  SIMU_CHECK(fs::is_directory(dir), "--objects {}: not a folder", dir);
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(dir)) {
    std::string ext = e.path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
    if (e.is_regular_file() && (ext == ".obj" || ext == ".ply" || ext == ".stl" || ext == ".glb" || ext == ".gltf"))
      files.push_back(e.path().string());
  }
  std::sort(files.begin(), files.end());
  if (files.empty()) fail_hint("OBJ, PLY, STL, GLB or glTF files", "--objects {}: no mesh files in the folder", dir);
  return files;
}

void validate_eval_options(const EvalLiftOptions& opt) {
  if (opt.world.empty() == opt.objects_dir.empty())
    fail_hint("--world test | heldout | val | train, or --objects DIR", "give exactly one of --world and --objects");
  if (!opt.objects_dir.empty()) list_mesh_files(opt.objects_dir);
  if (!opt.world.empty() && opt.world != "heldout") world::parse_split(opt.world, "--world (train | val | test | heldout)");
  SIMU_CHECK(opt.visible_lo >= 0 && opt.visible_hi <= 1 && opt.visible_lo <= opt.visible_hi,
             "--visible: [{}, {}] is not a range in [0, 1]", opt.visible_lo, opt.visible_hi);
  depth_kinds(opt.depth);
  SIMU_CHECK(opt.count >= 0, "--count {} must not be negative", opt.count);
  SIMU_CHECK(opt.object_size >= 0, "--object-size {} must not be negative", opt.object_size);
  SIMU_CHECK(opt.attempts >= 1, "eval_lift: attempts {} must be >= 1", opt.attempts);
  SIMU_CHECK(opt.shard_count >= 1 && opt.shard_index >= 0 && opt.shard_index < opt.shard_count,
             "--shard {}/{}: need 0 <= I < N", opt.shard_index, opt.shard_count);
  if (!(opt.oracle.empty() || opt.oracle == "none" || opt.oracle == "grid" || opt.oracle == "pose"))
    fail_hint("--oracle none | grid | pose", "--oracle: unknown value '{}'", opt.oracle);
  SIMU_CHECK(opt.bootstrap_resamples >= 1, "--bootstrap {} must be >= 1", opt.bootstrap_resamples);
  SIMU_CHECK(opt.metrics.fscore_thresholds == std::vector<double>({0.01, 0.02}),
             "eval_lift: the F-score thresholds are 1 and 2 cm (summary keys fscore_1cm, fscore_2cm)");
}

EvalLiftResult run_eval_lift(const EvalLiftOptions& opt, const EvalModels& models, const std::string& out_dir) {
  validate_eval_options(opt);
  SIMU_CHECK(opt.gt_as_prediction || models.base, "eval_lift: no model to lift with");
  const bool oracle_grid = opt.oracle == "grid", oracle_pose = opt.oracle == "pose";
  SIMU_CHECK(!oracle_grid || models.base, "eval_lift --oracle grid: the base model gives the grid side");
  const bool no_lift = opt.gt_as_prediction || oracle_grid;
  // --shape-grid must divide every compared model's decoder grid (checked before any lift).
  if (opt.shape_grid > 0)
    for (Resampler* model : {models.base, models.compare})
      if (model) check_shape_grid(occupancy_resolution(*model), opt.shape_grid);
  EvalLiftResult res;
  res.depths = depth_kinds(opt.depth);
  res.models = {"base"};
  if (models.compare && !no_lift) res.models.push_back("compare");

  Source src;
  if (!opt.objects_dir.empty()) {
    src.placed = true;
    src.files = list_mesh_files(opt.objects_dir);
    src.target = opt.count > 0 ? opt.count : static_cast<int>(src.files.size());
  } else if (opt.world == "heldout") {
    src.placed = true;
    src.target = opt.count > 0 ? opt.count : 20;
  } else {
    src.split = world::parse_split(opt.world, "--world (train | val | test | heldout)");
    src.target = opt.count > 0 ? opt.count : 20;
  }
  src.next_seed = derive(opt.seed, kScenes) >> 2;
  world::SceneConfig cfg = opt.scene;
  if (opt.visible_hi < 0.999) {
    // Occluded objects wanted: the generator places occluders in front of targets in the range.
    cfg.targets = std::max(cfg.targets, 1);
    cfg.visible_min = opt.visible_lo;
    cfg.visible_max = opt.visible_hi;
  }
  const std::string pictures_dir = out_dir + "/pictures";
  if (opt.pictures) std::filesystem::create_directories(pictures_dir);

  const int threads = opt.threads > 0 ? opt.threads : std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
  Progress progress{"eval_lift", "objects"};
  progress(0, src.target);
  int placed_k = 0;
  int taken = 0;  // objects of the whole run (every shard's) taken so far
  int scenes_taken = 0;  // world scenes with objects taken (every shard's)
  while (taken < src.target) {
    // One scene and the objects of it to evaluate.
    world::WorldScene scene;
    std::vector<int> chosen;
    std::string source;  // the mesh file of an external object
    if (src.placed) {
      const world::ShapeInstance inst = placed_instance(src, opt, placed_k);
      if (!src.files.empty()) source = src.files[placed_k % src.files.size()];
      const std::string what = source.empty() ? inst.name : source;
      // Scenes until one shows it usable and in the visible range; a scene the generator cannot place it
      // in counts as a try (the last reason is reported).
      std::string last = "not in the visible range";
      for (int a = 0;; ++a) {
        SIMU_CHECK(a < opt.attempts, "object {}: no usable placement with visible fraction in [{:.2f}, {:.2f}] in {} scenes "
                   "(last: {})", what, opt.visible_lo, opt.visible_hi, opt.attempts, last);
        ++res.scenes;
        try {
          scene = world::make_scene(cfg, take_scene_seed(src), world::Split::Test, {inst});
        } catch (const Error& e) {
          last = e.what();
          continue;
        }
        const auto& o = scene.objects.at(0);
        if (o.usable && o.visible_fraction >= opt.visible_lo && o.visible_fraction <= opt.visible_hi) break;
        last = fmt::format("visible fraction {:.2f}{}", o.visible_fraction, o.usable ? "" : ", not usable");
      }
      chosen = {0};
      ++taken;
      // Another shard's object: its scenes were made (the next object's seeds follow them), nothing else.
      if ((placed_k++) % opt.shard_count != opt.shard_index) continue;
    } else {
      scene = world::make_scene(cfg, take_scene_seed(src), src.split);
      ++res.scenes;
      for (size_t i = 0; i < scene.objects.size(); ++i) {
        const auto& o = scene.objects[i];
        if (taken + static_cast<int>(chosen.size()) >= src.target) break;
        if (o.usable && o.visible_fraction >= opt.visible_lo && o.visible_fraction <= opt.visible_hi)
          chosen.push_back(static_cast<int>(i));
      }
      SIMU_CHECK(res.scenes <= 50 * src.target + 100, "--world {}: {} scenes gave only {} objects with visible fraction in "
                 "[{:.2f}, {:.2f}]", opt.world, res.scenes, taken, opt.visible_lo, opt.visible_hi);
      if (chosen.empty()) continue;
      taken += static_cast<int>(chosen.size());
      // Another shard's scene (scenes with objects taken, in order, dealt round robin): made, not lifted.
      if ((scenes_taken++) % opt.shard_count != opt.shard_index) continue;
    }
    // Ground truth of the chosen objects.
    const int first = static_cast<int>(res.objects.size());
    std::vector<std::string> ids;
    const auto t_metrics0 = Clock::now();
    for (int i : chosen) {
      const world::WorldObject& o = scene.objects[i];
      EvalObject e;
      e.id = scene.name + "/" + o.id;
      e.scene = scene.name;
      e.scene_seed = scene.seed;
      e.family = o.shape.family;
      e.instance = o.shape.name;
      e.source = source;
      e.held_out = o.shape.held_out;
      e.visible_fraction = o.visible_fraction;
      e.bucket = visibility_bucket(o.visible_fraction);
      e.gt.canonical = o.shape.mesh;
      e.gt.scale = o.scale, e.gt.R = o.R, e.gt.t = o.t;
      e.camera = scene.camera;
      ids.push_back(e.id);
      res.objects.push_back(std::move(e));
    }
    parallel_for_each(static_cast<int64_t>(chosen.size()), threads, [&](int64_t k) {
      EvalObject& e = res.objects[first + k];
      e.symmetry = physics::find_symmetry(e.gt.scaled(), opt.metrics.symmetry);
    });
    res.seconds_metrics += since(t_metrics0);
    const uint64_t noise = derive(opt.seed, kNoise, scene.seed);
    std::map<std::pair<int, int64_t>, std::vector<uint8_t>> gt_grids;  // (object, R) -> filled occupancy
    for (const std::string& depth : res.depths) {
      world::PointMap pm = scene.pointmap;
      if (depth == "corrupted") pm = world::corrupt_pointmap(scene.pointmap, opt.corruption, derive(opt.seed, kCorruption, scene.seed));
      // Lift with every model (the same inputs and noise), then score every (model, object) in parallel.
      const size_t nk = chosen.size(), nm = res.models.size(), row0 = res.rows.size();
      std::vector<PlacedShape> preds(nm * nk);
      std::vector<physics::Mesh> pred_world(nm * nk);  // for the picture
      std::vector<LiftResult> lifts(nm);
      std::vector<std::vector<int>> usable(nm * nk);  // model lifts: the usable samples of each row
      for (size_t m = 0; m < nm; ++m) {
        LiftResult& lifted = lifts[m];
        if (!no_lift) {
          const auto t0 = Clock::now();
          LiftOptions lo;
          lo.seed = noise;
          lifted = lift_objects(m == 0 ? *models.base : *models.compare, lift_inputs(scene, pm, chosen, ids, opt.amodal_crop), lo);
          res.seconds_lift += since(t0);
        }
        for (size_t k = 0; k < nk; ++k) {
          const EvalObject& obj = res.objects[first + k];
          EvalRow row;
          row.object = first + static_cast<int>(k);
          row.depth = depth;
          row.model = res.models[m];
          if (opt.gt_as_prediction) {
            preds[m * nk + k] = obj.gt;
            row.ok = true;
            row.shape_iou = 1.0;
          } else if (oracle_grid) {
            // The truth's occupancy at the model's grid side, meshed like a decoder output, at the true pose.
            const int64_t R = occupancy_resolution(*models.base);
            auto& gt = gt_grids[{row.object, R}];
            if (gt.empty()) gt = world::voxelize_filled(obj.gt.canonical, static_cast<int>(R));
            const auto logits = torch::from_blob(gt.data(), {R, R, R}, torch::kUInt8).to(torch::kFloat32).mul(2).sub(1);
            ResampledShape rs;
            mesh_from_logits(logits, rs, models.base->config().surface_offset);
            row.ok = rs.ok;
            if (rs.ok) {
              preds[m * nk + k] = obj.gt;
              preds[m * nk + k].canonical = rs.mesh;
              row.shape_iou = occupancy_iou(rs.coords, gt, R);
            } else {
              row.error = fmt::format("object {}: --oracle grid: {}", obj.id, rs.message);
            }
          } else {
            // The first usable sample; with opt.select, the best of them (chosen in the scoring below).
            usable[m * nk + k] = usable_samples(lifted.objects[k]);
            row.ok = !usable[m * nk + k].empty();
            if (row.ok) {
              row.sample = usable[m * nk + k].front();
              preds[m * nk + k] = placed_sample(lifted.objects[k], row.sample);
              const int64_t S = opt.shape_grid > 0 ? opt.shape_grid : occupancy_resolution(m == 0 ? *models.base : *models.compare);
              auto& gt = gt_grids[{row.object, S}];  // the shape IoU's truth, made here (the map is not thread-safe)
              if (gt.empty()) gt = world::voxelize_filled(obj.gt.canonical, static_cast<int>(S));
            } else {
              row.error = lifted.objects[k].error.empty() ? fmt::format("object {}: no usable sample", obj.id)
                                                          : lifted.objects[k].error;
            }
          }
          res.rows.push_back(std::move(row));
        }
      }
      const auto t1 = Clock::now();
      parallel_for_each(static_cast<int64_t>(nm * nk), threads, [&](int64_t i) {
        EvalRow& row = res.rows[row0 + i];
        if (!row.ok) return;
        const EvalObject& obj = res.objects[row.object];
        try {
          RefineInput ri;
          ri.camera = &obj.camera;
          ri.pointmap = &pm;
          ri.modal = &scene.objects[chosen[i % nk]].modal;
          ri.id = obj.id;
          ri.gravity = scene.gravity;
          // Each candidate sample (one without opt.select) placed, refined and, with opt.select, scored;
          // the lowest score is kept.
          const std::vector<int> cands = opt.select && usable[i].size() > 1 ? usable[i] : std::vector<int>{row.sample};
          if (opt.select) row.sample_scores.assign(lifts[i / nk].objects.empty() ? 0 : lifts[i / nk].objects[i % nk].samples.size(),
                                                   std::numeric_limits<double>::quiet_NaN());
          double best = std::numeric_limits<double>::infinity();
          for (size_t c = 0; c < cands.size(); ++c) {
            PlacedShape p = no_lift ? preds[i] : placed_sample(lifts[i / nk].objects[i % nk], cands[c]);
            if (oracle_pose) p.scale = obj.gt.scale, p.R = obj.gt.R, p.t = obj.gt.t;  // the sampled shape at the true pose
            const physics::Vec3 lifted_t = p.t;
            const double lifted_size = p.size();
            const std::string note = opt.refine ? opt.refine(p, ri) : std::string();
            const double score = opt.select ? opt.select(p, ri) : 0.0;
            if (opt.select && !no_lift) row.sample_scores[size_t(cands[c])] = score;
            if (c == 0 || score < best) {
              best = score;
              preds[i] = std::move(p);
              row.sample = cands[c];
              if (opt.refine) row.lifted_t = lifted_t, row.lifted_size = lifted_size;
              row.refine_note = note;
              row.refined = opt.refine && note.empty();
            }
          }
          row.metrics = physics::shape_metrics(preds[i], obj.gt, obj.symmetry, opt.metrics);
          row.pred_t = preds[i].t;
          row.pred_size = preds[i].size();
          pred_world[i] = preds[i].world();
        } catch (const std::exception& e) {
          // A prediction the metrics cannot score (a degenerate mesh or pose) is that object's failure.
          row.ok = false;
          row.error = fmt::format("object {}: metrics: {}", obj.id, e.what());
        }
      });
      // The shape IoU of the kept sample, on its model's grid or opt.shape_grid.
      for (size_t i = 0; i < nm * nk && !no_lift; ++i) {
        EvalRow& row = res.rows[row0 + i];
        if (!row.ok) continue;
        const int64_t R = occupancy_resolution(i / nk == 0 ? *models.base : *models.compare);
        const int64_t S = opt.shape_grid > 0 ? opt.shape_grid : R;
        const auto& sample = lifts[i / nk].objects[i % nk].samples[size_t(row.sample)];
        row.shape_iou = occupancy_iou(pool_coords(sample.coords, R, S), gt_grids.at({row.object, S}), S);
      }
      res.seconds_metrics += since(t1);
      if (!opt.pictures) continue;
      std::vector<const physics::Mesh*> env;
      for (const auto& e : scene.environment) env.push_back(&e);
      for (size_t k = 0; k < chosen.size(); ++k) {
        const EvalObject& obj = res.objects[first + k];
        const physics::Mesh gt_world = obj.gt.world();
        std::vector<physics::MeshPanel> panels{{"GT " + obj.family, &gt_world}};
        for (size_t m = 0; m < res.models.size(); ++m) {
          const EvalRow& row = res.rows[row0 + m * nk + k];
          const std::string who = res.models.size() > 1 ? res.models[m] + " " : "";
          panels.push_back({row.ok ? fmt::format("{}IoU {:.2f} F2 {:.2f}", who, row.metrics.iou, row.metrics.fscore[1].f)
                                   : who + "FAILED",
                            &pred_world[m * nk + k]});
        }
        const std::string rel = "pictures/" + safe_name(obj.id) + "_" + depth + ".png";
        physics::write_object_comparison_png(
            out_dir + "/" + rel, scene.camera, scene.rgb, scene.objects[chosen[k]].modal, panels, env,
            fmt::format("{}  visible {:.0f}%  {} depth", obj.id, 100 * obj.visible_fraction, depth));
        for (size_t m = 0; m < res.models.size(); ++m) res.rows[row0 + m * nk + k].picture = rel;
      }
    }
    progress(taken, src.target);
  }
  return res;
}

}  // namespace simu::resample
