// eval_lift: objects rendered in shape-world scenes, lifted through the released preprocessing, the
// embedder, Stage-1 sampling, decoding and pose (lift_objects), and scored against their ground truth in
// the world frame (physics/shape_metrics.h: voxel IoU, F-score at 1 and 2 cm, Chamfer, rotation error
// modulo the object's symmetry, translation and scale errors). docs/eval_lift.md.
//
//   EvalLiftOptions opt;  opt.world = "test";  opt.count = 20;
//   Resampler base(cfg);                                  // embedder_config set
//   EvalLiftResult r = run_eval_lift(opt, {&base, nullptr}, "out/eval");
//   nlohmann::json s = eval_summary(r, opt, {"", ""});    // what summary.json holds
//
// Objects: the world's test (or train / val) split, its held-out family ("heldout"), or every mesh file
// of a folder (--objects: OBJ/PLY/STL/GLB in any units, world::load_external_shape) placed at rest
// among random test-split objects. Scenes come one after another from scene seeds derived from
// `seed`; an object enters when usable and its visible fraction is in [visible_lo, visible_hi] (a
// range below 1 turns on the scene generator's occlusion control). Each scene's chosen objects are
// lifted together, for every depth kind (clean / corrupted point map) and model (base, and base +
// the compare adapter), with the same noise seed, so the rows pair up.
#pragma once

#include <nlohmann/json.hpp>

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "pipeline/physics/shape_metrics.h"
#include "pipeline/resample/resampler.h"
#include "pipeline/world/corrupt.h"
#include "pipeline/world/scene.h"

namespace simu::resample {

// The inputs of a pose refinement of one prediction (EvalLiftOptions::refine): the scene's camera (its
// pose in the world, intrinsics), the point map the lift saw (OpenCV camera frame) and the object's
// modal mask.
struct RefineInput {
  const physics::Camera* camera = nullptr;
  const world::PointMap* pointmap = nullptr;
  const physics::BinaryMask* modal = nullptr;
  std::string id;  // the object, for messages
  physics::Vec3 gravity = physics::Vec3::Zero();  // the scene's gravity, world frame (zero: unknown)
};
// A pose refinement run on every lifted prediction before it is scored (eval_lift --align: the
// SimuScene alignment of src/pipeline/reconstruct, set by the program since that library sits above
// this one). It may change the prediction's scale and translation (world frame). Returns "" when it
// changed the pose, else why not (the lifted pose is then kept and the reason goes in the row).
using PoseRefiner = std::function<std::string(physics::PlacedShape& prediction, const RefineInput& input)>;
// How well a prediction at its pose agrees with what the image shows (lower is better): with several
// samples per object (the model's num_samples), each usable sample is refined (`refine`, when set) and
// scored, and the lowest is the one scored against the truth (EvalLiftOptions::select; reconstruct's
// render_compare_scorer). It must not look at the ground truth.
using PoseScorer = std::function<double(const physics::PlacedShape& prediction, const RefineInput& input)>;

struct EvalLiftOptions {
  std::string world;             // train | val | test | heldout ("" with objects_dir)
  std::string objects_dir;       // a folder of mesh files ("" with world)
  double visible_lo = 0, visible_hi = 1;  // visible fraction range of the objects taken
  int count = 0;                 // objects (0: 20 from the world; every mesh once from objects_dir)
  uint64_t seed = 0;             // scenes, corruption, sampling noise and the bootstrap
  std::string depth = "clean";   // clean | corrupted | both
  double object_size = 0;        // metres for external meshes (0: their units guessed, world::make_external_shape)
  int attempts = 30;             // scenes tried per external / held-out object before it is an error
  world::SceneConfig scene;      // scene generator
  world::CorruptionConfig corruption;
  physics::ShapeMetricsConfig metrics;
  int bootstrap_resamples = 10000;
  bool pictures = true;          // pictures/<object>_<depth>.png
  bool gt_as_prediction = false; // testing: each prediction replaced by its ground truth (no model runs;
                                 // `refine`, when set, still runs on it)
  // Diagnostic upper bounds (eval_lift --oracle; docs/eval_lift.md), not results of the model:
  //   "grid": no model runs; each prediction is the ground truth's filled occupancy at the base model's
  //           grid side R, meshed as decoder outputs are (mesh_from_logits), at the true pose: what a
  //           perfect Stage 1 could score at this resolution;
  //   "pose": the model's sampled shape at the true rotation, scale and translation.
  // `refine`, when set, still runs after it. "" or "none": off.
  std::string oracle;
  // The resampling input of the paper (probe --resample): the crop box and background removal from the
  // object's amodal mask (here the ground truth's, an ideal OBB-guided crop) instead of its modal mask.
  bool amodal_crop = false;
  // The grid side of EvalRow::shape_iou (0: each model's own decoder grid R). A side S < R that divides R
  // compares models of different R on one grid: the sample's voxels are pooled to S (a coarse voxel is
  // occupied when any of its (R/S)^3 fine ones is, as the conservative filled voxelisation does) against
  // the truth's filled occupancy at S.
  int64_t shape_grid = 0;
  int threads = 0;               // metric threads (0: every core; the lift runs on torch's threads)
  // Shard shard_index of shard_count (eval_lift --shard I/N): every scene of the whole run is made, but
  // only the objects of world scenes with index % N == I (the scenes that have objects taken, in order),
  // or placed objects with index % N == I, are lifted and scored here. A scene's objects stay together,
  // so the shards' rows are the whole run's (same objects, inputs and noise); merge their summaries
  // (scripts/merge_eval_shards.py). summary.json's aggregates are the shard's own.
  int shard_index = 0, shard_count = 1;
  PoseRefiner refine;            // optional: run on each prediction before scoring (see PoseRefiner)
  PoseScorer select;             // optional: best of the samples by this score (unset: the first usable)
  std::string select_name = "first";  // what `select` is, for summary.json
  std::string refine_name = "none";  // what `refine` is, for summary.json
};

// Checks the options before any work: exactly one of world / objects_dir, a known split, a mesh folder
// with mesh files, the visible range, --depth, --count, --shard. Throws simu::Error naming the flag or folder.
void validate_eval_options(const EvalLiftOptions& options);
// Which depth kinds the options ask for ("clean", "corrupted"); throws naming --depth otherwise.
std::vector<std::string> depth_kinds(const std::string& depth);

// EvalRow::shape_iou: IoU of a sample's occupied voxels (coords [N, 3] integer, (x, y, z) of an R^3
// grid; flat index (x R + y) R + z, the decoder's [R, R, R] layout; coordinates outside the grid are
// ignored) with a filled grid of that layout (R^3 bytes, non-zero = occupied). Two empty grids: 1.
double occupancy_iou(const torch::Tensor& coords, const std::vector<uint8_t>& grid, int64_t R);
// Throws naming --shape-grid unless 1 <= S <= R and S divides R.
void check_shape_grid(int64_t R, int64_t S);
// Voxel coordinates of an R^3 grid pooled to an S^3 grid (check_shape_grid): each (x, y, z) / (R / S),
// duplicates removed. coords [N, 3] integer -> [M, 3] int64.
torch::Tensor pool_coords(const torch::Tensor& coords, int64_t R, int64_t S);
// "I/N" (0 <= I < N): eval_lift --shard. Throws simu::Error naming --shard when malformed.
std::pair<int, int> parse_shard(const std::string& text);
// "LO-HI" as fractions ("0.4-0.7") or percentages ("40-70": either bound above 1 means percent).
// Throws simu::Error naming --visible when malformed, out of [0, 1] or LO > HI.
std::pair<double, double> parse_visible_range(const std::string& text);
// The visibility bucket of a visible fraction: "unoccluded" (>= 0.999), "70-100%", "40-70%", "<40%".
std::string visibility_bucket(double visible_fraction);
// The buckets in table order.
const std::vector<std::string>& visibility_buckets();
// The mesh files of a folder (.obj .ply .stl .glb .gltf, any case), sorted; throws naming the folder when
// it is missing or holds none.
std::vector<std::string> list_mesh_files(const std::string& dir);

// One evaluated object and its ground truth.
struct EvalObject {
  std::string id;              // "<scene name>/<object id>", unique
  std::string scene;           // scene name
  uint64_t scene_seed = 0;
  std::string family, instance, source;  // source: the mesh file (external objects)
  bool held_out = false;
  double visible_fraction = 1;
  std::string bucket;
  physics::PlacedShape gt;     // canonical mesh and world pose
  physics::Symmetry symmetry;  // of gt.scaled()
  physics::Camera camera;      // the scene's camera (its pose in the world)
};

// One object under one depth kind and one model.
struct EvalRow {
  int object = 0;              // index into EvalLiftResult::objects
  std::string depth, model;    // "clean" | "corrupted"; "base" | "compare"
  bool ok = false;             // lifted (at least one usable sample)
  std::string error;           // why not, naming the object
  physics::ShapeMetrics metrics;  // when ok
  physics::Vec3 pred_t = physics::Vec3::Zero();  // when ok: the prediction's world translation (m)
  double pred_size = 0;                          // and its longest side (m)
  // When ok: the shape alone, pose left out: IoU of the sample's occupancy grid (R^3, the decoder's)
  // with the ground truth's filled occupancy at R in the same canonical voxel frame (world/voxelize.h:
  // the grids the model was trained on; the measure build_pairs --filter-gt uses). No symmetry search.
  double shape_iou = 0;
  std::string picture;         // path relative to the output folder ("" when none)
  // With EvalLiftOptions::refine: whether it changed the pose, else why not; the lifted pose's world
  // translation and longest side before it.
  bool refined = false;
  std::string refine_note;
  physics::Vec3 lifted_t = physics::Vec3::Zero();
  double lifted_size = 0;
  // The sample scored (index into the lift's samples) and, with EvalLiftOptions::select, every
  // sample's selection score (NaN for a sample that failed).
  int sample = 0;
  std::vector<double> sample_scores;
};

struct EvalLiftResult {
  std::vector<EvalObject> objects;
  std::vector<EvalRow> rows;   // scene by scene; within a scene by depth kind, model, object
  std::vector<std::string> depths, models;
  int scenes = 0;              // scenes generated
  double seconds_lift = 0, seconds_metrics = 0;
};

// The models: base (required unless gt_as_prediction) and compare (optional: base + another adapter).
struct EvalModels {
  Resampler* base = nullptr;
  Resampler* compare = nullptr;
};

// Runs the evaluation; pictures go to out_dir/pictures (out_dir must exist). Throws simu::Error for bad
// options (naming the flag), an unreadable mesh folder or file (naming it), or a world / held-out
// object that no scene could place in the visible range (naming it). Objects the lift fails on are rows
// with ok false and their error.
EvalLiftResult run_eval_lift(const EvalLiftOptions& options, const EvalModels& models, const std::string& out_dir);

// ---- Report (eval_lift_report.cpp) ----

// Aggregates of one set of rows: n (objects), n_failed, iou_mean, fscore_1cm, fscore_2cm (means; a
// failed lift counts 0), chamfer_mean, rot_err_deg_median, trans_err_median, scale_err_pct_median (over
// the lifted objects; null when none).
nlohmann::json aggregate_rows(const EvalLiftResult& result, const std::vector<const EvalRow*>& rows);

// summary.json: settings, models (adapters), and
//   buckets[depth][model][bucket]  for bucket in unoccluded, 70-100%, 40-70%, <40%, all (and heldout
//                                  when the objects are the held-out family's);
//   deltas[depth][bucket][metric]  with a compare model: {base, compare, delta, ci95: [lo, hi]} by the
//                                  paired bootstrap (options.bootstrap_resamples, seeded);
//   objects                        one row per object, depth and model.
// adapters: {base adapter dir, compare adapter dir} as given ("" = none).
nlohmann::json eval_summary(const EvalLiftResult& result, const EvalLiftOptions& options,
                            const std::pair<std::string, std::string>& adapters, const nlohmann::json& run_info = {});

// The buckets table (and the deltas) of a summary as text for the terminal.
std::string format_summary_table(const nlohmann::json& summary);

}  // namespace simu::resample
