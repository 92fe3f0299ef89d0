// The physics-in-the-loop probe (paper Sec. 3.3-3.5, supplementary "Gravity-Based Diagnostics",
// "Sequential Composition"), on MuJoCo 2.2.
//
// run_probe():
//  1. loads meshes, builds cached convex collision hulls, flags bad objects (missing/degenerate
//     mesh, bad pose, outside the room) without stopping;
//  2. orders objects ascending by the lowest world-AABB corner along gravity;
//  3. per object (earlier ones static colliders, the active one dynamic): penetration resolution
//     (contacts grouped environment first; push by max depth + 7 mm along the depth-weighted mean
//     normal; <= 200 iterations; > 0.3 m in total or a surviving contact -> physics-disabled);
//     gravity diagnostics (free: fall until first contact -> dt_grv; point/line anchored: connect
//     constraints at the top-back pins, simulated until settled -> dR_grv, dt_grv);
//     decision (rho >= 0.15 -> resample, else gravity-axis stretch; anchored keep their geometry;
//     ProbeConfig::force_resample names objects resampled regardless of rho);
//  4. hands every object needing resampling to the ResampleFn in one call (or writes the hand-off);
//  5. final composition: sequential penetration resolution on the corrected objects, then one
//     joint settle (free objects 6-DoF, anchored ones on their pins) for T_settle; objects moving
//     more than the divergence bound are reverted to their pre-settle pose;
//  6. evaluation settle of the final scene (5 s, supplementary "Metrics"): per-object SettleRecords
//     and the PhysicsMetrics;
//  7. writes DIR/scene.json (+ DIR/meshes/), DIR/scene.xml (standalone MJCF), DIR/report.json and,
//     built with OpenCV, DIR/overlay.png (per object: modal mask, or its rendered visible mask when
//     it has none; pre-simulation OBB solid, target OBB dashed; auxiliary crop mask M' outlined).
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/core.hpp>
#endif

#include "common/config.h"
#include "pipeline/physics/collision.h"
#include "pipeline/physics/geometry.h"
#include "pipeline/physics/metrics.h"
#include "pipeline/physics/mjcf.h"
#include "pipeline/physics/scene.h"

namespace simu::physics {

#ifdef SIMU_HAVE_OPENCV
using MaskImage = cv::Mat;  // CV_8UC1, non-zero = inside
#else
// An 8-bit single-channel image, row-major, non-zero = inside.
struct MaskImage {
  int width = 0, height = 0;
  std::vector<uint8_t> data;
  bool empty() const { return data.empty(); }
};
#endif


// What the probe did with an object (the stretch/resample decision itself is geometry.h's Branch).
enum class ProbeBranch { None, Stretch, Resample, Anchored, Disabled };
const char* to_string(ProbeBranch b);

// The numbers the diagnostic simulation produces for one object (and the decision made from them).
struct Diagnostics {
  int order = -1;                 // position in the sequential order (-1: not simulated)
  ProbeBranch branch = ProbeBranch::None;
  bool physics_disabled = false;
  std::vector<std::string> flags; // e.g. "bad_input", "mesh_error", "outside_room", "physics_disabled",
                                  // "no_support", "solver_reset", "needs_resample", "resample_failed",
                                  // "reverted", "not_canonical", "forced_resample"
  std::string message;            // human-readable reasons
  // Pre-simulation pose (as read).
  Vec3 t_pre = Vec3::Zero();
  Mat3 R_pre = Mat3::Identity();
  Vec3 s_pre = Vec3::Ones();
  // Penetration resolution.
  Vec3 dt_pen = Vec3::Zero();
  int pen_iterations = 0;
  double pen_max_depth = 0;       // deepest contact at the start (m)
  // Gravity diagnostics.
  Vec3 dt_grv = Vec3::Zero();
  Mat3 dR_grv = Mat3::Identity();
  double sim_time = 0;            // simulated seconds until first contact / settled
  std::vector<Vec3> pins_world;   // object-side pins (anchored)
  std::vector<Vec3> wall_points;  // their wall mates (feet of the perpendiculars)
  std::string wall_id;
  // Decision (geometry.h): the OBB of the pre-simulation object (diagnosis.obb_pre), its axis most
  // aligned with gravity (diagnosis.axis: u oriented so u.g >= 0, l_pre its side length), rho, eta
  // and the stretch/resample branch; untouched (axis.length 0) for an object never diagnosed.
  Diagnosis diagnosis;
  Obb obb_target;         // desired stretched OBB (stretch and resample)
  // Final composition.
  Vec3 dt_final_pen = Vec3::Zero();
  double settle_displacement = 0; // m, during the joint settle
  bool reverted = false;
  SettleRecord final_settle;      // the final joint settle (T_settle) of this object
  SettleRecord evaluation;        // the metrics settle (metrics_settle_time) of the final scene
  // Resampling (branch Resample with a resampler): what the resampler returned and where it went.
  struct Candidate {
    std::string label;            // the resampler's name for it (e.g. "sample 1 (seed 0)")
    bool ok = false;              // placed, penetration resolved and settled without failure
    double displacement = 0;      // m: penetration push + settle motion of the candidate (stability figure)
    double rotation_deg = 0;      // rotation during the candidate's settle
    double penetration = 0;       // m: deepest contact where it was placed
    std::string message;          // why not ok
    Mesh world;                   // the candidate placed at the target OBB centre (world frame; pictures)
  };
  bool resampled = false;         // the object's geometry was replaced by the resampler's
  std::string resample_message;   // the resampler's note for this object
  std::vector<Candidate> candidates;  // best-of-N: every candidate's stability (empty for one)
  int chosen_candidate = -1;      // index into candidates (best-of-N)
  std::array<int, 4> crop_box{{0, 0, 0, 0}};  // condition crop box [x1, y1, x2, y2) (pixels), when reported
  bool has_crop_box = false;
  Vec3 t_resampled = Vec3::Zero();  // pose the resampled shape was placed at (before the final composition)
  Mat3 R_resampled = Mat3::Identity();
  Vec3 s_resampled = Vec3::Ones();
  Obb obb_final;                  // OBB of the object in its final pose (every usable object)
};

// One object handed to the resampler.
struct ProbeResampleRequest {
  int object_index = -1;         // index into Scene::objects
  std::string object_id;
  std::string image_path;
  std::string mask_path;
  MaskImage modal_mask;          // M_i (empty if the scene has none)
  MaskImage aux_mask;            // M'_i = M_i united with the projected lowest part of the stretched OBB
  Obb target_obb;        // desired stretched OBB; its centre becomes the translation
};

// One candidate shape for an object (best-of-N).
struct ProbeShapeCandidate {
  std::string label;
  Mesh mesh;                     // canonical (AABB-centred, longest side 1)
  Mat3 R = Mat3::Identity();     // world rotation
  Vec3 scale = Vec3::Ones();
};

struct ProbeResampleResult {
  bool ok = false;
  std::string message;
  Mesh mesh;                     // canonical (AABB-centred, longest side 1)
  Mat3 R = Mat3::Identity();
  Vec3 scale = Vec3::Ones();
  // Best-of-N: with two or more candidates, the probe settles each one at the target OBB centre with the
  // objects before it static, keeps the one that moves least (no failed penetration resolution; when
  // none settles, the one that penetrated least, flagged "no_stable_candidate"), and ignores mesh/R/scale above. Empty or one candidate: mesh/R/scale are used as they are.
  std::vector<ProbeShapeCandidate> candidates;
  // The condition crop box [x1, y1, x2, y2) in image pixels (reported; optional).
  std::array<int, 4> crop_box{{0, 0, 0, 0}};
  bool has_crop_box = false;
};

// Called once per scene with every object that needs resampling; returns one result per request.
using ResampleFn = std::function<std::vector<ProbeResampleResult>(const std::vector<ProbeResampleRequest>&)>;

struct ProbeConfig {
  PhysicsConfig physics;
  CollisionConfig collision;
  double rho_threshold = 0.15;     // rho >= this selects resampling
  // Object ids resampled whatever their rho (not in the paper; to show or study the resampling branch on
  // objects the rule stretches, e.g. the demo's showcase). Only free objects that reach the decision
  // (simulated, gravity diagnostics on) are affected; each gets the flag "forced_resample" and the same
  // hand-off as a triggered one (target OBB B_str from its rho/eta, crop mask M'). An id that names no
  // object of the scene is an error (run_probe). Empty: the paper's rule alone.
  std::vector<std::string> force_resample;
  double push_extra = 0.007;       // m added to the deepest contact per push
  int max_pen_iterations = 200;
  double max_pen_total = 0.3;      // m
  double pen_tolerance = 2e-4;     // m: a contact penetrates when dist < -pen_tolerance
  double max_fall_time = 2.0;      // s without contact -> "no_support"
  double settle_max_time = 3.0;    // s, anchored diagnostics
  double settle_speed = 2e-3;      // m/s and rad/s below which a body counts as settled
  double settle_hold_time = 0.1;   // s the speed must stay below settle_speed
  double final_settle_time = 2.0;  // T_settle (s)
  double settle_window = 0.25;     // s: the final settle stops early once, over one window, ...
  double settle_rest_distance = 1e-3;  // ... no body moved more than this (m)
  double divergence_bound = 0.25;  // m: larger final-settle motion is reverted
  double candidate_settle_time = 1.0;  // s: settle of each best-of-N candidate (stops early at rest)
  double pin_region = 0.1;         // top-back pin region, fraction of the object's extent
  // The gravity diagnostics (Sec. 3.4) and the decision they feed (stretch or resample). false:
  // sequential penetration resolution only, every object kept at its pushed pose with its input shape
  // (branch "none"), then the final pass as usual: the "+ Pen." row of the paper's ablation.
  bool gravity_diagnostics = true;
  // Evaluation (supplementary "Metrics"): a gravity settle of the final scene for this long (paper:
  // 5 s; 0 = none, the metrics then come from the final settle). It stops early once, over one
  // settle_window, no body moved more than metrics_rest_distance.
  double metrics_settle_time = 5.0;
  double metrics_rest_distance = 1e-4;
  MetricsConfig metrics;           // stability / penetration thresholds (5 cm, 2 mm)
  bool write_outputs = true;       // scene.json, meshes, scene.xml, report.json, hand-off, pictures
  bool overwrite = false;          // replace an existing output folder (else refused)
  // Headline metrics (ABO, IoU and their fh/fo variants) also for the input scene settled the same
  // way ("before" column). Costs one more evaluation settle.
  bool evaluate_input = true;

  // Typed, strict reading (configs/probe.yaml; common/config.h): every key below, unknown keys and
  // wrong types are errors naming the file and the key, values outside their domain too.
  static ProbeConfig from(simu::config::Reader& r);
  // Loads a config file (empty path: the defaults) with "a.b=value" overrides applied (--set).
  static ProbeConfig load(const std::string& path, const std::vector<std::string>& overrides = {});
  // Throws simu::Error naming the key of the first value outside its domain.
  void validate() const;
  // Every config key with its current value and its documentation, in file order ("physics.timestep").
  struct KeyDoc {
    std::string key, value, doc;
  };
  std::vector<KeyDoc> describe() const;
};

// A joint gravity settle of a scene (free objects 6-DoF, anchored ones on their pins) with the
// paper's physics metrics over it.
struct PhysicsEvaluation {
  bool ran = false;                   // false: nothing to simulate (or the model did not compile)
  std::vector<SettleRecord> objects;  // per Scene::objects index (unsimulated ones: physics_disabled)
  std::vector<Vec3> t;                // per object: position after the settle (input pose if unsimulated)
  std::vector<Mat3> R;
  PhysicsMetrics metrics;
  double scene_peak_energy = 0;       // J: max over time of the total kinetic energy
  double simulated_time = 0;          // s simulated
  double seconds = 0;                 // wall time
  bool solver_reset = false;          // MuJoCo reset the data (bad qacc): poses are the initial ones
  std::string message;
};

// The paper's headline numbers for one settled scene (supplementary "Metrics"): 2D IoU / ABO of the
// jointly rendered visible masks against the input masks, their strict fh / fo variants (an object
// penetrating > 2 mm, physics-disabled or unstable scores 0), 3D AABB IoU / ABO where the scene has
// ground-truth boxes, and the physics metrics (stability, penetration ratio, D_mean, E_pk).
struct HeadlineMetrics {
  bool computed = false;
  PhysicsMetrics physics;
  OverlapMetrics mask;       // n_gt = number of objects with an input mask
  OverlapMetrics box;        // n_gt = number of objects with a ground-truth box
  bool has_masks = false, has_boxes = false;
};
// Scores a settled scene: world meshes (nullptr: no geometry, scores 0), the settle's records, the
// scene's masks (SceneObject::mask_path) and boxes (SceneObject::gt_box).
HeadlineMetrics headline_metrics(const Scene& scene, const std::vector<const Mesh*>& world_meshes,
                                 const PhysicsEvaluation& settle, const MetricsConfig& config);
// A before/after table of the headline metrics for people (one line per metric).
std::string format_headline(const HeadlineMetrics& before, const HeadlineMetrics& after, double settle_time);
nlohmann::json headline_json(const HeadlineMetrics& m);

// Progress of one object (for a progress line per object).
using ProbeProgress = std::function<void(int done, int total, const std::string& object_id, const std::string& status)>;

struct ProbeResult {
  Scene scene;                      // corrected scene (mesh paths point into out_dir when written)
  // Per Scene::objects index: the canonical mesh the corrected scene uses (the input mesh, its
  // gravity-axis stretch when the stretch changed it, or the resampled shape); empty when the
  // object's mesh could not be used (bad input, mesh error). With scene's pose and scale this is
  // the output object, written or not.
  std::vector<Mesh> meshes;
  std::vector<Diagnostics> diagnostics;  // per Scene::objects index
  std::vector<int> order;           // object indices in sequential order
  std::vector<ProbeResampleRequest> resample_requests;
  std::string mjcf;                 // final MJCF text
  PhysicsEvaluation evaluation;     // metrics settle of the final scene (report.json "metrics")
  PhysicsEvaluation input_evaluation;  // the input scene settled the same way (cfg.evaluate_input)
  HeadlineMetrics before, after;    // headline metrics of input_evaluation / evaluation
  std::vector<std::string> pictures;  // files written next to the report (absolute paths in the final folder)
  double seconds_probe = 0, seconds_resample = 0, seconds_final = 0, seconds_metrics = 0;
};

// Runs the whole probe on a scene. out_dir may be "" (nothing written). Never throws for a bad
// object (it is flagged); throws simu::Error only when the scene as a whole is unusable or
// cfg.force_resample names an object the scene does not have.
ProbeResult run_probe(const Scene& scene, const ProbeConfig& cfg, const std::string& out_dir,
                      const ResampleFn& resampler = nullptr, const ProbeProgress& progress = nullptr);

// Per-object report as JSON (what report.json holds): per object the diagnostics and the
// "final_settle" / "evaluation" SettleRecords; "metrics": the PhysicsMetrics of the evaluation.
nlohmann::json report_json(const ProbeResult& r);

// Physics metrics of a scene as it is (no probe, no correction): reads and decomposes the meshes,
// pins anchored objects to their walls (choose_pins at the given pose), then settles every usable
// object jointly for settle_time (< 0: cfg.metrics_settle_time) and records each one. Bad objects
// are physics_disabled records. This is the "before" column of the synthetic benchmark.
PhysicsEvaluation evaluate_physics(const Scene& scene, const ProbeConfig& cfg, double settle_time = -1);

// JSON of one SettleRecord / of PhysicsMetrics.
nlohmann::json settle_json(const SettleRecord& r);
nlohmann::json metrics_json(const PhysicsMetrics& m);


// Pieces exposed for tests and for the geometry half.
// Ordering key: max over the 8 world-AABB corners of g.x (larger = lower); objects sort by its negation.
double lowest_corner_along_gravity(const Mesh& world, const Vec3& gravity);
// Object-side pins (top-back region; 1: highest, most centred; 2: leftmost and rightmost along the
// wall-parallel horizontal) for a world mesh hanging on a wall.
std::vector<Vec3> choose_pins(const Mesh& world, const Plane& wall, const Vec3& gravity, int count, double region);

}  // namespace simu::physics
