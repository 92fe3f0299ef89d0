// Scenes of the shape world: a floor, a back wall and a table against it, N objects of one split at
// rest on the table top or the floor (standing, lying on a stable face, leaning against the wall), a
// random camera, rendered with the project's rasteriser: shaded RGB (directional light + ambient,
// per-object albedo), label image, per-object modal and amodal masks, visible fraction and occluders,
// the clean OpenCV point map and the intrinsics. Deterministic from (config, scene seed, split).
//
//   world::SceneConfig cfg;                      // 320 x 240, 3..6 objects
//   auto s = world::make_scene(cfg, world::next_scene_seed(world::Split::Train, 0), world::Split::Train);
//   s.rgb;                 // uint8 [H, W, 3]
//   s.pointmap.xyz;        // float [H, W, 3], OpenCV camera, NaN = nothing
//   s.objects[i].modal;    // visible mask; .amodal, .visible_fraction, .occluders
//   s.objects[i].R_cam;    // pose in the camera frame: p_cam = R_cam (scale .* c) + t_cam
//   auto edited = world::render_without(s, {occluder});  // same scene, that object removed
//
// Frames: the world frame of physics/synthetic.h (y down = gravity [0, 1, 0], floor y = floor_y, back
// wall z = wall_z facing the camera); the camera's pose is physics::Camera::R_world_cam / t_world_cam
// (OpenCV axes). Object poses follow docs/scene_format.md: world = R (scale .* c) + t.
#pragma once

#include "common/config.h"
#include "pipeline/physics/raster.h"
#include "pipeline/physics/scene.h"
#include "pipeline/world/corrupt.h"
#include "pipeline/world/shapes.h"

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace simu::world {

// How an object rests.
enum class Rest { Stand, Lie, Lean };
const char* to_string(Rest r);  // "stand", "lie", "lean"

// Label image values: 0 nothing, 1 floor, 2 back wall, 3 table, kFirstObjectLabel + i object i.
inline constexpr int kLabelFloor = 1, kLabelWall = 2, kLabelTable = 3, kFirstObjectLabel = 4;

struct SceneConfig {
  int width = 320, height = 240;
  double fov_min_deg = 50, fov_max_deg = 65;     // horizontal field of view (fx = fy, centred principal point)
  int min_objects = 3, max_objects = 6;
  // Families drawn (uniformly); empty = split_families(split). Naming the held-out family is allowed
  // in Test scenes only.
  std::vector<std::string> families;
  // Rest mode weights and where objects go.
  double w_stand = 0.55, w_lie = 0.3, w_lean = 0.15;
  double floor_fraction = 0.25;                  // share of objects placed on the floor (the rest on the table)
  double max_size_m = 0.6;                       // instances larger than this are redrawn (table top space)
  // Camera: distance to the look-at point on the table top, elevation above it, yaw about the vertical.
  double cam_distance_min = 0.7, cam_distance_max = 1.5;
  double cam_elevation_min_deg = 20, cam_elevation_max_deg = 45;
  double cam_yaw_max_deg = 25;
  // Lighting: a directional light from a random upper-front direction, intensity in [light_min,
  // light_max], plus ambient; colours of floor / wall / table are drawn per scene.
  double light_min = 0.6, light_max = 0.9, ambient = 0.3;
  // Occlusion control: with targets > 0 the scene has at least that many objects whose visible
  // fraction lies in [visible_min, visible_max] (marked WorldObject::target): an occluder is placed
  // between the camera and each target, and the layout is redrawn (up to occlusion_attempts) until the
  // fractions hold. 0 = no requirement (occlusion as it happens).
  int targets = 0;
  double visible_min = 0.2, visible_max = 0.6;
  int occlusion_attempts = 12;
  // Objects whose visible fraction is below this, or with fewer modal pixels than min_pixels, are
  // kept in the scene but flagged WorldObject::usable = false (nothing to lift).
  double min_visible = 0.05;
  int min_pixels = 64;
  // Short MuJoCo settle of the analytic rest poses (needs SIMU_HAVE_MUJOCO; off: analytic only).
  bool settle = false;
  double settle_seconds = 0.5;
  int placement_attempts = 40;                   // tries per object before it is left out
  static SceneConfig from(simu::config::Reader& r);
};

// One object of a scene with its ground truth and what the render says about it.
struct WorldObject {
  std::string id;             // "obj<k>_<family>"
  ShapeInstance shape;
  Rest rest = Rest::Stand;
  bool on_floor = false;      // support: floor (true) or table top
  // Pose in the world frame: world = R (scale .* c) + t (scale = shape.scale()).
  Mat3 R = Mat3::Identity();
  Vec3 scale = Vec3::Ones();
  Vec3 t = Vec3::Zero();
  // The same pose in the OpenCV camera frame (the frame of the point map and of lift's output).
  Mat3 R_cam = Mat3::Identity();
  Vec3 t_cam = Vec3::Zero();
  // Render: modal (visible) and amodal (silhouette alone) masks, their pixel ratio and who hides it.
  physics::BinaryMask modal, amodal;
  int64_t modal_pixels = 0, amodal_pixels = 0;
  double visible_fraction = 0;   // modal_pixels / amodal_pixels (0 when the amodal mask is empty)
  std::vector<int> occluders;    // indices into WorldScene::objects covering part of its amodal mask
  bool occluded_by_table = false;  // the table hides part of it (floor objects)
  bool target = false;           // counted for SceneConfig::targets
  bool usable = true;            // visible enough to lift (SceneConfig::min_visible, min_pixels)
  int label = 0;                 // its value in WorldScene::labels (kFirstObjectLabel + index)
};

// A rendered scene.
struct WorldScene {
  uint64_t seed = 0;
  Split split = Split::Train;
  std::string name;               // "<split>_<seed>"
  physics::Camera camera;         // intrinsics, size and pose in the world
  Vec3 gravity = Vec3(0, 1, 0);
  double floor_y = 0, wall_z = 0, table_top_y = 0;
  std::vector<physics::Mesh> environment;  // world-frame meshes: floor, wall, table (labels 1..3)
  std::vector<Vec3> environment_albedo;
  Vec3 light_dir = Vec3(0, 1, 0);  // world direction the light travels
  double light = 0.8, ambient = 0.3;
  std::vector<WorldObject> objects;
  std::vector<int> removed;       // objects left out of the render (render_without), ascending
  double min_visible = 0.05;      // WorldObject::usable thresholds (SceneConfig::min_visible, min_pixels)
  int min_pixels = 64;
  // Render.
  std::vector<uint8_t> rgb;       // [H, W, 3] sRGB-ish uint8
  std::vector<int32_t> labels;    // [H, W] label values (see kLabel*)
  std::vector<float> depth;       // [H, W] camera z (m), +inf where nothing is hit
  PointMap pointmap;              // clean [H, W, 3] OpenCV camera, NaN where nothing is hit
};

// Generates and renders one scene. scene_seed must belong to the split (scene_split_of(scene_seed) ==
// split; next_scene_seed finds one); objects are instances of that split (held-out family only in
// Test, on request). `extra` instances (external meshes, chosen instances) are placed first, each in a
// stable rest pose; then random instances up to the drawn count. Throws simu::Error for a bad config,
// a seed of another split, or an extra instance too large for the table.
WorldScene make_scene(const SceneConfig& config, uint64_t scene_seed, Split split,
                      const std::vector<ShapeInstance>& extra = {});

// Renders (again) the scene's current objects minus s.removed: rgb, labels, depth, point map, every
// object's modal / amodal masks, visible fraction and occluders. make_scene calls it.
void render_scene(WorldScene& s);

// The "edited image": a copy of the scene with the given objects removed (not re-settled: every other
// object keeps its pose; objects leaning on the wall only, so none falls) and rendered again. Removed
// objects keep their entries (empty masks, visible fraction 0, usable false) so indices stay valid.
// Throws simu::Error naming an index out of range.
WorldScene render_without(const WorldScene& s, const std::vector<int>& removed);

// The world-frame mesh of object i (its canonical mesh at its pose).
physics::Mesh object_world_mesh(const WorldObject& o);

}  // namespace simu::world
