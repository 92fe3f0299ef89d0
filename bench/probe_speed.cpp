// probe_speed: time of the physics probe (penetration, gravity diagnostics, decision) and the final
// settle on a 26-object scene (the Aria Digital Twin average in the paper): floor clutter, a table
// with objects on it, a stack, and four objects hanging on a wall. Every object gets its own mesh
// (so a cold hull cache decomposes 26 meshes), small hover/sink errors and a random yaw.
// Prints a table: hull cache cold / warm, single scene, and N scenes on N threads.
#include <fmt/format.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <random>
#include <thread>

#include "common/cli.h"
#include "common/fs.h"
#include "common/parallel.h"
#include "common/timing.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/probe.h"

using namespace simu::physics;
using simu::seconds_since;

namespace {

// One canonical mesh per object: a box, an L prism or a 12-sided prism, jittered so each is unique.
Mesh make_mesh(int kind, std::mt19937& rng) {
  std::uniform_real_distribution<double> u(0.4, 1.0);
  Mesh m;
  if (kind == 0) {
    m = box_mesh(Vec3(0.5, 0.5 * u(rng), 0.5 * u(rng)));
  } else if (kind == 1) {
    const double a = 0.3 + 0.3 * u(rng);
    m = prism_mesh({{a, a}, {a, 1}, {0, 1}, {0, 0}, {1, 0}, {1, a}}, 0.2 + 0.2 * u(rng));
  } else {
    std::vector<Eigen::Vector2d> poly;
    for (int k = 0; k < 12; ++k) poly.emplace_back(std::cos(k * M_PI / 6), std::sin(k * M_PI / 6));
    m = prism_mesh(poly, 0.5 + u(rng));
  }
  std::normal_distribution<double> jitter(0, 1e-4);
  for (Eigen::Index i = 0; i < m.V.size(); ++i) m.V.data()[i] += jitter(rng);
  canonicalize(m);
  return m;
}

// Rotation about the gravity axis (z).
Mat3 yaw(double a) { return Eigen::AngleAxisd(a, Vec3::UnitZ()).toRotationMatrix(); }

// Places object o with canonical mesh m so its lowest point sits at height z_bottom (+ error).
void place(SceneObject& o, const Mesh& m, double x, double y, double z_bottom) {
  const Mesh w = transform_mesh(m, o.linear(), Vec3::Zero());
  const double low = mesh_aabb(w).min.z();
  o.t = Vec3(x, y, z_bottom - low);
}

Scene make_scene(const std::string& dir, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> U(0, 1);
  Scene s;
  s.gravity = Vec3(0, 0, -1);
  s.floor = Plane{"floor", Vec3::Zero(), Vec3::UnitZ()};
  s.walls.push_back(Plane{"back", Vec3(0, 2, 0), Vec3(0, -1, 0)});
  s.walls.push_back(Plane{"left", Vec3(-2.5, 0, 0), Vec3(1, 0, 0)});
  // Table: top slab 1.2 x 0.8 x 0.04 (top at 0.76) on four legs.
  auto base = [&](const std::string& id, const Vec3& half, const Vec3& t) {
    Mesh m = box_mesh(half);
    const std::string path = dir + "/" + id + ".obj";
    write_mesh(m, path);
    BaseBody b;
    b.id = id, b.mesh_path = path, b.t = t;
    s.bases.push_back(b);
  };
  base("table_top", Vec3(0.6, 0.4, 0.02), Vec3(0, 0.8, 0.74));
  for (int k = 0; k < 4; ++k)
    base(fmt::format("leg{}", k), Vec3(0.025, 0.025, 0.36), Vec3((k & 1) ? 0.55 : -0.55, 0.8 + ((k & 2) ? 0.35 : -0.35), 0.36));
  auto object = [&](int i, int kind, double size) {
    SceneObject o;
    o.id = fmt::format("obj{:02d}", i);
    const Mesh m = make_mesh(kind, rng);
    o.mesh_path = dir + "/" + o.id + ".obj";
    write_mesh(m, o.mesh_path);
    o.scale = Vec3::Constant(size);
    o.R = yaw(2 * M_PI * U(rng));
    return std::make_pair(o, m);
  };
  // Monocular error: hover up to 3 cm or sink up to 1.5 cm.
  auto err = [&] { return U(rng) < 0.5 ? 0.03 * U(rng) : -0.015 * U(rng); };
  int i = 0;
  // 10 on the floor, away from the table.
  for (int k = 0; k < 10; ++k, ++i) {
    auto [o, m] = object(i, k % 3, 0.15 + 0.25 * U(rng));
    place(o, m, -2.0 + 0.42 * k, -0.6 - 0.4 * (k % 2), err());
    s.objects.push_back(o);
  }
  // 10 on the table top (z = 0.76).
  for (int k = 0; k < 10; ++k, ++i) {
    auto [o, m] = object(i, k % 3, 0.06 + 0.08 * U(rng));
    place(o, m, -0.5 + 0.22 * (k % 5), 0.6 + 0.3 * (k / 5), 0.76 + err());
    s.objects.push_back(o);
  }
  // A stack of two boxes on the floor.
  {
    auto [a, ma] = object(i++, 0, 0.3);
    a.R = Mat3::Identity();
    place(a, ma, 1.5, 0.8, 0.0);
    s.objects.push_back(a);
    const double top = a.t.z() + 0.5 * a.scale.z() * (mesh_aabb(ma).size().z());
    auto [b, mb] = object(i++, 0, 0.2);
    b.R = Mat3::Identity();
    place(b, mb, 1.5, 0.8, top + 0.01);
    s.objects.push_back(b);
  }
  // Four hanging on the back wall: two frames (two pins), two lamps (one pin).
  for (int k = 0; k < 4; ++k, ++i) {
    SceneObject o;
    o.id = fmt::format("obj{:02d}", i);
    const Mesh m = k < 2 ? box_mesh(Vec3(0.5, 0.03, 0.35)) : make_mesh(2, rng);
    o.mesh_path = dir + "/" + o.id + ".obj";
    write_mesh(m, o.mesh_path);
    o.scale = Vec3::Constant(k < 2 ? 0.6 : 0.25);
    o.dof = k < 2 ? PoseDof::LineAnchored : PoseDof::PointAnchored;
    const double half_depth = 0.5 * o.scale.y() * mesh_aabb(m).size().y();
    o.t = Vec3(-1.5 + 0.9 * k, 2.0 - half_depth - 0.003, 1.6);
    s.objects.push_back(o);
  }
  return s;
}


}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Time the physics probe and final settle on a 26-object scene"};
  int threads = 2;
  bool no_coacd = false;
  std::string dir = (std::filesystem::temp_directory_path() / "simu_probe_speed").string();
  app.add_option("--threads", threads, "scenes run in parallel in the last row");
  app.add_option("--dir", dir, "work directory (meshes, hull cache, outputs)");
  app.add_flag("--no-coacd", no_coacd, "one hull per mesh");
  std::string integrator = "implicit";
  int max_hulls = ProbeConfig().collision.max_hulls;
  double settle = ProbeConfig().final_settle_time;
  app.add_option("--integrator", integrator, "MuJoCo integrator (implicit, Euler)");
  app.add_option("--max-hulls", max_hulls, "CoACD max hulls per mesh");
  app.add_option("--settle-time", settle, "final settle T_settle (s)");
  int decompose_threads = 0;
  app.add_option("--decompose-threads", decompose_threads,
                 "meshes decomposed in parallel (0 = one per core; 1 for the one-core figure, with OMP_NUM_THREADS=1 "
                 "and taskset -c 0)");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    simu::fs::remove_tree(dir);
    std::filesystem::create_directories(dir);
    const Scene scene = make_scene(dir, 7);
    ProbeConfig cfg;
    cfg.collision.use_coacd = !no_coacd;
    cfg.collision.max_hulls = max_hulls;
    cfg.physics.integrator = integrator;
    cfg.final_settle_time = settle;
    cfg.collision.cache_dir = dir + "/hull_cache";
    cfg.collision.threads = decompose_threads;
    cfg.metrics_settle_time = 0;  // timed separately below
    cfg.evaluate_input = false;   // the "before" settle is a metric, not part of the probe's time
    fmt::print("{:<34} {:>8} {:>10} {:>9} {:>9} {:>8}\n", "run", "objects", "probe (s)", "final (s)", "total (s)", "flagged");
    auto row = [&](const std::string& name, const ProbeResult& r, double total) {
      int flagged = 0;
      for (const auto& d : r.diagnostics) flagged += d.flags.empty() ? 0 : 1;
      fmt::print("{:<34} {:>8} {:>10.3f} {:>9.3f} {:>9.3f} {:>8}\n", name, r.scene.objects.size(), r.seconds_probe,
                 r.seconds_final, total, flagged);
    };
    // Cold hull cache: includes the convex decomposition of every mesh.
    auto t = std::chrono::steady_clock::now();
    auto r = run_probe(scene, cfg, dir + "/out_cold");
    row(no_coacd ? "1 scene, qhull hulls" : "1 scene, hull cache cold (CoACD)", r, seconds_since(t));
    // Warm: hulls from the cache (the in-process cache; the disk cache serves later processes).
    t = std::chrono::steady_clock::now();
    r = run_probe(scene, cfg, dir + "/out_warm");
    row("1 scene, hull cache warm", r, seconds_since(t));
    {
      // The paper's 5 s evaluation settle of the final scene (metrics), not part of the 10 s budget.
      ProbeConfig mc = cfg;
      mc.metrics_settle_time = 5.0;
      const auto rm = run_probe(scene, mc, "");
      fmt::print("{:<34} {:>8} {:>10} {:>9} {:>9.3f} {:>8}   (stability {:.0f}%, penetration {:.0f}%)\n",
                 "  + 5 s metrics settle (alone)", rm.scene.objects.size(), "", "", rm.seconds_metrics, "",
                 rm.evaluation.metrics.stability, rm.evaluation.metrics.penetration_ratio);
    }
    for (const auto& d : r.diagnostics)
      if (!d.flags.empty()) fmt::print("  flagged: {}\n", d.message);
    // Several scenes in parallel threads.
    t = std::chrono::steady_clock::now();
    std::vector<ProbeResult> rs(threads);
    simu::parallel_for_each(threads, threads,
                            [&](int64_t k) { rs[k] = run_probe(scene, cfg, dir + fmt::format("/out_t{}", k)); });
    const double wall = seconds_since(t);
    fmt::print("{:<34} {:>8} {:>10} {:>9} {:>9.3f} {:>8}\n", fmt::format("{} scenes on {} threads", threads, threads),
               threads * static_cast<int>(scene.objects.size()), "", "", wall, "");
    int counts[5] = {0, 0, 0, 0, 0};
    for (const auto& d : r.diagnostics) ++counts[static_cast<int>(d.branch)];
    fmt::print("branches: stretch {}, resample {}, anchored {}, disabled {}\n", counts[1], counts[2], counts[3], counts[4]);
    return 0;
  });
}
