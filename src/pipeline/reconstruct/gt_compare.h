// A reconstruction scored against the ground truth of a shape-world scene (`world scenes`' gt.json,
// docs/world.md): the world-frame voxel IoU of every object before the probe's correction (the
// pre-simulation scene: lifted and aligned) and after it (the probe's final scene), with what the probe
// did. `reconstruct --gt` and the demo print this table (docs/reconstruct.md, "Against ground truth").
//
//   WorldGt gt = load_world_gt("scene/gt.json");
//   auto rows = compare_with_gt(physics::load_scene("out/input/scene.json"),
//                               physics::load_scene("out/probe/scene.json"), probe_outcomes(report), gt);
//   fmt::print("{}", format_gt_table(rows));
//
// Frames: a scene's world maps to its camera by the scene camera's pose (reconstruct: the OpenCV camera,
// pose identity); gt.json's R_world_cam, t_world_cam map that same OpenCV camera into the world the
// ground truth lives in. An object placed by (R, s, t) in the scene world is placed by
// (Rg Rs^T R, s, Rg Rs^T (t - ts) + tg) in the GT world, and scored there as eval_lift scores lifted
// objects: physics::solid_iou of the filled occupancies on the world lattice, spacing
// min(max_voxel, GT size / voxels_across) (physics::shape_metrics' rule).
#pragma once

#include <nlohmann/json.hpp>

#include <map>
#include <optional>
#include <string>
#include <vector>

#include "pipeline/physics/scene.h"
#include "pipeline/physics/shape_metrics.h"

namespace simu::reconstruct {

// One ground-truth object: its canonical mesh placed in the GT world.
struct GtObject {
  std::string id, family;
  double visible_fraction = 1;
  physics::PlacedShape shape;
};

// A shape-world scene's ground truth: the camera (intrinsics and its pose in the GT world) and objects.
struct WorldGt {
  std::string path;
  physics::Camera camera;
  std::vector<GtObject> objects;
};

// Reads gt.json and every object's mesh (paths relative to its folder). Throws simu::Error naming the
// file and the key when it is malformed or a mesh cannot be read.
WorldGt load_world_gt(const std::string& gt_json);

// A scene object's pose carried from the scene's world into the GT world through the shared camera.
physics::PlacedShape placed_in_gt_world(const physics::Mesh& canonical, const physics::SceneObject& object,
                                        const physics::Camera& scene_camera, const physics::Camera& gt_camera);

// Each GT object's world AABB taken in the camera frame (x_cam = R_world_cam^T (x_world - t_world_cam)):
// the axis-aligned box of its placed mesh's vertices there, by id. reconstruct's scene world is that
// OpenCV camera, so these are the ground-truth boxes of the probe's 3D AABB IoU / ABO (`reconstruct
// --gt`; physics::box_metrics). Axis-aligned with the camera, not with gravity.
std::map<std::string, physics::Box3> gt_boxes_in_camera(const WorldGt& gt);

// Voxel IoU of a prediction and the ground truth, both in the GT world (shape_metrics' spacing rule).
double world_iou(const physics::PlacedShape& pred, const physics::PlacedShape& gt,
                 const physics::ShapeMetricsConfig& config = {});

// What the probe did to one object (its report.json entry).
struct ProbeOutcome {
  std::string branch;        // stretch | resample | anchored | disabled | ...
  bool resampled = false;    // the shape was replaced by a resampled candidate
  bool reverted = false;     // the final settle's motion was reverted
  bool forced = false;       // resampled only because decision.force_resample named it (flag forced_resample)
};
// By object id, from the probe's report.json content (objects without an id are left out).
std::map<std::string, ProbeOutcome> probe_outcomes(const nlohmann::json& probe_report);

// The scene with each object's pose replaced by where the probe's 5 s evaluation settle left it
// (report.json per object: "evaluation_input_pose" for the input scene when input, else
// "evaluation_pose" for the final scene), matched by id; objects without one keep their pose. Scored
// by compare_with_gt, this is the voxel IoU of the scenes the headline metrics score (`reconstruct
// --gt`: gt_iou_settled). Throws simu::Error naming the object when a pose is malformed.
physics::Scene settled_scene(const physics::Scene& scene, const nlohmann::json& probe_report, bool input);

// One GT object's row.
struct GtIouRow {
  std::string id, family;
  double visible_fraction = 1;
  ProbeOutcome probe;                   // branch "" when the probe did not report the object
  std::optional<double> before, after;  // unset when the object is not in that scene (or unusable)
  std::string note;                     // why a value is unset
};

// One row per GT object, in gt.json's order, matched by id with the scenes' objects (scene objects
// without a GT object, such as a lifted table, are left out).
std::vector<GtIouRow> compare_with_gt(const physics::Scene& before, const physics::Scene& after,
                                      const std::map<std::string, ProbeOutcome>& outcomes, const WorldGt& gt,
                                      const physics::ShapeMetricsConfig& config = {});

// {"gt": path, "objects": [{id, family, visible_fraction, branch, resampled, reverted, gt_iou_before,
// gt_iou_after, note}], "mean_before", "mean_after", "n"} (means over the rows; an unset value counts 0).
nlohmann::json gt_rows_json(const std::vector<GtIouRow>& rows, const std::string& gt_path);

// The rows as a text table with a mean line.
std::string format_gt_table(const std::vector<GtIouRow>& rows);

}  // namespace simu::reconstruct
