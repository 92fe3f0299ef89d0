// Tests the reconstruct run's steps on an in-memory synthetic photo (run.h, synthetic_inputs.h; no image
// I/O, no probe): bring-your-own-lift objects are all composed; the re-extraction's mesh-derived up
// (the fitted meshes' canonical up axes) is within 3 degrees of the true up and decides up when there is
// no wall pair, no floor mask and no fallback floor; the floor then sits at the lowest fitted vertex; a
// hanging object is anchored to the back wall, and without wall masks gets a wall fitted to the depth
// around its mask, within 1 degree / 2 cm of the true back wall; an output is replaced atomically (a failed
// run keeps the earlier one).
#include <gtest/gtest.h>

#include <filesystem>

#include "common/error.h"
#include "pipeline/physics/scene.h"

#include "pipeline/reconstruct/planes.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/reconstruct/run.h"
#include "pipeline/reconstruct/synthetic_inputs.h"
#include "test_util.h"

using namespace simu::reconstruct;

namespace {
CameraScene small_scene() {
  CameraSceneConfig cfg;
  cfg.generator.width = 240;
  cfg.generator.height = 180;
  cfg.generator.fx = 210;
  cfg.generator.min_objects = cfg.generator.max_objects = 3;
  cfg.generator.min_hanging = cfg.generator.max_hanging = 1;
  return generate_camera_scene(cfg, 7, "run");
}
// Drops the sidecar entries (and masks) of the given roles.
void drop_roles(ReconstructInputs& in, const std::vector<std::string>& roles) {
  std::vector<std::string> masks;
  std::vector<ObjectSpec> keep;
  for (auto& s : in.specs) {
    if (std::find(roles.begin(), roles.end(), s.role) != roles.end()) masks.push_back(s.mask_id);
    else keep.push_back(s);
  }
  in.specs = keep;
  std::vector<simu::resample::LiftObjectInput> objs;
  for (auto& o : in.lift.objects)
    if (std::find(masks.begin(), masks.end(), o.id) == masks.end()) objs.push_back(o);
  in.lift.objects = objs;
}
ReconstructOptions options() {
  ReconstructOptions o;
  o.run_probe = false;
  return o;
}
const CameraObject* hanging(const CameraScene& s) {
  for (const auto& o : s.objects)
    if (o.dof != simu::physics::PoseDof::Free) return &o;
  return nullptr;
}
}  // namespace

// Every object composed; up from the walls; the fitted meshes' up agrees; the hanging object on the back wall.
TEST(ReconstructRun, InMemoryPhotoWithWalls) {
  const CameraScene s = small_scene();
  ASSERT_NE(hanging(s), nullptr);
  const auto dir = simu::testing::temp_dir("reconstruct_run_walls");
  write_camera_scene_lift(s, dir + "/photo");
  const ReconstructResult r = reconstruct(camera_scene_inputs(s, dir + "/photo", true), options(), nullptr, dir + "/out");
  size_t free_or_hanging = 0;
  for (const auto& o : s.objects) free_or_hanging += !o.is_base;
  EXPECT_EQ(r.scene.objects.size(), free_or_hanging);
  EXPECT_EQ(r.planes.up_source, "walls");
  // Up from two noisy wall fits (1 degree: as in planes_test); from the meshes' own up axes (a vote of
  // a few objects' rotations, each a few degrees off by construction of the synthetic scene): 3 degrees.
  EXPECT_LT(angle_deg(r.planes.up, s.up), 1.0);
  ASSERT_GT(r.mesh_up.norm(), 0.5);
  EXPECT_LT(angle_deg(r.mesh_up, s.up), 3.0);
  for (const auto& o : r.scene.objects)
    if (o.id == hanging(s)->id) EXPECT_EQ(o.wall_id, "back_wall");
}

// No floor / wall masks and the fallback off: up from the fitted meshes, the floor at their lowest vertex.
TEST(ReconstructRun, MeshDerivedUpWithoutWallsOrFloor) {
  const CameraScene s = small_scene();
  const auto dir = simu::testing::temp_dir("reconstruct_run_meshup");
  write_camera_scene_lift(s, dir + "/photo");
  ReconstructInputs in = camera_scene_inputs(s, dir + "/photo", true);
  drop_roles(in, {"floor", "wall"});
  ReconstructOptions opt = options();
  opt.planes.fallback_planes = 0;
  const ReconstructResult r = reconstruct(in, opt, nullptr, dir + "/out");
  EXPECT_EQ(r.planes.up_source, "mesh");
  EXPECT_LT(angle_deg(r.planes.up, s.up), 3.0);  // the meshes' vote, as above
  ASSERT_TRUE(r.planes.floor.has_value());
  // The floor plane passes through the lowest vertex (along up) of the standing objects' placed meshes.
  double low = 1e300;
  for (const auto& o : r.scene.objects)
    if (o.dof == simu::physics::PoseDof::Free) {
      const simu::physics::Mesh m = simu::physics::read_mesh(o.mesh_path);
      for (Eigen::Index i = 0; i < m.V.rows(); ++i) low = std::min(low, r.planes.up.dot(o.to_world(m.V.row(i).transpose())));
    }
  for (const auto& b : r.scene.bases) {
    const simu::physics::Mesh m = simu::physics::read_mesh(b.mesh_path);
    for (Eigen::Index i = 0; i < m.V.rows(); ++i)
      low = std::min(low, r.planes.up.dot(Vec3(b.R * b.scale.cwiseProduct(m.V.row(i).transpose()) + b.t)));
  }
  // The snap puts the plane through the lowest vertex: float64 on ~1 m values, and the meshes' fp32
  // storage (u of a metre: 6e-8 m); 1e-6 m.
  EXPECT_NEAR(r.planes.up.dot(r.planes.floor->plane.point), low, 1e-6);
}

// No wall masks: the hanging object's wall is fitted to the depth around it and matches the true back wall.
TEST(ReconstructRun, HangingObjectGetsAWallFromTheDepthAroundIt) {
  const CameraScene s = small_scene();
  const CameraObject* h = hanging(s);
  ASSERT_NE(h, nullptr);
  const auto dir = simu::testing::temp_dir("reconstruct_run_hang");
  write_camera_scene_lift(s, dir + "/photo");
  ReconstructInputs in = camera_scene_inputs(s, dir + "/photo", true);
  drop_roles(in, {"wall"});
  const ReconstructResult r = reconstruct(in, options(), nullptr, dir + "/out");
  std::string wall;
  for (const auto& o : r.scene.objects)
    if (o.id == h->id) wall = o.wall_id;
  ASSERT_EQ(wall, h->id + "_wall");
  const simu::physics::Plane* p = nullptr;
  for (const auto& w : r.scene.walls)
    if (w.id == wall) p = &w;
  ASSERT_NE(p, nullptr);
  // A wall fitted behind a hanging object from its mesh's back face and the point map: 1 degree and
  // the 2 cm the object hangs off it.
  EXPECT_LT(angle_deg(p->normal, s.back_wall.plane.normal), 1.0);
  EXPECT_LT(std::abs(s.back_wall.plane.distance(p->point)), 0.02);
}

// Output replacement: an existing output is refused without overwrite; with it, a run that fails part-way
// (an invalid probe config) leaves the earlier output as it was and no temporary; a good run replaces
// it and its scene.json names files inside the final folder.
TEST(ReconstructRun, OverwriteIsAtomicAndAFailedRunKeepsTheEarlierOutput) {
  namespace sfs = std::filesystem;
  const CameraScene s = small_scene();
  const auto dir = simu::testing::temp_dir("reconstruct_run_overwrite");
  write_camera_scene_lift(s, dir + "/photo");
  const ReconstructInputs byo = camera_scene_inputs(s, dir + "/photo", true);
  const std::string out = dir + "/out";
  reconstruct(byo, options(), nullptr, out);
  const auto first_time = sfs::last_write_time(out + "/input/scene.json");
  // Refused without overwrite.
  EXPECT_THROW(reconstruct(byo, options(), nullptr, out), simu::Error);
  // A run with overwrite that fails part-way (its probe config is invalid: the inputs are written, then the
  // probe refuses): the old output untouched, no temporary left.
  ReconstructOptions ow = options();
  ow.overwrite = true;
  ReconstructOptions bad = ow;
  bad.run_probe = true;
  bad.probe.physics.timestep = -1;
  EXPECT_THROW(reconstruct(byo, bad, nullptr, out), simu::Error);
  EXPECT_EQ(sfs::last_write_time(out + "/input/scene.json"), first_time);
  for (const auto& e : sfs::directory_iterator(dir))
    EXPECT_EQ(e.path().filename().string().find(".tmp-"), std::string::npos) << e.path();
  // A good run with overwrite replaces it; every file the result and the scene name is in the final folder.
  const ReconstructResult r = reconstruct(byo, ow, nullptr, out);
  ASSERT_FALSE(r.scene.objects.empty());
  for (const auto& o : r.scene.objects) {
    EXPECT_TRUE(sfs::exists(o.mesh_path)) << o.mesh_path;
    EXPECT_EQ(o.mesh_path.find(".tmp-"), std::string::npos) << o.mesh_path;
  }
  const auto reread = simu::physics::load_scene(out + "/input/scene.json");
  for (const auto& o : reread.objects) EXPECT_TRUE(sfs::exists(o.mesh_path)) << o.mesh_path;
}
