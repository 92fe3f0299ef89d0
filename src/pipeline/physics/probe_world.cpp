// The probe's MuJoCo world: inputs read and checked, worlds built and compiled, pose access, pins,
// the sequential order (probe_world.h).
#include "pipeline/physics/probe_world.h"

#include <mujoco/mujoco.h>

#include <fmt/format.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cmath>
#include <limits>
#include <thread>

#include "common/error.h"
#include "common/log.h"
#include "common/parallel.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/overlay.h"

namespace simu::physics {

double lowest_corner_along_gravity(const Mesh& world, const Vec3& g) {
  const auto b = mesh_aabb(world);
  double best = -std::numeric_limits<double>::infinity();
  for (int c = 0; c < 8; ++c) {
    const Vec3 p((c & 1) ? b.max.x() : b.min.x(), (c & 2) ? b.max.y() : b.min.y(), (c & 4) ? b.max.z() : b.min.z());
    best = std::max(best, g.dot(p));
  }
  return best;
}


std::vector<Vec3> choose_pins(const Mesh& world, const Plane& wall, const Vec3& g, int count, double region) {
  std::vector<Vec3> pins;
  if (count <= 0 || world.V.rows() == 0) return pins;
  // Frame: up = -g, back = towards the wall, lateral = wall-parallel horizontal.
  const Vec3 up = -g.normalized();
  Vec3 lateral = wall.normal.cross(g);
  if (lateral.norm() < 1e-9) lateral = up.unitOrthogonal();
  lateral.normalize();
  const Eigen::Index n = world.V.rows();
  Eigen::VectorXd h(n), d(n), l(n);
  for (Eigen::Index i = 0; i < n; ++i) {
    const Vec3 p = world.V.row(i).transpose();
    h[i] = up.dot(p);
    d[i] = wall.distance(p);
    l[i] = lateral.dot(p);
  }
  // Top-back region: within `region` of the extent from the top and from the wall-facing back. It is
  // widened (doubling, up to the whole object) while it is empty or, for two pins, while its vertices
  // span less than half the object's lateral extent: on a coarse, slightly tilted mesh the top region
  // can hold a single corner, and two pins at one point would let the object swing about it.
  const double hr = std::max(h.maxCoeff() - h.minCoeff(), 1e-9), dr = std::max(d.maxCoeff() - d.minCoeff(), 1e-9);
  const double lr = l.maxCoeff() - l.minCoeff();
  std::vector<Eigen::Index> cand;
  for (double f = region;; f = std::min(2 * f, 1.0)) {
    cand.clear();
    double lmin = 1e300, lmax = -1e300;
    for (Eigen::Index i = 0; i < n; ++i)
      if (h[i] >= h.maxCoeff() - f * hr && d[i] <= d.minCoeff() + f * dr) {
        cand.push_back(i);
        lmin = std::min(lmin, l[i]);
        lmax = std::max(lmax, l[i]);
      }
    const bool enough = !cand.empty() && (count < 2 || lmax - lmin >= 0.5 * lr);
    if (enough || f >= 1.0) break;
  }
  if (cand.empty()) cand.push_back(0);
  if (count == 1) {
    // Highest, then most laterally centred: among the top few percent, the one nearest the lateral mid.
    double hmax = -1e300;
    for (auto i : cand) hmax = std::max(hmax, h[i]);
    const double lmid = 0.5 * (l.maxCoeff() + l.minCoeff());
    Eigen::Index best = cand[0];
    double best_score = 1e300;
    for (auto i : cand) {
      if (h[i] < hmax - 0.02 * hr) continue;
      const double score = std::abs(l[i] - lmid);
      if (score < best_score) best_score = score, best = i;
    }
    pins.push_back(world.V.row(best).transpose());
  } else {
    // Leftmost and rightmost along the lateral direction.
    auto lo = *std::min_element(cand.begin(), cand.end(), [&](auto a, auto b) { return l[a] < l[b]; });
    auto hi = *std::max_element(cand.begin(), cand.end(), [&](auto a, auto b) { return l[a] < l[b]; });
    pins.push_back(world.V.row(lo).transpose());
    pins.push_back(world.V.row(hi).transpose());
  }
  return pins;
}

namespace probe_detail {

std::mutex& compile_mutex() {
  static std::mutex m;
  return m;
}

void add_flag(Diagnostics& d, const std::string& flag, const std::string& msg) {
  if (std::find(d.flags.begin(), d.flags.end(), flag) == d.flags.end()) d.flags.push_back(flag);
  if (!msg.empty()) d.message += (d.message.empty() ? "" : "; ") + msg;
}

std::string safe_name(const std::string& id) {
  std::string s;
  for (char ch : id) s += (std::isalnum(static_cast<unsigned char>(ch)) || ch == '-' || ch == '_') ? ch : '_';
  return s.empty() ? "object" : s;
}

namespace {

// The object's colour in the MJCF (the same palette as the pictures: overlay_color).
std::string object_rgba(int i, double alpha = 1.0) {
  const auto bgr = overlay_color(i);
  return fmt::format("{:.3f} {:.3f} {:.3f} {:.2f}", bgr[2] / 255.0, bgr[1] / 255.0, bgr[0] / 255.0, alpha);
}

// visual: the reconstructed mesh is a visual geom read from meshes/<id>.obj beside the MJCF.
MjBody object_body(const Ctx& c, int i, bool dynamic, bool pins, bool visual = false) {
  const Obj& o = c.objs[i];
  MjBody b;
  b.name = fmt::format("obj{}", i);
  b.pos = o.t;
  b.R = o.R;
  b.hulls = transform_hulls(o.shape.hulls, o.s.asDiagonal());
  b.dynamic = dynamic;
  if (dynamic) b.mass = mass_properties(b.hulls, c.scene.objects[i].density);
  if (pins) b.pins = o.pins_body;
  b.rgba = object_rgba(i);
  if (visual && o.visual_ok) {
    b.visual_file = "meshes/" + safe_name(c.scene.objects[i].id) + ".obj";
    b.visual_scale = o.s;
  }
  return b;
}

}  // namespace

World build_world(const Ctx& c, const std::vector<int>& statics, const std::vector<int>& dynamics, bool pins,
                  std::string* xml_out, const std::vector<int>& visual_only, int buffer_factor, bool detect,
                  bool visuals) {
  MjScene ms;
  ms.gravity = c.scene.gravity * c.scene.gravity_magnitude;
  if (c.scene.floor) {
    Plane f = *c.scene.floor;
    f.id = "floor";
    ms.planes.push_back(f);
  }
  for (const auto& w : c.scene.walls) ms.planes.push_back(w);
  for (size_t k = 0; k < c.bases.size(); ++k) {
    MjBody b;
    b.name = fmt::format("base{}", k);
    b.pos = c.bases[k].t;
    b.R = c.bases[k].R;
    b.hulls = c.base_hulls[k];
    b.rgba = "0.6 0.6 0.55 1";
    ms.bodies.push_back(std::move(b));
  }
  for (int i : statics) ms.bodies.push_back(object_body(c, i, false, false));
  for (int i : dynamics) ms.bodies.push_back(object_body(c, i, true, pins));
  // Contact and constraint buffers sized to the dynamic bodies (mjData holds an njmax^2 matrix).
  PhysicsConfig pc = c.cfg.physics;
  const int ndyn = static_cast<int>(dynamics.size());
  pc.nconmax = std::min(pc.nconmax, (100 + 25 * ndyn) * buffer_factor);
  pc.njmax = std::min(pc.njmax, (300 + 60 * ndyn) * buffer_factor);
  const std::string xml = write_mjcf(ms, pc, detect);
  if (xml_out) {
    if (visuals) {
      MjScene vs = ms;
      // Visual-only bodies (disabled objects in the final file): their mesh, half transparent, no contacts.
      for (int i : visual_only) {
        MjBody b = object_body(c, i, false, false, true);
        b.collide = false;
        b.rgba = object_rgba(i, 0.4);
        if (!b.visual_file.empty()) vs.bodies.push_back(std::move(b));
      }
      for (auto& b : vs.bodies) {
        const int i = b.name.rfind("obj", 0) == 0 ? std::stoi(b.name.substr(3)) : -1;
        if (i >= 0 && b.visual_file.empty() && c.objs[i].visual_ok) {
          b.visual_file = "meshes/" + safe_name(c.scene.objects[i].id) + ".obj";
          b.visual_scale = c.objs[i].s;
        }
      }
      *xml_out = write_mjcf(vs, pc, detect);
    } else {
      *xml_out = xml;
    }
  }
  World w;
  {
    std::lock_guard<std::mutex> lock(compile_mutex());
    w.model = load_mjcf_string(xml);
  }
  w.data = make_data(w.model.get());
  const mjModel* m = w.model.get();
  w.env_body.assign(m->nbody, false);
  w.body_obj.assign(m->nbody, -1);
  w.env_body[0] = true;
  for (size_t k = 0; k < c.bases.size(); ++k) {
    const int id = mj_name2id(m, mjOBJ_BODY, fmt::format("base{}", k).c_str());
    if (id >= 0) w.env_body[id] = true;
  }
  w.obj_body.assign(c.objs.size(), -1);
  for (int i : statics) {
    const int id = mj_name2id(m, mjOBJ_BODY, fmt::format("obj{}", i).c_str());
    if (id >= 0) w.body_obj[id] = i;
  }
  for (int i : dynamics) {
    const int id = mj_name2id(m, mjOBJ_BODY, fmt::format("obj{}", i).c_str());
    w.obj_body[i] = id;
    if (id >= 0) w.body_obj[id] = i;
  }
  mj_forward(m, w.data.get());
  take_warnings(w.data.get());
  return w;
}

// Free-joint pose access.
void set_pose(World& w, int body, const Vec3& t, const Mat3& R) {
  const mjModel* m = w.model.get();
  const int adr = m->jnt_qposadr[m->body_jntadr[body]];
  Eigen::Quaterniond q(R);
  q.normalize();
  mjtNum* qp = w.data->qpos + adr;
  qp[0] = t.x(), qp[1] = t.y(), qp[2] = t.z();
  qp[3] = q.w(), qp[4] = q.x(), qp[5] = q.y(), qp[6] = q.z();
  const int dadr = m->body_dofadr[body];
  for (int k = 0; k < 6; ++k) w.data->qvel[dadr + k] = 0;
}
void get_pose(const World& w, int body, Vec3* t, Mat3* R) {
  const mjModel* m = w.model.get();
  const mjtNum* qp = w.data->qpos + m->jnt_qposadr[m->body_jntadr[body]];
  *t = Vec3(qp[0], qp[1], qp[2]);
  *R = Eigen::Quaterniond(qp[3], qp[4], qp[5], qp[6]).normalized().toRotationMatrix();
}
double body_speed(const World& w, int body) {
  const mjtNum* v = w.data->qvel + w.model->body_dofadr[body];
  double s = 0;
  for (int k = 0; k < 6; ++k) s = std::max(s, std::abs(v[k]));
  return s;
}

void start_at_pose(const Ctx& c, World& w, int i) {
  const Obj& o = c.objs[i];
  set_pose(w, w.obj_body[i], o.t, o.R);
  mj_forward(w.model.get(), w.data.get());
  take_warnings(w.data.get());
}

void place_pins(Ctx& c, int i, Diagnostics& d) {
  Obj& o = c.objs[i];
  const Plane& wall = c.scene.walls[o.wall];
  const Mesh world = transform_mesh(o.canonical, o.R * o.s.asDiagonal(), o.t);
  d.pins_world = choose_pins(world, wall, c.scene.gravity, pin_count(c.scene.objects[i].dof), c.cfg.pin_region);
  o.pins_body.clear();
  d.wall_points.clear();
  for (const auto& p : d.pins_world) {
    o.pins_body.push_back(o.R.transpose() * (p - o.t));
    d.wall_points.push_back(p - wall.distance(p) * wall.normal);
  }
}

std::vector<int> sequential_order(const Ctx& c, const std::vector<int>& idx) {
  std::vector<std::pair<double, int>> key;
  for (int i : idx) {
    const Obj& o = c.objs[i];
    const Mesh w = transform_mesh(o.canonical, o.R * o.s.asDiagonal(), o.t);
    key.emplace_back(-lowest_corner_along_gravity(w, c.scene.gravity), i);
  }
  std::stable_sort(key.begin(), key.end());
  std::vector<int> out;
  for (auto& k : key) out.push_back(k.second);
  return out;
}

namespace {

// Bases: read, decomposed, scaled; a bad base is skipped with a warning.
void load_bases(Ctx& c) {
  for (const auto& b : c.scene.bases) {
    if (!b.error.empty()) {
      log::warn("base skipped: {}", b.error);
      continue;
    }
    try {
      const Mesh mesh = read_mesh(b.mesh_path);
      const std::string p = mesh_problem(mesh);
      SIMU_CHECK(p.empty(), "base {}: {}", b.id, p);
      const auto shape = decompose(mesh, c.cfg.collision);
      c.bases.push_back(b);
      c.base_hulls.push_back(transform_hulls(shape.hulls, b.scale.asDiagonal()));
    } catch (const std::exception& e) {
      log::warn("base {} skipped: {}", b.id, e.what());
    }
  }
}

// Objects: poses as read, meshes read and checked (non-manifold and non-canonical meshes are flagged
// and still used). Returns the indices of the readable meshes; a mesh that cannot be used has its
// error in mesh_errors.
std::vector<size_t> read_object_meshes(Ctx& c, std::vector<Diagnostics>& diags, std::vector<std::string>& mesh_errors) {
  std::vector<size_t> readable;
  for (size_t i = 0; i < c.scene.objects.size(); ++i) {
    const SceneObject& so = c.scene.objects[i];
    Diagnostics& d = diags[i];
    Obj& o = c.objs[i];
    d.t_pre = so.t, d.R_pre = so.R, d.s_pre = so.scale;
    o.t = so.t, o.R = so.R, o.s = so.scale;
    if (!so.error.empty()) continue;
    try {
      o.canonical = read_mesh(so.mesh_path);
      const std::string p = mesh_problem(o.canonical);
      SIMU_CHECK(p.empty(), "{}: {}", so.mesh_path, p);
      if (const int bad = nonmanifold_edges(o.canonical); bad > 0)
        add_flag(d, "non_manifold", fmt::format("{}: {} edges shared by more than two faces; simulated by its convex "
                                                "collision hulls", so.mesh_path, bad));
      // Visual geom in scene.xml only for a mesh current MuJoCo compiles (>= 4 vertices, a volume).
      o.visual_ok = o.canonical.V.rows() >= 4 && std::abs(signed_volume(o.canonical)) * so.scale.prod() > 1e-9;
      const auto b = mesh_aabb(o.canonical);
      if (std::abs(b.size().maxCoeff() - 1.0) > 0.02 || b.center().norm() > 0.02)
        add_flag(d, "not_canonical", fmt::format("mesh AABB longest side {:.3f}, centre offset {:.3f} (expected 1, 0)",
                                                 b.size().maxCoeff(), b.center().norm()));
      readable.push_back(i);
    } catch (const std::exception& e) {
      mesh_errors[i] = e.what();
    }
  }
  return readable;
}

// Collision hulls of the readable meshes, several meshes at a time (cfg.collision.threads, 0 = one
// per hardware thread); a mesh that cannot be decomposed has its error in mesh_errors.
void decompose_objects(Ctx& c, const std::vector<size_t>& readable, std::vector<std::string>& mesh_errors) {
  const unsigned hw = std::max(1u, std::thread::hardware_concurrency());
  const int threads = c.cfg.collision.threads > 0 ? c.cfg.collision.threads : static_cast<int>(hw);
  parallel_for_each(static_cast<int64_t>(readable.size()), threads, [&](int64_t k) {
    const size_t i = readable[static_cast<size_t>(k)];
    try {
      c.objs[i].shape = decompose(c.objs[i].canonical, c.cfg.collision);
      c.objs[i].usable = true;
    } catch (const std::exception& e) {
      mesh_errors[i] = e.what();
    }
  });
}

// Whether object i (usable) can be simulated: its centre inside the room (not behind the floor or a
// wall) and, for an anchored object, a wall to hang on (its own wall_id, else the nearest). Flags it
// otherwise.
bool check_placement(Ctx& c, size_t i, Diagnostics& d) {
  const Scene& scene = c.scene;
  const SceneObject& so = scene.objects[i];
  Obj& o = c.objs[i];
  const Vec3 centre = so.to_world(mesh_aabb(o.canonical).center());
  std::string outside;
  if (scene.floor && scene.floor->distance(centre) < 0) outside = "below the floor";
  for (const auto& w : scene.walls)
    if (w.distance(centre) < 0) outside = "behind wall " + w.id;
  if (!outside.empty()) {
    add_flag(d, "outside_room", "object centre is " + outside);
    return false;
  }
  if (so.dof != PoseDof::Free) {
    int best = -1;
    double best_d = 1e300;
    for (size_t k = 0; k < scene.walls.size(); ++k) {
      if (!so.wall_id.empty() && scene.walls[k].id != so.wall_id) continue;
      const double dist = std::abs(scene.walls[k].distance(centre));
      if (dist < best_d) best_d = dist, best = static_cast<int>(k);
    }
    if (best < 0) {
      add_flag(d, "no_wall", so.wall_id.empty() ? "anchored object but the scene has no walls"
                                                : "anchored object: wall '" + so.wall_id + "' not found");
      return false;
    }
    o.wall = best;
    d.wall_id = scene.walls[best].id;
  }
  return true;
}

}  // namespace

void load_inputs(Ctx& c, std::vector<Diagnostics>& diags) {
  const size_t n = c.scene.objects.size();
  load_bases(c);
  std::vector<std::string> mesh_errors(n);
  const std::vector<size_t> readable = read_object_meshes(c, diags, mesh_errors);
  decompose_objects(c, readable, mesh_errors);
  // Per object: flags, room and wall checks; the others leave the physics.
  for (size_t i = 0; i < n; ++i) {
    const SceneObject& so = c.scene.objects[i];
    Diagnostics& d = diags[i];
    if (!so.error.empty()) {
      add_flag(d, "bad_input", so.error);
    } else if (!c.objs[i].usable) {
      add_flag(d, "mesh_error", mesh_errors[i].empty() ? "no collision hulls" : mesh_errors[i]);
    } else {
      c.objs[i].simulate = check_placement(c, i, d);
    }
  }
  for (size_t i = 0; i < n; ++i)
    if (!c.objs[i].simulate) {
      diags[i].physics_disabled = true;
      diags[i].branch = ProbeBranch::Disabled;
    }
}

}  // namespace probe_detail
}  // namespace simu::physics
