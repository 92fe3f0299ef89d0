// Scene model of the physics probe: camera, masks, gravity, floor/walls, fixed bases and the
// per-object canonical meshes with their poses. Loaded from and saved to the JSON scene file
// documented in docs/scene_format.md.
//
// Conventions (shared by geometry, metrics, probe and the resampler hand-off):
// - An object's canonical mesh is AABB-centred with longest side 1 (SAM3D convention).
// - Its world vertices are x = R * (s .* v) + t, where s is a per-axis scale in the canonical
//   frame (the paper's isotropic s_i; a gravity-axis stretch folds into it, so it is a 3-vector).
// - The world frame is the scene's; by default the camera frame is the world frame
//   (camera.R_world_cam = I, t_world_cam = 0; OpenCV camera: x right, y down, z forward).
// - Planes (floor, walls) are {point, normal}; the normal points into the free space of the room.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include <optional>
#include <string>
#include <vector>

namespace simu::physics {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;

// A triangle mesh: V [n, 3] vertex positions, F [m, 3] vertex indices (counter-clockwise seen from
// outside for closed meshes).
struct Mesh {
  Eigen::Matrix<double, -1, 3, Eigen::RowMajor> V;
  Eigen::Matrix<int, -1, 3, Eigen::RowMajor> F;
  bool empty() const { return V.rows() == 0 || F.rows() == 0; }
};

// Pinhole camera: intrinsics in pixels, image size, and its pose in the world
// (p_world = R_world_cam * p_cam + t_world_cam; p_cam in OpenCV convention, z forward).
struct Camera {
  double fx = 0, fy = 0, cx = 0, cy = 0;
  int width = 0, height = 0;
  Mat3 R_world_cam = Mat3::Identity();
  Vec3 t_world_cam = Vec3::Zero();
  bool valid() const;
};

// An infinite plane through `point` with unit `normal` pointing into the room's free space.
struct Plane {
  std::string id;
  Vec3 point = Vec3::Zero();
  Vec3 normal = Vec3::UnitZ();
  // Signed distance of x from the plane (positive on the free side).
  double distance(const Vec3& x) const { return normal.dot(x - point); }
};

// The pose-DoF tag from the VLM: free (6-DoF), point-anchored (one pin, 3-DoF rotation about a
// wall point), line-anchored (two pins, 1-DoF rotation about the line through them).
enum class PoseDof { Free, PointAnchored, LineAnchored };
const char* to_string(PoseDof d);
// Parses "free", "point_anchored", "line_anchored" (also "point-anchored", "line-anchored").
std::optional<PoseDof> parse_pose_dof(const std::string& s);
// Number of wall pins of a tag (0, 1, 2).
int pin_count(PoseDof d);

// A world-frame axis-aligned box (ground truth for the 3D IoU/ABO metrics).
struct Box3 {
  Vec3 min = Vec3::Zero();
  Vec3 max = Vec3::Zero();
};

// A fixed collider (table, shelf): a mesh placed like an object, never moved.
struct BaseBody {
  std::string id;
  std::string mesh_path;  // absolute after load
  Vec3 scale = Vec3::Ones();
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
  std::string error;  // non-empty when this entry could not be parsed (it is then skipped)
};

// One reconstructed object.
struct SceneObject {
  std::string id;
  std::string label;         // free-form class name (optional)
  std::string mesh_path;     // canonical mesh (OBJ/PLY/GLB), absolute after load
  std::string mask_path;     // modal mask image (non-zero = object), absolute after load; optional
  Vec3 scale = Vec3::Ones(); // s (per canonical axis)
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
  PoseDof dof = PoseDof::Free;
  std::string wall_id;       // wall to anchor to (anchored objects); empty = nearest wall
  double density = 500.0;    // kg/m^3, for mass and inertia from the collision hulls
  std::optional<Box3> gt_box;  // ground-truth world AABB (optional)
  nlohmann::json extra;      // any unknown keys of the entry, passed through on save
  std::string error;         // non-empty when the entry is unusable (bad pose, missing field...)

  // The linear part R * diag(s) of the canonical-to-world map.
  Mat3 linear() const { return R * scale.asDiagonal(); }
  // Canonical point -> world point.
  Vec3 to_world(const Vec3& v) const { return R * scale.cwiseProduct(v) + t; }
};

// A whole scene.
struct Scene {
  std::string path;        // file it was loaded from (empty if built in memory)
  std::string image_path;  // RGB image, absolute after load; optional
  std::string depth_path;  // depth or point map (optional)
  Camera camera;
  Vec3 gravity = -Vec3::UnitZ();  // unit direction of gravity in the world
  double gravity_magnitude = 9.81;
  std::optional<Plane> floor;
  std::vector<Plane> walls;
  std::vector<BaseBody> bases;
  std::vector<SceneObject> objects;
  nlohmann::json extra;  // unknown top-level keys, passed through

  // Index of the object with this id, or -1.
  int find_object(const std::string& id) const;
};

// Places a canonical mesh in the world with the object's pose.
Mesh transform_mesh(const Mesh& canonical, const Mat3& linear, const Vec3& t);
Mesh world_mesh(const Mesh& canonical, const SceneObject& o);

// Parses a scene from JSON; relative paths resolve against base_dir. Throws simu::Error naming
// the key for a malformed top level (camera, gravity, planes); a malformed object entry does not
// throw: it keeps its id and gets SceneObject::error.
Scene scene_from_json(const nlohmann::json& j, const std::string& base_dir, const std::string& what = "scene");
// Serialises a scene; paths are written relative to out_dir when they lie below it, else absolute.
nlohmann::json scene_to_json(const Scene& s, const std::string& out_dir);
// Loads a scene file (throws simu::Error naming the file on unreadable or malformed JSON).
Scene load_scene(const std::string& path);
// Writes a scene file atomically.
void save_scene(const Scene& s, const std::string& path);

}  // namespace simu::physics
