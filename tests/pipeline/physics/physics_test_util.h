// Helpers of the physics tests (no torch): temporary directories, box meshes, scene files, the
// hand-made probe scenes (a room with a floor and a wall, objects placed in it, a quick config).
#pragma once

#include <unistd.h>

#include <filesystem>
#include <string>

#include "common/fs.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/scene.h"

namespace simu::testing {

// How far a body resting under gravity sinks into MuJoCo's soft contacts with the probe's settings
// (solref time constant t_c 0.01 s, damping ratio 2; solimp d up to 0.95): to where the contact's
// spring holds its weight, ~g (t_c 2)^2 (1 - d) / d = 0.2 mm. Resting positions, penetrations and
// settle displacements are checked to 2 mm: ten times that, for the settle's last motion and the
// timestep (1/480 s) of contact onset.
inline constexpr double kContactSinkM = 0.002;

// A fresh temporary directory for one test.
inline std::string physics_temp_dir(const std::string& name) {
  auto p = std::filesystem::temp_directory_path() / ("simu_physics_" + name + "_" + std::to_string(::getpid()));
  simu::fs::remove_tree(p.string());
  std::filesystem::create_directories(p);
  return p.string();
}

// Writes a canonical box mesh (AABB-centred; half extents h, longest side 1 expected) and returns its path.
inline std::string write_box(const std::string& dir, const std::string& name, const physics::Vec3& half) {
  const std::string path = dir + "/" + name + ".obj";
  physics::write_mesh(physics::box_mesh(half), path);
  return path;
}

// A room: floor z = 0, gravity -z, one wall "back" at y = 1 facing -y; an fx = fy = f pinhole camera
// of w x h pixels with its principal point at the centre (pose: the identity; tests set their own).
inline physics::Scene test_room(double f, int w, int h) {
  physics::Scene s;
  s.gravity = physics::Vec3(0, 0, -1);
  s.floor = physics::Plane{"floor", physics::Vec3::Zero(), physics::Vec3::UnitZ()};
  s.walls.push_back(physics::Plane{"back", physics::Vec3(0, 1, 0), physics::Vec3(0, -1, 0)});
  s.camera.fx = s.camera.fy = f;
  s.camera.cx = w / 2.0, s.camera.cy = h / 2.0, s.camera.width = w, s.camera.height = h;
  return s;
}

// An object with the given mesh file, uniform scale and position (identity rotation).
inline physics::SceneObject placed_object(const std::string& id, const std::string& mesh, const physics::Vec3& scale,
                                          const physics::Vec3& t) {
  physics::SceneObject o;
  o.id = id;
  o.mesh_path = mesh;
  o.scale = scale;
  o.t = t;
  return o;
}

// A probe config for boxes: a 1 s final settle, one convex hull per mesh (boxes are convex: no
// decomposition time).
inline physics::ProbeConfig quick_probe_config() {
  physics::ProbeConfig c;
  c.final_settle_time = 1.0;
  c.collision.use_coacd = false;
  return c;
}

}  // namespace simu::testing
