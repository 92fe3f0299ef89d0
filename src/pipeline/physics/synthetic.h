// Synthetic scenes with known ground truth for the probe's benchmark and tests: tabletop or shelf
// clutter of primitives (boxes, cylinders) and lathe meshes (bottles, bowls), some objects hanging on
// the back wall, rendered modal masks (and optionally depth), and an injected monocular error per
// object (hovering / sinking offset, bottom cut off as under occlusion, scale error, small rotation)
// recorded with the correction branch it should trigger.
//
// World frame: y points down (gravity [0, 1, 0]), the floor is the plane y = floor_y, the back wall
// z = wall_z faces the camera; the camera sits at the origin pitched down by camera_pitch_deg.
// Each object's canonical mesh is AABB-centred with longest side 1, canonical y is its up/down axis.
#pragma once

#include "pipeline/physics/geometry.h"
#include "pipeline/physics/metrics.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/raster.h"
#include "pipeline/physics/scene.h"

#include <cstdint>
#include <random>
#include <string>
#include <vector>

namespace simu::physics {

// What was done to an object's reconstruction.
enum class InjectedError { None, Hover, Sink, BottomCut, Scale, Rotation };
const char* to_string(InjectedError e);
std::optional<InjectedError> parse_injected_error(const std::string& s);
// The branch the paper's criterion should pick for a free object with this error: BottomCut ->
// Resample (the cut leaves the object hovering by >= 25% of its remaining height), the others
// (kept below rho = 0.15 by construction) -> Stretch.
Branch expected_branch(InjectedError e);

// Generator parameters.
struct SyntheticConfig {
  std::string layout = "tabletop";  // "tabletop" | "shelf" | "mixed" (alternates by seed)
  int min_objects = 4, max_objects = 8;  // free objects
  int min_hanging = 0, max_hanging = 2;  // wall-anchored objects (min..max)
  int placement_attempts = 60;           // rejection-sampling tries per free object (one that does not fit is left out)
  bool floor_supports = false;           // tabletop: objects may also stand on floor strips left and right of the table
  int width = 320, height = 240;
  double fx = 280;                       // fy = fx, principal point at the image centre
  double camera_pitch_deg = 15;
  bool write_depth = false;              // 16-bit PNG depth (millimetres) of the ground-truth render
  // Error mix (relative weights) and magnitudes.
  double w_none = 1, w_hover = 2, w_sink = 2, w_cut = 2, w_scale = 1.5, w_rotation = 1.5;
  double hover_min = 0.03, hover_max = 0.12;  // offset as a fraction of the object height
  double cut_min = 0.2, cut_max = 0.6;        // removed fraction of the height
  double scale_min = 0.85, scale_max = 1.15;  // isotropic scale factor
  double rotation_max_deg = 5;
  static SyntheticConfig from(simu::config::Reader& r);
};

// One generated object: ground truth and the erroneous reconstruction the probe receives.
struct SyntheticObject {
  std::string id, label;
  PoseDof dof = PoseDof::Free;
  Mesh gt_mesh;                 // canonical ground-truth mesh
  Vec3 gt_scale = Vec3::Ones();
  Mat3 gt_R = Mat3::Identity();
  Vec3 gt_t = Vec3::Zero();
  Mesh pred_mesh;               // canonical reconstructed mesh (the cut one for BottomCut)
  Vec3 pred_scale = Vec3::Ones();
  Mat3 pred_R = Mat3::Identity();
  Vec3 pred_t = Vec3::Zero();
  InjectedError error = InjectedError::None;
  double magnitude = 0;         // hover/sink: metres; cut: fraction; scale: factor; rotation: degrees
  double support_y = 0;         // y of the surface the ground truth rests on (free objects)
  BinaryMask modal_mask;        // visible ground-truth mask (bottom hidden for BottomCut)
  Box3 gt_box;                  // world AABB of the ground truth
  std::string wall_id;
};

// A fixed base (table, shelf board) as a world-placed canonical mesh.
struct SyntheticBase {
  std::string id;
  Mesh mesh;
  Vec3 scale = Vec3::Ones();
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
};

struct SyntheticScene {
  std::string name;
  std::string layout;
  Camera camera;
  Vec3 gravity = Vec3(0, 1, 0);
  Plane floor;
  std::vector<Plane> walls;
  std::vector<SyntheticBase> bases;
  std::vector<SyntheticObject> objects;
  std::vector<float> depth;  // ground-truth depth (camera z, metres; +inf = background), width*height
};

// Generates one scene (deterministic for a given config and seed).
SyntheticScene generate_scene(const SyntheticConfig& config, uint64_t seed, const std::string& name);

// The ground truth rendered from the scene's camera: bases first (labels 0..B-1), then the objects
// (B..), each at its true pose. When `world` is given it receives the placed meshes in that order.
LabelImage render_truth_labels(const SyntheticScene& s, std::vector<Mesh>* world = nullptr);

// Builds the probe's input Scene (reconstructed poses; paths relative to dir as write_scene_dir
// lays them out). Each object's `extra["synthetic"]` records the error, its magnitude, the expected
// branch and the ground-truth pose/mesh.
Scene to_probe_scene(const SyntheticScene& s, const std::string& dir);

// Writes dir/scene.json, dir/meshes/*.obj (reconstructed and ground-truth), dir/masks/*.png,
// dir/depth.png (when depth is present) and dir/rgb.png (the ground-truth label render, coloured).
void write_scene_dir(const SyntheticScene& s, const std::string& dir);

// Reads a scene written by write_scene_dir back (dir/scene.json with its "synthetic" records, meshes,
// masks): the inverse of write_scene_dir up to depth. Throws simu::Error naming the file and the
// object when a record, mesh or mask is missing. Masks need OpenCV.
SyntheticScene load_synthetic_scene(const std::string& scene_json);

// Canonical primitive meshes (AABB-centred, longest side 1, up = canonical y):
Mesh canonical_box_mesh(const Vec3& extents);  // normalised box of these proportions
// A surface of revolution about canonical y from a radius profile (heights top to bottom, in y-down
// order), closed with caps; normalised.
Mesh lathe_mesh(const std::vector<std::pair<double, double>>& y_radius, int segments = 24);
// Rescales a mesh to the canonical convention; returns the longest side it had (the scale factor
// that restores its size).
double normalise_canonical(Mesh& m);
// Writes a Wavefront OBJ (vertices and triangles) atomically.
void write_obj(const std::string& path, const Mesh& m);

// ---- Benchmark support -------------------------------------------------------------------------

// The ideal probe measurement for a free synthetic object (used until / besides the MuJoCo probe):
// the reconstructed object moved along gravity until its lowest vertex meets its ground-truth support
// (other objects ignored). A sinking object gets the push out as dt_pen (against gravity), a hovering
// one the fall as dt_grv (along gravity).
struct Displacement {
  Vec3 dt_pen = Vec3::Zero();
  Vec3 dt_grv = Vec3::Zero();
};
Displacement oracle_displacement(const SyntheticScene& s, const SyntheticObject& o);

// Per free object: injected error, expected and chosen branch, rho / eta.
struct ObjectOutcome {
  std::string id;
  InjectedError error = InjectedError::None;
  Branch expected = Branch::Stretch, got = Branch::Stretch;
  bool decided = true;       // false: no stretch-or-resample decision was made (physics-disabled,
                             // decision failed); `got` is then meaningless and counts as wrong
  double rho = 0, eta = 0;
  double support_gap_before = 0, support_gap_after = 0;  // |lowest point - support| (metres)
  std::vector<std::string> flags;  // the probe's flags for the object (physics_disabled, reverted, ...)
};

// What stands in for the resampler in the benchmark (it lives in another component):
//   Stretch: the gravity-axis stretch applied anyway (the object fills B_str; the paper's "Stretched"
//            baseline), Drop: moved by the measured displacement only (layout-only fix),
//   Keep: left as reconstructed (oracle only: the physics probe always moves an object).
enum class ResampleProxy { Stretch, Drop, Keep };
std::optional<ResampleProxy> parse_resample_proxy(const std::string& s);

// One object after the correction, as the benchmark scores it: world geometry R (scale .* mesh) + t.
struct CorrectedObject {
  Mesh mesh;                   // canonical mesh used (empty: the input reconstruction's pred_mesh)
  Vec3 scale = Vec3::Ones();
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
  bool valid = true;           // false: physics-disabled or unusable (zeroed by the strict fh/fo variants)
  bool decided = true;         // free objects: a stretch-or-resample decision was made
  Branch branch = Branch::Stretch;
  double rho = 0, eta = 0;
  std::vector<std::string> flags;
};

// Before/after scores of one scene: "before" is the reconstruction as given (injected errors, every
// object valid), "after" the corrected objects. Overlap metrics are over all objects; the masks are
// rendered jointly from the camera with the bases as occluders; 3D boxes are the world AABBs of the
// placed meshes against SyntheticObject::gt_box.
struct SceneEvaluation {
  std::vector<ObjectOutcome> objects;  // free objects, in scene order
  OverlapMetrics mask_before, mask_after, box_before, box_after;
};
// Scores `after` (one per SyntheticScene::objects index) against the ground truth.
SceneEvaluation evaluate_corrected(const SyntheticScene& s, const std::vector<CorrectedObject>& after);

// The idealised correction without simulation: each free object diagnosed from its displacement
// (displacements[i]; empty: the oracle drop to its known support) and corrected in isolation from
// its input pose (stretch branch: the gravity-axis stretch; resample branch: the proxy); hanging
// objects unchanged. No penetration resolution between objects, no joint settle.
SceneEvaluation evaluate_scene(const SyntheticScene& s, const CorrectionConfig& config,
                               const std::vector<Displacement>& displacements = {},
                               ResampleProxy proxy = ResampleProxy::Stretch);

// The physics probe's output for a synthetic scene (run_probe on to_probe_scene / the written scene,
// objects in the same order): per object the corrected scene's pose and scale (ProbeResult::scene:
// after the stretch or the resampler, the final penetration resolution and the joint settle) with
// the mesh it uses (ProbeResult::meshes: stretched or resampled). The decision is the probe's own
// (Diagnostics::branch, rho, eta). Handled as the probe leaves them:
//   physics-disabled objects: the probe restores their input pose (and mesh); scored there, invalid,
//     no decision (counted as a wrong decision by synth_bench);
//   reverted objects (diverged in the final settle, or a solver reset): their pre-settle pose, valid;
//   resample-branch objects without a resampler: the input mesh where the diagnostic left it
//     (dropped / pushed out), then through the final composition;
//   unusable meshes (bad input, mesh error): the input reconstruction at its input pose, invalid.
std::vector<CorrectedObject> probe_output_objects(const SyntheticScene& s, const ProbeResult& r);
// evaluate_corrected(s, probe_output_objects(s, r)).
SceneEvaluation evaluate_probe_output(const SyntheticScene& s, const ProbeResult& r);

// The --resample-proxy stretch as a resampler for run_probe: for each request, the object's input
// mesh stretched along gravity so that, placed by the probe at the request's target OBB centre, it
// fills B_str (the paper's "Stretched" baseline in place of a learned resampler).
ResampleFn stretch_resampler(const SyntheticScene& s, const CorrectionConfig& config = {});

}  // namespace simu::physics
