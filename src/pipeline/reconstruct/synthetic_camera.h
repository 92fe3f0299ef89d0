// Synthetic camera data for the reconstruct front end: a scene of physics/synthetic.h's generator
// (floor, back wall, a table with objects on it, hanging frames / clocks) with a second (left) wall,
// rendered as a camera gives it: a shaded RGB image, visible instance masks of every object, base,
// wall and the floor, a depth map and K; with the ground truth in the camera frame, and SAM 3D-like
// errors injected into the "lifted" poses for the bring-your-own-lift path:
//   scale   s_lift = s_gt * (1 + e), |e| uniform in [scale_err_min, scale_err_max], random sign
//   ray     t_lift = t_gt + d * t_gt / |t_gt|, |d| uniform in [ray_err_min, ray_err_max] * |t_gt|
//   rotation  R_lift = R(axis, a) R_gt, a uniform in [0, rotation_err_max_deg], random axis
// Frame: everything is in the OpenCV camera frame (the frame of src/pipeline/reconstruct, types.h).
#pragma once

#include "pipeline/physics/synthetic.h"
#include "pipeline/reconstruct/planes.h"
#include "pipeline/reconstruct/types.h"

#include <cstdint>
#include <string>
#include <vector>

namespace simu::reconstruct {

struct CameraSceneConfig {
  physics::SyntheticConfig generator;  // layout forced to "tabletop"
  double left_wall_x = -1.1;            // world x of the left wall (normal +x)
  double scale_err_min = 0.10, scale_err_max = 0.25;
  double ray_err_min = 0.01, ray_err_max = 0.05;  // fraction of the object's distance
  double rotation_err_max_deg = 2;
  double table_scale_err = 0.05, table_rotation_err_deg = 3, table_lift_m = 0.03;
  CameraSceneConfig() {
    generator.layout = "tabletop";
    generator.max_hanging = 2;
  }
};

// One object as the reconstruct front end sees it (bases included, is_base set).
struct CameraObject {
  std::string id, label;
  physics::PoseDof dof = physics::PoseDof::Free;
  bool is_base = false;
  Points canonical;  // ground-truth canonical mesh (AABB-centred, longest side 1)
  Faces faces;
  // Ground truth (camera frame): world = R (scale .* c) + t.
  Vec3 gt_scale = Vec3::Ones();
  Mat3 gt_R = Mat3::Identity();
  Vec3 gt_t = Vec3::Zero();
  // The "lifted" pose with the injected errors.
  Vec3 lift_scale = Vec3::Ones();
  Mat3 lift_R = Mat3::Identity();
  Vec3 lift_t = Vec3::Zero();
  double scale_error = 1;     // lift / gt scale factor
  double ray_error = 0;       // m along the ray
  double rotation_error = 0;  // degrees
  Mask mask;                  // visible (modal) mask in the joint render
  int64_t amodal_pixels = 0;  // pixels of its silhouette alone
  int label_value = 0;        // its value in CameraScene::labels
};

struct CameraScene {
  physics::SyntheticScene source;     // the generator's scene (world frame, y down)
  Pinhole K;
  Mat3 R_world_cam = Mat3::Identity();  // of the source scene
  Vec3 t_world_cam = Vec3::Zero();
  std::vector<uint8_t> rgb;             // [H, W, 3] shaded render
  std::vector<int32_t> labels;          // [H, W]: 0 background, 1 floor, 2 back wall, 3 left wall, 4 + i object i
  std::vector<float> depth;             // [H, W] camera z (m), +inf = nothing
  PointMap points;                      // the depth unprojected (camera frame)
  NamedPlane floor, back_wall, left_wall;  // ground truth, camera frame
  Vec3 up = -Vec3::UnitY();             // ground-truth up (camera frame)
  std::vector<CameraObject> objects;    // bases first, then the generator's objects
  Mask mask_of_label(int value) const;
};

CameraScene generate_camera_scene(const CameraSceneConfig& config, uint64_t seed, const std::string& name);

// Writes the inputs of the `reconstruct` program into dir: image.png, labels.png (16-bit), objects.json
// (the sidecar: per label value the object id, label, dof, pins, base flag, its "lift" mesh + pose, its
// canonical up axis),
// depth.png (16-bit millimetres), K.json, lift/<id>.obj (canonical ground-truth mesh) and
// lift/<id>.json (its erroneous pose in SAM 3D's convention, see sam3d_pose_from_scene), truth.json.
void write_camera_scene(const CameraScene& s, const std::string& dir);
// The part of write_camera_scene that needs no image I/O: K.json, objects.json, lift/, truth.json.
void write_camera_scene_lift(const CameraScene& s, const std::string& dir);
// The canonical up axis of a generated object's mesh ("-y", clocks "+z": their lathe axis is horizontal).
std::string canonical_up_axis(const CameraObject& o);

// SAM 3D's pose convention (PyTorch3D camera, row vectors p = (scale * v) @ R + translation with
// R = the quaternion's matrix, v the mesh vertex) <-> the scene convention in the OpenCV camera.
struct Sam3dPose {
  Eigen::Vector4d rotation_wxyz = Eigen::Vector4d(1, 0, 0, 0);
  Vec3 translation = Vec3::Zero();
  Vec3 scale = Vec3::Ones();
};
// A scene pose (world = R (s .* c) + t, camera frame) of mesh vertices c -> SAM 3D's pose of the same
// vertices.
Sam3dPose sam3d_pose_from_scene(const Mat3& R, const Vec3& scale, const Vec3& t);
// SAM 3D's pose of mesh vertices v (any frame of the mesh file) -> the scene pose of the canonical
// mesh c = (v - centre) * factor (AABB-centred, longest side 1; centre and factor of the vertices).
struct ScenePoseOut {
  Mat3 R = Mat3::Identity();
  Vec3 scale = Vec3::Ones();
  Vec3 t = Vec3::Zero();
};
ScenePoseOut scene_pose_from_sam3d_mesh(const Sam3dPose& pose, const Vec3& centre, double factor);

}  // namespace simu::reconstruct
