// MuJoCo settle of a world scene through physics::evaluate_physics.
#include "pipeline/world/settle.h"

#include "common/error.h"
#include "common/fs.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/synthetic.h"

#include <Eigen/Geometry>

#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fmt/format.h>
#include <unistd.h>

namespace simu::world {

SettleReport settle_scene(WorldScene& s, double seconds, bool apply) {
  SettleReport rep;
  const size_t n = s.objects.size();
  rep.displacement.assign(n, 0.0);
  rep.rotation_deg.assign(n, 0.0);
  rep.simulated.assign(n, false);
#ifndef SIMU_HAVE_MUJOCO
  rep.message = "built without MuJoCo (SIMU_WITH_MUJOCO=OFF)";
  return rep;
#else
  const auto t0 = std::chrono::steady_clock::now();
  static std::atomic<int> counter{0};
  const std::string dir = (std::filesystem::temp_directory_path() /
                           fmt::format("simu_world_settle_{}_{}", getpid(), counter.fetch_add(1))).string();
  std::filesystem::create_directories(dir);
  struct Cleanup {
    std::string d;
    ~Cleanup() {
      try {
        fs::remove_tree(d);
      } catch (...) {
      }
    }
  } cleanup{dir};
  std::vector<bool> removed(n, false);
  for (int i : s.removed) removed.at(size_t(i)) = true;
  physics::Scene scene;
  scene.camera = s.camera;
  scene.gravity = s.gravity;
  scene.floor = physics::Plane{"floor", Vec3(0, s.floor_y, 0), Vec3(0, -1, 0)};
  scene.walls.push_back(physics::Plane{"back", Vec3(0, 0, s.wall_z), Vec3(0, 0, -1)});
  // The table as its bounding box (floor objects never stand under it).
  const physics::Mesh& table = s.environment.at(2);
  const Vec3 lo = table.V.colwise().minCoeff().transpose(), hi = table.V.colwise().maxCoeff().transpose();
  physics::Mesh box = physics::canonical_box_mesh(hi - lo);
  physics::write_obj(dir + "/table.obj", box);
  physics::BaseBody base;
  base.id = "table";
  base.mesh_path = dir + "/table.obj";
  base.scale = Vec3::Constant((hi - lo).maxCoeff());
  base.t = 0.5 * (lo + hi);
  scene.bases.push_back(base);
  std::vector<int> index;  // scene object -> world object
  for (size_t i = 0; i < n; ++i) {
    if (removed[i]) continue;
    const WorldObject& o = s.objects[i];
    physics::SceneObject so;
    so.id = o.id;
    so.mesh_path = fmt::format("{}/{}.obj", dir, o.id);
    physics::write_obj(so.mesh_path, o.shape.mesh);
    so.scale = o.scale, so.R = o.R, so.t = o.t;
    scene.objects.push_back(so);
    index.push_back(int(i));
  }
  physics::ProbeConfig cfg;
  cfg.collision.use_coacd = false;  // one hull per object, as the rest analysis
  cfg.metrics_rest_distance = 1e-4;
  const physics::PhysicsEvaluation ev = physics::evaluate_physics(scene, cfg, seconds);
  rep.ran = ev.ran;
  rep.message = ev.message;
  for (size_t k = 0; k < index.size(); ++k) {
    WorldObject& o = s.objects[size_t(index[k])];
    if (ev.objects[k].physics_disabled) continue;
    rep.simulated[size_t(index[k])] = true;
    rep.displacement[size_t(index[k])] = (ev.t[k] - o.t).norm();
    rep.rotation_deg[size_t(index[k])] = Eigen::AngleAxisd(ev.R[k] * o.R.transpose()).angle() * 180.0 / 3.14159265358979323846;
    if (apply) o.t = ev.t[k], o.R = ev.R[k];
  }
  rep.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return rep;
#endif
}

}  // namespace simu::world
