// The physics probe: sequential penetration resolution, gravity diagnostics, stretch-or-resample
// decision, resample hand-off, final composition and outputs (see probe.h).
#include "physics/probe.h"

#include <mujoco/mujoco.h>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#endif

#include <fmt/ranges.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <mutex>
#include <numeric>
#include <thread>

#include <unistd.h>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "physics/mesh.h"
#include "physics/overlay.h"
#include "physics/pictures.h"
#include "physics/raster.h"

namespace simu::physics {

namespace stdfs = std::filesystem;
using nlohmann::json;

const char* to_string(ProbeBranch b) {
  switch (b) {
    case ProbeBranch::None: return "none";
    case ProbeBranch::Stretch: return "stretch";
    case ProbeBranch::Resample: return "resample";
    case ProbeBranch::Anchored: return "anchored";
    case ProbeBranch::Disabled: return "disabled";
  }
  return "none";
}

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

namespace {

// mj_loadXML keeps global compiler state: compile one model at a time.
std::mutex& compile_mutex() {
  static std::mutex m;
  return m;
}

// Per-object working state.
struct Obj {
  bool usable = false;    // has a mesh and collision hulls
  bool simulate = false;  // takes part in the physics (not disabled)
  Mesh canonical;
  CollisionShape shape;
  Vec3 t, s;
  Mat3 R;
  bool visual_ok = false;       // its mesh can be a visual geom of scene.xml
  std::vector<Vec3> pins_body;  // object-frame pins (anchored)
  int wall = -1;                // index into scene.walls (anchored)
};

void add_flag(Diagnostics& d, const std::string& flag, const std::string& msg) {
  if (std::find(d.flags.begin(), d.flags.end(), flag) == d.flags.end()) d.flags.push_back(flag);
  if (!msg.empty()) d.message += (d.message.empty() ? "" : "; ") + msg;
}

// A compiled world for one simulation.
struct World {
  MjModelPtr model;
  MjDataPtr data;
  std::vector<int> obj_body;   // object index -> MuJoCo body id (-1 if absent or static)
  std::vector<bool> env_body;  // MuJoCo body id -> environment (world, planes, bases)
  std::vector<int> body_obj;   // MuJoCo body id -> object index (-1 for environment)
};

struct Ctx {
  const Scene& scene;
  const ProbeConfig& cfg;
  std::vector<Obj>& objs;
  std::vector<BaseBody> bases;
  std::vector<std::vector<Mesh>> base_hulls;  // scaled, base frame
};

std::string safe_name(const std::string& id);

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

// Builds and compiles a world: planes, bases, static objects, dynamic objects (pins optional).
// detect: a diagnostic model (contacts reported detect_margin before touching, no force there).
// visuals: the final file's visual geoms (OBJ files under meshes/); such a model is not compiled here
// (its mesh files do not exist yet): the world returned is compiled from the same text without them.
World build_world(const Ctx& c, const std::vector<int>& statics, const std::vector<int>& dynamics, bool pins,
                  std::string* xml_out = nullptr, const std::vector<int>& visual_only = {}, int buffer_factor = 1,
                  bool detect = false, bool visuals = false) {
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

// A contact of the active body: depth (positive = penetration), push direction (away from the other
// geom), whether the other side is environment, and the other geom id.
struct Touch {
  double dist;
  Vec3 push;
  bool env;
  int other_geom;
};
std::vector<Touch> touches(const World& w, int body) {
  std::vector<Touch> out;
  const mjModel* m = w.model.get();
  const mjData* d = w.data.get();
  for (int i = 0; i < d->ncon; ++i) {
    const mjContact& c = d->contact[i];
    const int b1 = m->geom_bodyid[c.geom1], b2 = m->geom_bodyid[c.geom2];
    if ((b1 == body) == (b2 == body)) continue;
    const Vec3 n(c.frame[0], c.frame[1], c.frame[2]);  // from geom1 to geom2
    const bool active_first = b1 == body;
    const int other_body = active_first ? b2 : b1;
    out.push_back({c.dist, active_first ? Vec3(-n) : n, w.env_body[other_body], active_first ? c.geom2 : c.geom1});
  }
  return out;
}

// Penetration resolution of one dynamic object (paper: environment group first, push by max depth +
// 7 mm along the depth-weighted mean normal, <= 200 iterations, > 0.3 m or surviving contact fails).
// For anchored objects, pushes keep the object on its wall (the wall-normal component is removed
// unless the wall itself is penetrated).
bool resolve_penetration(const Ctx& c, World& w, int i, Vec3* dt, int* iters, double* max_depth, std::string* why) {
  Obj& o = c.objs[i];
  const int body = w.obj_body[i];
  const mjModel* m = w.model.get();
  const Plane* wall = (o.wall >= 0) ? &c.scene.walls[o.wall] : nullptr;
  const int wall_geom = wall ? mj_name2id(m, mjOBJ_GEOM, ("plane:" + wall->id).c_str()) : -1;
  Vec3 t = o.t;
  double path = 0;
  *dt = Vec3::Zero();
  *iters = 0;
  *max_depth = 0;
  for (int it = 0; it <= c.cfg.max_pen_iterations; ++it) {
    set_pose(w, body, t, o.R);
    mj_fwdPosition(m, w.data.get());
    take_warnings(w.data.get());
    std::vector<Touch> env, placed;
    for (const auto& tc : touches(w, body))
      if (tc.dist < -c.cfg.pen_tolerance) (tc.env ? env : placed).push_back(tc);
    if (env.empty() && placed.empty()) {
      *dt = t - o.t;
      o.t = t;
      return true;
    }
    if (it == c.cfg.max_pen_iterations) break;
    const auto& group = env.empty() ? placed : env;
    Vec3 n = Vec3::Zero();
    double dmax = 0;
    bool hits_wall = false;
    for (const auto& tc : group) {
      n += -tc.dist * tc.push;
      dmax = std::max(dmax, -tc.dist);
      hits_wall = hits_wall || tc.other_geom == wall_geom;
    }
    if (it == 0) *max_depth = dmax;
    if (n.norm() < 1e-12) n = -c.scene.gravity;
    n.normalize();
    if (wall && !hits_wall) {
      n -= wall->normal.dot(n) * wall->normal;
      if (n.norm() < 1e-6) n = -c.scene.gravity - (-c.scene.gravity).dot(wall->normal) * wall->normal;
      n.normalize();
    }
    const double step = dmax + c.cfg.push_extra;
    t += step * n;
    path += step;
    *iters = it + 1;
    if (path > c.cfg.max_pen_total) {
      *why = fmt::format("penetration resolution moved {:.3f} m > {:.2f} m", path, c.cfg.max_pen_total);
      return false;
    }
  }
  *why = fmt::format("contact survives {} penetration-resolution iterations", c.cfg.max_pen_iterations);
  return false;
}

// Free-object gravity diagnostic: fall until the first frame with a contact (margin makes it
// visible before touching), then close the remaining gap along gravity.
bool fall_until_contact(const Ctx& c, World& w, int i, Vec3* dt, double* time, std::string* why) {
  Obj& o = c.objs[i];
  const int body = w.obj_body[i];
  const mjModel* m = w.model.get();
  mjData* d = w.data.get();
  set_pose(w, body, o.t, o.R);
  mj_forward(m, d);
  take_warnings(d);
  const Vec3 g = c.scene.gravity;
  const int max_steps = static_cast<int>(std::ceil(c.cfg.max_fall_time / m->opt.timestep));
  std::vector<mjtNum> prev(d->qpos, d->qpos + m->nq);
  std::vector<Touch> hit = touches(w, body);
  int steps = 0;
  while (hit.empty() && steps < max_steps) {
    std::copy(d->qpos, d->qpos + m->nq, prev.begin());
    mj_step(m, d);
    ++steps;
    const int warn = take_warnings(d);
    if (warn & (1 << mjWARN_BADQACC)) {
      *why = "MuJoCo reset the data (bad qacc) during the fall";
      return false;
    }
    // Contacts of this step were computed at the state before integration.
    hit = touches(w, body);
  }
  if (!hit.empty() && steps > 0) std::copy(prev.begin(), prev.end(), d->qpos);
  *time = steps * m->opt.timestep;
  if (hit.empty()) {
    *why = fmt::format("no contact after falling {:.2f} s (no support below)", c.cfg.max_fall_time);
    return false;
  }
  Vec3 t;
  Mat3 R;
  get_pose(w, body, &t, &R);
  // Close the remaining gap (or undo the overshoot) along gravity at the nearest contact.
  const auto nearest = *std::min_element(hit.begin(), hit.end(), [](const Touch& a, const Touch& b) { return a.dist < b.dist; });
  const double cosang = -g.dot(nearest.push);  // gravity points into the surface
  if (cosang > 0.3) t += (nearest.dist / cosang) * g;
  // Free fall does not rotate; keep only the translation along gravity.
  *dt = g.dot(t - o.t) * g;
  o.t += *dt;
  return true;
}

// Anchored-object gravity diagnostic: simulate on the pins until settled.
bool settle_on_pins(const Ctx& c, World& w, int i, Vec3* dt, Mat3* dR, double* time, std::string* why) {
  Obj& o = c.objs[i];
  const int body = w.obj_body[i];
  const mjModel* m = w.model.get();
  mjData* d = w.data.get();
  set_pose(w, body, o.t, o.R);
  mj_forward(m, d);
  take_warnings(d);
  const int max_steps = static_cast<int>(std::ceil(c.cfg.settle_max_time / m->opt.timestep));
  const int hold = std::max(1, static_cast<int>(c.cfg.settle_hold_time / m->opt.timestep));
  int calm = 0, steps = 0;
  while (steps < max_steps && calm < hold) {
    mj_step(m, d);
    ++steps;
    if (take_warnings(d) & (1 << mjWARN_BADQACC)) {
      *why = "MuJoCo reset the data (bad qacc) while settling on the pins";
      return false;
    }
    calm = body_speed(w, body) < c.cfg.settle_speed ? calm + 1 : 0;
  }
  *time = steps * m->opt.timestep;
  Vec3 t;
  Mat3 R;
  get_pose(w, body, &t, &R);
  if (!t.allFinite() || !R.allFinite()) {
    *why = "non-finite pose after settling";
    return false;
  }
  *dt = t - o.t;
  *dR = R * o.R.transpose();
  o.t = t;
  o.R = R;
  return true;
}

// Deepest contact (m, >= 0) of each object in the current contact set (margin contacts with
// dist >= 0 count as 0). A contact between two objects counts for both.
std::vector<double> deepest_contacts(const World& w, size_t n_objects) {
  std::vector<double> deepest(n_objects, 0.0);
  const mjModel* m = w.model.get();
  const mjData* d = w.data.get();
  for (int k = 0; k < d->ncon; ++k) {
    const mjContact& con = d->contact[k];
    const double depth = std::max(0.0, -static_cast<double>(con.dist));
    for (int g : {con.geom1, con.geom2}) {
      const int obj = w.body_obj[m->geom_bodyid[g]];
      if (obj >= 0) deepest[obj] = std::max(deepest[obj], depth);
    }
  }
  return deepest;
}

// Kinetic energy of one body (J): translation of the centre of mass + rotation about it.
double body_kinetic_energy(const mjModel* m, const mjData* d, int body) {
  mjtNum vel[6];  // [angular, linear] at the centre of mass, world frame
  mj_objectVelocity(m, d, mjOBJ_BODY, body, vel, 0);
  const Eigen::Map<const Eigen::Matrix<mjtNum, 3, 3, Eigen::RowMajor>> ximat(d->ximat + 9 * body);
  const Vec3 w_world(vel[0], vel[1], vel[2]), v(vel[3], vel[4], vel[5]);
  const Vec3 w_local = ximat.transpose() * w_world;  // principal inertia frame
  const Vec3 inertia(m->body_inertia[3 * body], m->body_inertia[3 * body + 1], m->body_inertia[3 * body + 2]);
  return 0.5 * m->body_mass[body] * v.squaredNorm() + 0.5 * w_local.dot(inertia.cwiseProduct(w_local));
}

// Outcome of one joint settle over `objects` (Scene::objects indices).
struct SettleRun {
  std::vector<SettleRecord> rec;  // per entry of `objects`
  std::vector<Vec3> t;            // poses after the settle
  std::vector<Mat3> R;
  bool reset = false;             // MuJoCo reset the data (bad qacc): poses are the initial ones
  bool full = false;              // contact buffers still full at the largest size
  double simulated = 0;           // s
  double scene_peak = 0;          // J: max over time of the summed kinetic energy
  int buffer_factor = 1;          // contact/constraint buffer multiplier that sufficed
};

// Joint settle: free objects 6-DoF, anchored ones on their pins, everything under gravity for
// `duration` s; stops early once, over one settle_window, no body moved more than rest_distance.
// Full contact/constraint buffers restart it with larger ones. Records per object: displacement,
// deepest contact at the start and at the end, peak kinetic energy, category.
SettleRun joint_settle(const Ctx& c, const std::vector<int>& objects, double duration, double rest_distance) {
  SettleRun run;
  const size_t n = objects.size();
  bool full = true;
  World w;
  for (run.buffer_factor = 1; full; run.buffer_factor *= 2) {
    w = build_world(c, {}, objects, true, nullptr, {}, run.buffer_factor);
    const mjModel* m = w.model.get();
    mjData* d = w.data.get();
    // Start: poses and contacts (build_world ran mj_forward).
    const std::vector<double> depth0 = deepest_contacts(w, c.objs.size());
    run.rec.assign(n, SettleRecord{});
    run.t.assign(n, Vec3::Zero());
    run.R.assign(n, Mat3::Identity());
    std::vector<Vec3> t0(n), last(n);
    for (size_t k = 0; k < n; ++k) {
      const int i = objects[k];
      SettleRecord& r = run.rec[k];
      r.category = metric_category(c.scene.objects[i].dof);
      r.initial_penetration = depth0[i];
      r.initially_penetrating = depth0[i] > c.cfg.metrics.penetration_depth;
      get_pose(w, w.obj_body[i], &t0[k], &run.R[k]);
      last[k] = Eigen::Map<const Vec3>(d->xpos + 3 * w.obj_body[i]);
    }
    const int steps = static_cast<int>(std::ceil(duration / m->opt.timestep));
    const int window = std::max(1, static_cast<int>(c.cfg.settle_window / m->opt.timestep));
    run.scene_peak = 0;
    run.reset = false;
    full = false;
    bool calm = false;
    int s = 0;
    for (; s < steps && !calm; ++s) {
      mj_step(m, d);
      const int warn = take_warnings(d);
      if (warn & ((1 << mjWARN_CONTACTFULL) | (1 << mjWARN_CNSTRFULL))) {
        // Restart with larger buffers; at the largest size go on (contacts beyond it are dropped).
        if (run.buffer_factor < 8) {
          full = true;
          break;
        }
        run.full = true;
      }
      if (warn & (1 << mjWARN_BADQACC)) {
        run.reset = true;
        break;
      }
      // Kinetic energy of each object and of the scene (velocities of the state this step started from).
      double total = 0;
      for (size_t k = 0; k < n; ++k) {
        const double e = body_kinetic_energy(m, d, w.obj_body[objects[k]]);
        run.rec[k].peak_kinetic_energy = std::max(run.rec[k].peak_kinetic_energy, e);
        total += e;
      }
      run.scene_peak = std::max(run.scene_peak, total);
      // Rest test every window: no body moved more than rest_distance since the last one.
      if ((s + 1) % window == 0) {
        double moved = 0;
        for (size_t k = 0; k < n; ++k) {
          const Vec3 p = Eigen::Map<const Vec3>(d->xpos + 3 * w.obj_body[objects[k]]);
          moved = std::max(moved, (p - last[k]).norm());
          last[k] = p;
        }
        calm = moved < rest_distance;
      }
    }
    if (full) continue;
    run.simulated = s * m->opt.timestep;
    if (run.reset) {
      // The data was reset to qpos0: report the initial poses, no motion measured.
      for (size_t k = 0; k < n; ++k) run.t[k] = t0[k];
      break;
    }
    // End: poses, displacement, contacts of the final state.
    mj_forward(m, d);
    take_warnings(d);
    const std::vector<double> depth1 = deepest_contacts(w, c.objs.size());
    for (size_t k = 0; k < n; ++k) {
      get_pose(w, w.obj_body[objects[k]], &run.t[k], &run.R[k]);
      run.rec[k].displacement = (run.t[k] - t0[k]).norm();
      run.rec[k].max_penetration = depth1[objects[k]];
    }
    break;
  }
  return run;
}

// Object-side pins at the object's current pose, paired with its wall (anchored objects).
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

// The metrics settle over `live` objects: a PhysicsEvaluation over every scene object (the others
// are physics_disabled records at their current pose).
PhysicsEvaluation evaluate_settle(const Ctx& c, const std::vector<int>& live, double duration) {
  using clock = std::chrono::steady_clock;
  const auto t0 = clock::now();
  PhysicsEvaluation ev;
  const size_t n = c.objs.size();
  ev.objects.assign(n, SettleRecord{});
  ev.t.resize(n);
  ev.R.resize(n);
  for (size_t i = 0; i < n; ++i) {
    ev.objects[i].category = metric_category(c.scene.objects[i].dof);
    ev.objects[i].physics_disabled = true;
    ev.t[i] = c.objs[i].t, ev.R[i] = c.objs[i].R;
  }
  if (!live.empty() && duration > 0) {
    try {
      const SettleRun run = joint_settle(c, live, duration, c.cfg.metrics_rest_distance);
      for (size_t k = 0; k < live.size(); ++k) {
        const int i = live[k];
        ev.objects[i] = run.rec[k];
        ev.t[i] = run.t[k], ev.R[i] = run.R[k];
      }
      ev.ran = true;
      ev.solver_reset = run.reset;
      ev.scene_peak_energy = run.scene_peak;
      ev.simulated_time = run.simulated;
      if (run.reset) ev.message = "MuJoCo reset the data (bad qacc) during the evaluation settle";
      if (run.full) ev.message = "contact buffers full during the evaluation settle";
    } catch (const std::exception& e) {
      ev.message = std::string("evaluation settle failed: ") + e.what();
      log::warn("{}", ev.message);
    }
  }
  ev.metrics = physics_metrics(ev.objects, c.cfg.metrics, ev.ran ? ev.scene_peak_energy : -1);
  ev.seconds = std::chrono::duration<double>(clock::now() - t0).count();
  return ev;
}

// Best-of-N: the stability figure of one candidate shape for object i. The candidate is placed at
// `centre` with `statics` as static colliders, its penetration resolved, then it settles alone for
// candidate_settle_time (stopping once at rest over settle_window). displacement = |final - centre|
// (the push out of penetration included). The object's working state is restored afterwards.
Diagnostics::Candidate settle_candidate(const Ctx& c, const std::vector<int>& statics, int i,
                                        const ProbeShapeCandidate& cand, const CollisionShape& shape, const Vec3& centre) {
  Diagnostics::Candidate rec;
  rec.label = cand.label;
  Obj& o = c.objs[i];
  const Obj saved = o;
  try {
    o.canonical = cand.mesh;
    o.shape = shape;
    o.R = cand.R;
    o.s = cand.scale;
    o.t = centre;
    World w = build_world(c, statics, {i}, false);
    Vec3 dt;
    int iters = 0;
    double depth = 0;
    std::string why;
    rec.ok = resolve_penetration(c, w, i, &dt, &iters, &depth, &why);
    rec.penetration = depth;
    if (!rec.ok) {
      rec.message = why;
      rec.displacement = dt.norm();
    } else {
      // Settle alone until at rest over one window, or candidate_settle_time.
      const mjModel* m = w.model.get();
      const int body = w.obj_body[i];
      set_pose(w, body, o.t, o.R);
      mj_forward(m, w.data.get());
      take_warnings(w.data.get());
      const int steps = static_cast<int>(std::ceil(c.cfg.candidate_settle_time / m->opt.timestep));
      const int window = std::max(1, static_cast<int>(c.cfg.settle_window / m->opt.timestep));
      Vec3 last = o.t;
      for (int s = 0; s < steps; ++s) {
        mj_step(m, w.data.get());
        if (take_warnings(w.data.get()) & (1 << mjWARN_BADQACC)) {
          rec.ok = false;
          rec.message = "MuJoCo reset the data (bad qacc) while settling the candidate";
          break;
        }
        if ((s + 1) % window == 0) {
          const Vec3 p = Eigen::Map<const Vec3>(w.data->xpos + 3 * body);
          const bool calm = (p - last).norm() < c.cfg.settle_rest_distance;
          last = p;
          if (calm) break;
        }
      }
      Vec3 t;
      Mat3 R;
      get_pose(w, body, &t, &R);
      if (!t.allFinite() || !R.allFinite()) {
        rec.ok = false;
        rec.message = "non-finite pose after the candidate's settle";
      } else {
        rec.displacement = (t - centre).norm();
        rec.rotation_deg = std::acos(std::clamp(((R * cand.R.transpose()).trace() - 1.0) / 2.0, -1.0, 1.0)) * 180.0 / M_PI;
      }
    }
  } catch (const std::exception& e) {
    rec.ok = false;
    rec.message = e.what();
  }
  o = saved;
  return rec;
}

// Fills the resample hand-off: modal mask, auxiliary mask M' (raster.h: modal mask united with the
// projection of the lowest part of B_str), target OBB B_str.
ProbeResampleRequest make_request(const Scene& scene, int i, const Diagnostics& d, const Diagnosis& dg,
                             const CorrectionConfig& cc) {
  ProbeResampleRequest r;
  r.object_index = i;
  r.object_id = scene.objects[i].id;
  r.image_path = scene.image_path;
  r.mask_path = scene.objects[i].mask_path;
  r.target_obb = d.obb_target;
  const Camera& cam = scene.camera;
  if (!cam.valid()) return r;
  BinaryMask modal(cam.width, cam.height);
#ifdef SIMU_HAVE_OPENCV
  if (!r.mask_path.empty() && stdfs::exists(r.mask_path)) {
    cv::Mat m = cv::imread(r.mask_path, cv::IMREAD_GRAYSCALE);
    if (!m.empty() && (m.cols != cam.width || m.rows != cam.height))
      cv::resize(m, m, cv::Size(cam.width, cam.height), 0, 0, cv::INTER_NEAREST);
    if (!m.empty())
      for (int y = 0; y < cam.height; ++y)
        for (int x = 0; x < cam.width; ++x) modal.at(y, x) = m.at<uint8_t>(y, x) ? 255 : 0;
  }
#endif
  BinaryMask aux = auxiliary_crop_mask(cam, modal, dg, cc);
#ifdef SIMU_HAVE_OPENCV
  r.modal_mask = cv::Mat(cam.height, cam.width, CV_8UC1, modal.data.data()).clone();
  r.aux_mask = cv::Mat(cam.height, cam.width, CV_8UC1, aux.data.data()).clone();
#else
  r.modal_mask = MaskImage{modal.width, modal.height, modal.data};
  r.aux_mask = MaskImage{aux.width, aux.height, aux.data};
#endif
  return r;
}

std::string safe_name(const std::string& id) {
  std::string s;
  for (char ch : id) s += (std::isalnum(static_cast<unsigned char>(ch)) || ch == '-' || ch == '_') ? ch : '_';
  return s.empty() ? "object" : s;
}

json vec_j(const Vec3& v) { return json::array({v[0], v[1], v[2]}); }
json mat_j(const Mat3& m) {
  return json::array({json::array({m(0, 0), m(0, 1), m(0, 2)}), json::array({m(1, 0), m(1, 1), m(1, 2)}),
                      json::array({m(2, 0), m(2, 1), m(2, 2)})});
}
json box_j(const Obb& b) { return {{"center", vec_j(b.center)}, {"axes", mat_j(b.axes)}, {"extents", vec_j(b.extents)}}; }
double angle_of(const Mat3& R) { return std::acos(std::clamp((R.trace() - 1.0) / 2.0, -1.0, 1.0)); }

// Sequential order: ascending lowest world-AABB corner along gravity.
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

// The overlay PNG (overlay.h) of a probe run: modal masks (or the rendered visible masks of the
// corrected objects), OBBs before / targeted, auxiliary crop masks of the resample requests.
void write_overlay(const ProbeResult& res, const std::vector<Obj>& objs, const std::string& path) {
  const Scene& scene = res.scene;
  const size_t n = scene.objects.size();
  // Visible masks of the corrected scene (for objects without a modal mask file).
  std::vector<Mesh> world(n);
  std::vector<const Mesh*> ptrs(n, nullptr);
  for (size_t i = 0; i < n; ++i)
    if (objs[i].usable) {
      world[i] = transform_mesh(objs[i].canonical, objs[i].R * objs[i].s.asDiagonal(), objs[i].t);
      ptrs[i] = &world[i];
    }
  const LabelImage labels = render_labels(scene.camera, ptrs);
  std::vector<BinaryMask> masks(n), aux(n);
  std::vector<OverlayItem> items(n);
  for (size_t i = 0; i < n; ++i) {
    const SceneObject& so = scene.objects[i];
    const Diagnostics& d = res.diagnostics[i];
    OverlayItem& it = items[i];
    it.label = so.id + " " + to_string(d.branch);
    try {
      if (!so.mask_path.empty() && stdfs::exists(so.mask_path)) masks[i] = read_mask(so.mask_path);
    } catch (const std::exception& e) {
      log::warn("overlay: {}", e.what());
    }
    if (masks[i].width != scene.camera.width || masks[i].height != scene.camera.height) masks[i] = labels.mask_of(int(i));
    it.mask = &masks[i];
    if (d.obb_pre.extents.minCoeff() > 0) it.obb = d.obb_pre;
    if ((d.branch == ProbeBranch::Stretch || d.branch == ProbeBranch::Resample) && d.obb_target.extents.minCoeff() > 0)
      it.obb_target = d.obb_target;
  }
  for (const ProbeResampleRequest& r : res.resample_requests) {
    if (r.object_index < 0 || r.object_index >= int(n) || r.aux_mask.empty()) continue;
    BinaryMask& m = aux[r.object_index];
#ifdef SIMU_HAVE_OPENCV
    m = BinaryMask(r.aux_mask.cols, r.aux_mask.rows);
    for (int y = 0; y < m.height; ++y)
      for (int x = 0; x < m.width; ++x) m.at(y, x) = r.aux_mask.at<uint8_t>(y, x) ? 1 : 0;
#else
    m = BinaryMask(r.aux_mask.width, r.aux_mask.height);
    for (size_t k = 0; k < m.data.size(); ++k) m.data[k] = r.aux_mask.data[k] ? 1 : 0;
#endif
    items[r.object_index].aux_mask = &m;
  }
  write_overlay_png(path, scene.camera, scene.image_path, items);
}

// Step 1 of the probe (and of evaluate_physics): bases read and decomposed (a bad base is skipped
// with a warning), objects read, decomposed and checked; problems flag the object, the rest goes on.
void load_inputs(Ctx& c, std::vector<Diagnostics>& diags) {
  const Scene& scene = c.scene;
  const ProbeConfig& cfg = c.cfg;
  std::vector<Obj>& objs = c.objs;
  const size_t n = scene.objects.size();
  // 1. Bases: read, decompose, scale (a bad base is skipped with a warning).
  for (const auto& b : scene.bases) {
    if (!b.error.empty()) {
      log::warn("base skipped: {}", b.error);
      continue;
    }
    try {
      const Mesh mesh = read_mesh(b.mesh_path);
      const std::string p = mesh_problem(mesh);
      SIMU_CHECK(p.empty(), "base {}: {}", b.id, p);
      const auto shape = decompose(mesh, cfg.collision);
      c.bases.push_back(b);
      c.base_hulls.push_back(transform_hulls(shape.hulls, b.scale.asDiagonal()));
    } catch (const std::exception& e) {
      log::warn("base {} skipped: {}", b.id, e.what());
    }
  }

  // 1. Objects: meshes read and checked; problems flag the object, the rest goes on.
  std::vector<std::string> mesh_errors(n);
  std::vector<size_t> to_decompose;
  for (size_t i = 0; i < n; ++i) {
    const SceneObject& so = scene.objects[i];
    Diagnostics& d = diags[i];
    Obj& o = objs[i];
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
      to_decompose.push_back(i);
    } catch (const std::exception& e) {
      mesh_errors[i] = e.what();
    }
  }
  // Collision hulls of every readable mesh, several meshes at a time (cfg.collision.threads).
  {
    const unsigned hw = std::max(1u, std::thread::hardware_concurrency());
    const size_t nthreads = std::min<size_t>(to_decompose.size(), cfg.collision.threads > 0 ? size_t(cfg.collision.threads) : hw);
    std::atomic<size_t> next{0};
    auto worker = [&] {
      for (size_t k = next++; k < to_decompose.size(); k = next++) {
        const size_t i = to_decompose[k];
        try {
          objs[i].shape = decompose(objs[i].canonical, cfg.collision);
          objs[i].usable = true;
        } catch (const std::exception& e) {
          mesh_errors[i] = e.what();
        }
      }
    };
    if (nthreads <= 1) {
      worker();
    } else {
      std::vector<std::thread> pool;
      for (size_t t = 0; t < nthreads; ++t) pool.emplace_back(worker);
      for (auto& t : pool) t.join();
    }
  }
  // Per object: flags, room and wall checks.
  for (size_t i = 0; i < n; ++i) {
    const SceneObject& so = scene.objects[i];
    Diagnostics& d = diags[i];
    Obj& o = objs[i];
    if (!so.error.empty()) {
      add_flag(d, "bad_input", so.error);
      continue;
    }
    if (!o.usable) {
      add_flag(d, "mesh_error", mesh_errors[i].empty() ? "no collision hulls" : mesh_errors[i]);
      continue;
    }
    // Outside the room: centre behind the floor or a wall.
    const Vec3 centre = so.to_world(mesh_aabb(o.canonical).center());
    std::string outside;
    if (scene.floor && scene.floor->distance(centre) < 0) outside = "below the floor";
    for (const auto& w : scene.walls)
      if (w.distance(centre) < 0) outside = "behind wall " + w.id;
    if (!outside.empty()) {
      add_flag(d, "outside_room", "object centre is " + outside);
      continue;
    }
    // Anchored objects need a wall.
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
        continue;
      }
      o.wall = best;
      d.wall_id = scene.walls[best].id;
    }
    o.simulate = true;
  }
  for (size_t i = 0; i < n; ++i)
    if (!objs[i].simulate) {
      diags[i].physics_disabled = true;
      diags[i].branch = ProbeBranch::Disabled;
    }

}

// Writes every output of a probe run into `dir` (which exists and is empty): meshes, scene.json
// (mesh paths relative, valid once dir is moved to final_dir), scene.xml (checked by compiling it from
// disk with MuJoCo 2.2; without its visual meshes when they do not compile), hand-off, report, pictures.
void write_outputs_into(ProbeResult& res, const std::vector<Obj>& objs, const std::string& dir,
                        const std::string& final_dir) {
  Scene& scene = res.scene;
  const size_t n = scene.objects.size();
  stdfs::create_directories(dir + "/meshes");
  for (size_t i = 0; i < n; ++i) {
    if (!objs[i].usable) continue;
    const std::string name = "meshes/" + safe_name(scene.objects[i].id) + ".obj";
    try {
      write_mesh(objs[i].canonical, dir + "/" + name);
      scene.objects[i].mesh_path = (stdfs::absolute(final_dir) / name).lexically_normal().string();
    } catch (const std::exception& e) {
      add_flag(res.diagnostics[i], "write_failed", e.what());
    }
  }
  fs::atomic_write(dir + "/scene.json", scene_to_json(scene, stdfs::absolute(final_dir).string()).dump(2) + "\n");
  if (!res.mjcf.empty()) {
    fs::atomic_write(dir + "/scene.xml", res.mjcf);
    try {
      std::lock_guard<std::mutex> lock(compile_mutex());
      load_mjcf_file(dir + "/scene.xml");
    } catch (const std::exception& e) {
      // A visual mesh MuJoCo cannot compile must not cost the user the scene: drop the visual geoms.
      log::warn("scene.xml with visual meshes does not compile ({}); written without them", e.what());
      std::string xml = res.mjcf;
      for (size_t p; (p = xml.find("/visual\"")) != std::string::npos;) {
        const size_t start = xml.rfind('\n', p), end = xml.find('\n', p);
        xml.erase(start, end - start);
      }
      res.mjcf = xml;
      fs::atomic_write(dir + "/scene.xml", res.mjcf);
    }
  }
  // Resample hand-off files (masks and target OBB).
  for (const auto& r : res.resample_requests) {
    const std::string rdir = dir + "/resample/" + safe_name(r.object_id);
    stdfs::create_directories(rdir);
    json j = {{"object_index", r.object_index}, {"object_id", r.object_id}, {"image", r.image_path},
              {"mask", r.mask_path}, {"target_obb", box_j(r.target_obb)},
              {"translation", vec_j(r.target_obb.center)}};
#ifdef SIMU_HAVE_OPENCV
    if (!r.aux_mask.empty()) {
      cv::imwrite(rdir + "/aux_mask.png", r.aux_mask);
      j["aux_mask"] = "aux_mask.png";
    }
#endif
    fs::atomic_write(rdir + "/request.json", j.dump(2) + "\n");
  }
  fs::atomic_write(dir + "/report.json", report_json(res).dump(2) + "\n");
  // Pictures for a person to look at (need OpenCV's PNG codec and a camera).
#ifdef SIMU_HAVE_OPENCV
  if (scene.camera.valid()) {
    try {
      write_overlay(res, objs, dir + "/overlay.png");
    } catch (const std::exception& e) {
      log::warn("overlay.png not written: {}", e.what());
    }
    try {
      for (const auto& f : write_probe_pictures(res, dir))
        res.pictures.push_back((stdfs::path(final_dir) / stdfs::path(f).filename()).string());
    } catch (const std::exception& e) {
      log::warn("pictures not written: {}", e.what());
    }
  } else {
    log::info("pictures skipped: the scene has no valid camera");
  }
#else
  log::info("pictures skipped: built without OpenCV (SIMU_WITH_OPENCV=OFF)");
#endif
}

void write_outputs(ProbeResult& res, const std::vector<Obj>& objs, const std::string& out_dir, const ProbeConfig& cfg) {
  const stdfs::path final_dir = stdfs::absolute(out_dir).lexically_normal();
  const stdfs::path parent = final_dir.parent_path();
  const std::string base = final_dir.filename().string();
  stdfs::create_directories(parent);
  // Staging folders of writers that died (their pid is gone) are removed.
  const std::string prefix = "." + base + ".staging-";
  for (const auto& e : stdfs::directory_iterator(parent)) {
    const std::string name = e.path().filename().string();
    if (name.rfind(prefix, 0) != 0) continue;
    const std::string pid = name.substr(prefix.size());
    if (!pid.empty() && pid.find_first_not_of("0123456789") == std::string::npos &&
        !stdfs::exists("/proc/" + pid)) fs::remove_tree(e.path().string());
  }
  if (stdfs::exists(final_dir) && !cfg.overwrite)
    fail_hint("pass --overwrite (probe) or choose another --out", "output folder {} already exists; not overwritten",
              final_dir.string());
  const std::string staging = (parent / (prefix + std::to_string(::getpid()))).string();
  fs::remove_tree(staging);
  try {
    write_outputs_into(res, objs, staging, final_dir.string());
    if (stdfs::exists(final_dir)) {
      // Replace: swap atomically where the filesystem can, else move the old one aside first.
      if (!fs::atomic_exchange(staging, final_dir.string())) {
        const std::string old = (parent / ("." + base + ".old-" + std::to_string(::getpid()))).string();
        fs::atomic_rename(final_dir.string(), old);
        fs::atomic_rename(staging, final_dir.string());
        fs::remove_tree(old);
      } else {
        fs::remove_tree(staging);  // now holds the previous output
      }
    } else {
      fs::atomic_rename(staging, final_dir.string());
    }
  } catch (...) {
    try { fs::remove_tree(staging); } catch (...) {}
    throw;
  }
  // The corrected scene's mesh paths point into the final folder.
}

}  // namespace

nlohmann::json report_json(const ProbeResult& r) {
  json objs = json::array();
  for (size_t i = 0; i < r.diagnostics.size(); ++i) {
    const auto& d = r.diagnostics[i];
    json e;
    e["id"] = r.scene.objects[i].id;
    e["dof"] = to_string(r.scene.objects[i].dof);
    e["order"] = d.order;
    e["branch"] = to_string(d.branch);
    e["physics_disabled"] = d.physics_disabled;
    e["flags"] = d.flags;
    e["message"] = d.message;
    e["dt_pen"] = vec_j(d.dt_pen);
    e["pen_iterations"] = d.pen_iterations;
    e["pen_max_depth"] = d.pen_max_depth;
    e["dt_grv"] = vec_j(d.dt_grv);
    e["dR_grv"] = mat_j(d.dR_grv);
    e["dR_grv_deg"] = angle_of(d.dR_grv) * 180.0 / M_PI;
    e["sim_time"] = d.sim_time;
    e["rho"] = d.rho;
    e["eta"] = d.eta;
    e["ell"] = d.ell;
    e["u_grv"] = vec_j(d.u_grv);
    e["obb_pre"] = box_j(d.obb_pre);
    if (d.branch == ProbeBranch::Stretch || d.branch == ProbeBranch::Resample) e["obb_target"] = box_j(d.obb_target);
    if (!d.pins_world.empty()) {
      e["pins"] = json::array();
      for (size_t k = 0; k < d.pins_world.size(); ++k)
        e["pins"].push_back({{"object", vec_j(d.pins_world[k])}, {"wall", vec_j(d.wall_points[k])}});
      e["wall"] = d.wall_id;
    }
    e["t_pre"] = vec_j(d.t_pre);
    e["dt_final_pen"] = vec_j(d.dt_final_pen);
    e["settle_displacement"] = d.settle_displacement;
    e["reverted"] = d.reverted;
    e["final_settle"] = settle_json(d.final_settle);
    e["evaluation"] = settle_json(d.evaluation);
    if (r.input_evaluation.ran && i < r.input_evaluation.objects.size())
      e["evaluation_input"] = settle_json(r.input_evaluation.objects[i]);  // the input scene, settled the same way
    // What changed: OBB extents before / after, displacement of the OBB centre.
    e["change"] = {{"obb_extents_before", vec_j(d.obb_pre.extents)},
                   {"obb_extents_after", vec_j(d.obb_final.extents)},
                   {"displacement", (d.obb_final.center - d.obb_pre.center).norm()}};
    if (d.branch == ProbeBranch::Resample) {
      json rs = {{"resampled", d.resampled}, {"message", d.resample_message}};
      if (d.resampled)
        rs["placed"] = {{"t", vec_j(d.t_resampled)}, {"R", mat_j(d.R_resampled)}, {"scale", vec_j(d.s_resampled)}};
      if (d.has_crop_box) rs["crop_box"] = d.crop_box;
      if (!d.candidates.empty()) {
        rs["chosen_candidate"] = d.chosen_candidate;
        rs["candidates"] = json::array();
        for (size_t k = 0; k < d.candidates.size(); ++k) {
          const auto& cd = d.candidates[k];
          rs["candidates"].push_back({{"label", cd.label}, {"ok", cd.ok}, {"displacement", cd.displacement},
                                      {"rotation_deg", cd.rotation_deg}, {"penetration", cd.penetration}, {"message", cd.message},
                                      {"chosen", static_cast<int>(k) == d.chosen_candidate}});
        }
      }
      e["resample"] = rs;
    }
    objs.push_back(e);
  }
  json metrics = metrics_json(r.evaluation.metrics);
  metrics["settle_time"] = r.evaluation.simulated_time;
  metrics["solver_reset"] = r.evaluation.solver_reset;
  if (!r.evaluation.message.empty()) metrics["message"] = r.evaluation.message;
  json headline = {{"after", headline_json(r.after)}};
  if (r.before.computed) headline["before"] = headline_json(r.before);
  return {{"objects", objs},
          {"order", r.order},
          {"metrics", metrics},
          {"headline", headline},
          {"seconds",
           {{"probe", r.seconds_probe}, {"resample", r.seconds_resample}, {"final", r.seconds_final}, {"metrics", r.seconds_metrics}}}};
}

HeadlineMetrics headline_metrics(const Scene& scene, const std::vector<const Mesh*>& world,
                                 const PhysicsEvaluation& settle, const MetricsConfig& config) {
  HeadlineMetrics h;
  const size_t n = scene.objects.size();
  SIMU_CHECK(world.size() == n && settle.objects.size() == n, "headline_metrics: {} objects, {} meshes, {} records", n,
             world.size(), settle.objects.size());
  h.physics = physics_metrics(settle.objects, config, settle.ran ? settle.scene_peak_energy : -1);
  // Objects with ground truth first (identity pairs i <-> i), the others only as predictions.
  auto scored = [&](const std::vector<int>& with, const auto& iou_of) {
    std::vector<int> order = with;
    for (size_t i = 0; i < n; ++i)
      if (std::find(with.begin(), with.end(), int(i)) == with.end()) order.push_back(int(i));
    std::vector<bool> valid;
    std::vector<MetricCategory> cat;
    for (int j : order) {
      valid.push_back(world[j] != nullptr && is_valid(settle.objects[j], config));
      cat.push_back(metric_category(scene.objects[j].dof));
    }
    std::vector<std::vector<double>> iou(with.size(), std::vector<double>(order.size(), 0.0));
    for (size_t a = 0; a < with.size(); ++a)
      for (size_t b = 0; b < order.size(); ++b) iou[a][b] = iou_of(with[a], order[b]);
    return overlap_metrics(iou, valid, cat);
  };
  // 2D: visible masks of the jointly rendered meshes against the input masks.
  std::vector<BinaryMask> gt(n);
  std::vector<int> with_mask, with_box;
  for (size_t i = 0; i < n; ++i) {
    const auto& so = scene.objects[i];
    if (so.gt_box) with_box.push_back(int(i));
    if (so.mask_path.empty() || !scene.camera.valid()) continue;
    try {
      gt[i] = read_mask(so.mask_path);
      if (gt[i].width == scene.camera.width && gt[i].height == scene.camera.height) with_mask.push_back(int(i));
    } catch (const std::exception& e) {
      log::debug("headline metrics: {}", e.what());
    }
  }
  if (!with_mask.empty()) {
    const LabelImage img = render_labels(scene.camera, world);
    std::vector<BinaryMask> pred(n);
    for (size_t j = 0; j < n; ++j) pred[j] = img.mask_of(int(j));
    h.mask = scored(with_mask, [&](int i, int j) { return mask_iou(gt[i], pred[j]); });
    h.has_masks = true;
  }
  if (!with_box.empty()) {
    h.box = scored(with_box, [&](int i, int j) {
      return world[j] && world[j]->V.rows() ? box_iou(*scene.objects[i].gt_box, world_aabb(*world[j])) : 0.0;
    });
    h.has_boxes = true;
  }
  h.computed = true;
  return h;
}

std::string format_headline(const HeadlineMetrics& b, const HeadlineMetrics& a, double settle_time) {
  std::string s = fmt::format("{:<34} {:>9} {:>9}\n", fmt::format("metric (after a {:g} s settle)", settle_time),
                              b.computed ? "before" : "", "after");
  auto row = [&](const std::string& name, bool have_b, double vb, bool have_a, double va, const char* f) {
    const std::string sb = b.computed && have_b ? fmt::format(fmt::runtime(f), vb) : "n/a";
    const std::string sa = have_a ? fmt::format(fmt::runtime(f), va) : "n/a";
    s += fmt::format("{:<34} {:>9} {:>9}\n", name, sb, sa);
  };
  row("ABO (2D)", b.has_masks, b.mask.abo, a.has_masks, a.mask.abo, "{:.4f}");
  row("ABO_fh/fo (2D, strict)", b.has_masks, b.mask.abo_fhfo(), a.has_masks, a.mask.abo_fhfo(), "{:.4f}");
  row("IoU (2D)", b.has_masks, b.mask.iou, a.has_masks, a.mask.iou, "{:.4f}");
  row("IoU_fh/fo (2D, strict)", b.has_masks, b.mask.iou_fhfo(), a.has_masks, a.mask.iou_fhfo(), "{:.4f}");
  if (a.has_boxes || b.has_boxes) {
    row("3D ABO (AABB)", b.has_boxes, b.box.abo, a.has_boxes, a.box.abo, "{:.4f}");
    row("3D ABO_fh/fo", b.has_boxes, b.box.abo_fhfo(), a.has_boxes, a.box.abo_fhfo(), "{:.4f}");
    row("3D IoU (AABB)", b.has_boxes, b.box.iou, a.has_boxes, a.box.iou, "{:.4f}");
    row("3D IoU_fh/fo", b.has_boxes, b.box.iou_fhfo(), a.has_boxes, a.box.iou_fhfo(), "{:.4f}");
  }
  row("stability (%, free, < 5 cm)", true, b.physics.stability, true, a.physics.stability, "{:.1f}");
  row("penetration ratio (%, > 2 mm)", true, b.physics.penetration_ratio, true, a.physics.penetration_ratio, "{:.1f}");
  row("D_mean (mm)", true, 1000 * b.physics.mean_displacement, true, 1000 * a.physics.mean_displacement, "{:.2f}");
  row("E_pk (J)", true, b.physics.peak_energy, true, a.physics.peak_energy, "{:.4g}");
  return s;
}

nlohmann::json headline_json(const HeadlineMetrics& m) {
  auto ov = [](const OverlapMetrics& o) {
    return json{{"abo", o.abo}, {"abo_fh", o.abo_fh}, {"abo_fo", o.abo_fo}, {"abo_fhfo", o.abo_fhfo()}, {"iou", o.iou},
                {"iou_fh", o.iou_fh}, {"iou_fo", o.iou_fo}, {"iou_fhfo", o.iou_fhfo()}, {"n_gt", o.n_gt},
                {"n_fh", o.n_fh}, {"n_fo", o.n_fo}};
  };
  json j = {{"physics", metrics_json(m.physics)}};
  if (m.has_masks) j["mask_2d"] = ov(m.mask);
  if (m.has_boxes) j["box_3d"] = ov(m.box);
  return j;
}

nlohmann::json settle_json(const SettleRecord& r) {
  const char* cat = r.category == MetricCategory::Free ? "free" : r.category == MetricCategory::Hanging ? "hanging" : "fixed";
  return {{"category", cat},
          {"physics_disabled", r.physics_disabled},
          {"displacement", r.displacement},
          {"initial_penetration", r.initial_penetration},
          {"initially_penetrating", r.initially_penetrating},
          {"final_penetration", r.max_penetration},
          {"peak_kinetic_energy", r.peak_kinetic_energy}};
}

nlohmann::json metrics_json(const PhysicsMetrics& m) {
  return {{"stability", m.stability},
          {"stability_count", m.stability_count},
          {"penetration_ratio", m.penetration_ratio},
          {"initial_penetration_ratio", m.initial_penetration_ratio},
          {"evaluated_count", m.evaluated_count},
          {"disabled_count", m.disabled_count},
          {"mean_displacement", m.mean_displacement},
          {"peak_energy", m.peak_energy}};
}

PhysicsEvaluation evaluate_physics(const Scene& scene_in, const ProbeConfig& cfg, double settle_time) {
  Scene scene = scene_in;
  const size_t n = scene.objects.size();
  std::vector<Obj> objs(n);
  std::vector<Diagnostics> diags(n);
  Ctx c{scene, cfg, objs, {}, {}};
  load_inputs(c, diags);
  // Every usable object as read; anchored ones pinned to their wall at this pose.
  std::vector<int> live;
  for (size_t i = 0; i < n; ++i) {
    if (!objs[i].simulate) continue;
    if (scene.objects[i].dof != PoseDof::Free) place_pins(c, static_cast<int>(i), diags[i]);
    live.push_back(static_cast<int>(i));
  }
  return evaluate_settle(c, live, settle_time < 0 ? cfg.metrics_settle_time : settle_time);
}

ProbeResult run_probe(const Scene& scene_in, const ProbeConfig& cfg, const std::string& out_dir,
                      const ResampleFn& resampler, const ProbeProgress& progress) {
  using clock = std::chrono::steady_clock;
  const auto t0 = clock::now();
  ProbeResult res;
  res.scene = scene_in;
  Scene& scene = res.scene;
  const size_t n = scene.objects.size();
  res.diagnostics.resize(n);
  std::vector<Obj> objs(n);
  Ctx c{scene, cfg, objs, {}, {}};

  if (!out_dir.empty() && cfg.write_outputs && !cfg.overwrite && stdfs::exists(out_dir))
    fail_hint("pass --overwrite (probe) or choose another --out", "output folder {} already exists; not overwritten", out_dir);
  load_inputs(c, res.diagnostics);

  // "Before" column of the headline metrics: the input scene settled exactly like the final one
  // (anchored objects pinned at their input pose).
  if (cfg.evaluate_input && cfg.metrics_settle_time > 0) {
    std::vector<int> live_in;
    for (size_t i = 0; i < n; ++i) {
      if (!objs[i].simulate) continue;
      if (scene.objects[i].dof != PoseDof::Free) {
        Diagnostics scratch;
        place_pins(c, static_cast<int>(i), scratch);
      }
      live_in.push_back(static_cast<int>(i));
    }
    res.input_evaluation = evaluate_settle(c, live_in, cfg.metrics_settle_time);
    std::vector<Mesh> world(n);
    std::vector<const Mesh*> ptrs(n, nullptr);
    for (size_t i = 0; i < n; ++i)
      if (objs[i].usable) {
        world[i] = transform_mesh(objs[i].canonical, res.input_evaluation.R[i] * objs[i].s.asDiagonal(), res.input_evaluation.t[i]);
        ptrs[i] = &world[i];
      }
    try {
      res.before = headline_metrics(scene, ptrs, res.input_evaluation, cfg.metrics);
    } catch (const std::exception& e) {
      log::warn("headline metrics (before): {}", e.what());
    }
  }

  // 2. Sequential order over the simulated objects.
  std::vector<int> live;
  for (size_t i = 0; i < n; ++i)
    if (objs[i].simulate) live.push_back(static_cast<int>(i));
  res.order = sequential_order(c, live);

  // 3. Per object: penetration resolution, gravity diagnostics, decision.
  std::vector<int> placed;
  std::vector<int> needs_resample;
  std::vector<Diagnosis> diagnoses(n);
  int done = 0;
  for (int i : res.order) {
    Diagnostics& d = res.diagnostics[i];
    Obj& o = objs[i];
    const SceneObject& so = scene.objects[i];
    d.order = done;
    std::string why;
    try {
      World w = build_world(c, placed, {i}, false, nullptr, {}, 1, /*detect=*/true);
      bool ok = resolve_penetration(c, w, i, &d.dt_pen, &d.pen_iterations, &d.pen_max_depth, &why);
      if (ok && so.dof == PoseDof::Free) {
        ok = fall_until_contact(c, w, i, &d.dt_grv, &d.sim_time, &why);
        if (!ok && why.rfind("no contact", 0) == 0) add_flag(d, "no_support", "");
      } else if (ok) {
        // Pins at the current (post-penetration) pose, paired with the wall.
        place_pins(c, i, d);
        World wp = build_world(c, placed, {i}, true, nullptr, {}, 1, /*detect=*/true);
        ok = settle_on_pins(c, wp, i, &d.dt_grv, &d.dR_grv, &d.sim_time, &why);
      }
      if (!ok) {
        d.physics_disabled = true;
        d.branch = ProbeBranch::Disabled;
        add_flag(d, "physics_disabled", why);
        // Leave it out of the physics: back to its pre-simulation pose.
        o.t = d.t_pre, o.R = d.R_pre;
        o.simulate = false;
      }
    } catch (const std::exception& e) {
      d.physics_disabled = true;
      d.branch = ProbeBranch::Disabled;
      add_flag(d, "physics_disabled", e.what());
      o.t = d.t_pre, o.R = d.R_pre;
      o.simulate = false;
    }
    // Decision through the geometry half (geometry.h): OBB of the pre-simulation object,
    // gravity-most-aligned axis, rho, eta, branch, the stretch and the desired OBB B_str.
    if (o.simulate) {
      try {
        CorrectionConfig cc;
        cc.resample_threshold = cfg.rho_threshold;
        d.obb_pre = object_obb(o.canonical, d.s_pre, d.R_pre, d.t_pre, scene.gravity);
        const Diagnosis dg = diagnose(d.obb_pre, scene.gravity, d.dt_pen, d.dt_grv, cc);
        d.u_grv = dg.axis.u;
        d.ell = dg.axis.length;
        d.eta = dg.eta;
        d.rho = dg.rho;
        d.obb_target = stretched_obb(dg, cc);
        if (so.dof != PoseDof::Free) {
          d.branch = ProbeBranch::Anchored;  // wall-anchored objects keep their geometry and constrained pose
        } else if (dg.branch == Branch::Resample) {
          d.branch = ProbeBranch::Resample;
          needs_resample.push_back(i);
          diagnoses[i] = dg;
          // Until resampled: the object stays where the diagnostic left it.
        } else {
          // Gravity-axis stretch (supplementary equations; anti-gravity face fixed).
          d.branch = ProbeBranch::Stretch;
          const StretchResult st = gravity_axis_stretch(o.canonical.V, d.s_pre, d.R_pre, d.t_pre, d.dR_grv * d.R_pre, dg, cc);
          if (st.mesh_changed) {
            Mesh m = o.canonical;
            m.V = st.canonical;
            // The stretch is affine in the canonical frame: map the hulls instead of decomposing anew.
            auto mapped = map_shape(o.canonical, m, o.shape, cfg.collision);
            o.shape = mapped ? std::move(*mapped) : decompose(m, cfg.collision);
            o.canonical = m;
          }
          o.s = st.scale;
          o.R = st.R;
          o.t = st.t;
        }
      } catch (const std::exception& e) {
        // Degenerate OBB or non-finite numbers: keep the diagnostic pose, no correction.
        add_flag(d, "decision_failed", e.what());
      }
      placed.push_back(i);
    }
    ++done;
    if (progress) {
      std::string status = fmt::format("{} rho={:.3f}", to_string(d.branch), d.rho);
      if (!d.flags.empty()) status += " [" + fmt::format("{}", fmt::join(d.flags, ",")) + "]";
      progress(done, static_cast<int>(res.order.size()), so.id, status);
    }
  }
  const auto t1 = clock::now();
  res.seconds_probe = std::chrono::duration<double>(t1 - t0).count();

  // 4. Resample hand-off, one call for the whole scene.
  {
    CorrectionConfig cc;
    cc.resample_threshold = cfg.rho_threshold;
    for (int i : needs_resample) {
      try {
        res.resample_requests.push_back(make_request(scene, i, res.diagnostics[i], diagnoses[i], cc));
      } catch (const std::exception& e) {
        add_flag(res.diagnostics[i], "handoff_failed", e.what());
        ProbeResampleRequest r;
        r.object_index = i, r.object_id = scene.objects[i].id, r.target_obb = res.diagnostics[i].obb_target;
        res.resample_requests.push_back(r);
      }
    }
  }
  if (!needs_resample.empty()) {
    std::vector<ProbeResampleResult> results;
    if (resampler) {
      try {
        results = resampler(res.resample_requests);
      } catch (const std::exception& e) {
        log::warn("resampler failed: {}", e.what());
      }
    }
    for (size_t r = 0; r < needs_resample.size(); ++r) {
      const int i = needs_resample[r];
      Diagnostics& d = res.diagnostics[i];
      Obj& o = objs[i];
      if (!resampler) {
        add_flag(d, "needs_resample", "no resampler: hand-off written, object kept at its diagnostic pose");
        continue;
      }
      if (r >= results.size() || !results[r].ok) {
        add_flag(d, "resample_failed", r < results.size() ? results[r].message : "resampler returned too few results");
        continue;
      }
      const ProbeResampleResult& rr = results[r];
      d.resample_message = rr.message;
      d.crop_box = rr.crop_box;
      d.has_crop_box = rr.has_crop_box;
      try {
        ProbeShapeCandidate chosen{rr.message, rr.mesh, rr.R, rr.scale};
        CollisionShape chosen_shape;
        if (rr.candidates.size() >= 2) {
          // Best-of-N: settle every valid candidate with the objects before this one static; keep the
          // one that moves least.
          const auto at = std::find(placed.begin(), placed.end(), i);
          const std::vector<int> statics(placed.begin(), at);
          double best = std::numeric_limits<double>::infinity();
          std::vector<CollisionShape> shapes(rr.candidates.size());
          std::vector<bool> usable(rr.candidates.size(), false);
          for (size_t k = 0; k < rr.candidates.size(); ++k) {
            const auto& cand = rr.candidates[k];
            Diagnostics::Candidate rec;
            CollisionShape shape;
            const std::string p = mesh_problem(cand.mesh);
            if (!p.empty() || !cand.R.allFinite() || !cand.scale.allFinite() || cand.scale.minCoeff() <= 0) {
              rec.label = cand.label;
              rec.message = p.empty() ? "pose is not finite" : p;
            } else {
              shape = decompose(cand.mesh, cfg.collision);
              rec = settle_candidate(c, statics, i, cand, shape, d.obb_target.center);
              rec.world = transform_mesh(cand.mesh, cand.R * cand.scale.asDiagonal(), d.obb_target.center);
              shapes[k] = shape;
              usable[k] = true;
            }
            if (rec.ok && rec.displacement < best) {
              best = rec.displacement;
              d.chosen_candidate = static_cast<int>(k);
              chosen = cand;
              chosen_shape = shape;
            }
            d.candidates.push_back(rec);
          }
          // None passed its checks: nothing is a replacement. The object keeps its input shape where the
          // diagnostic left it; every candidate's figures stay in the report.
          if (d.chosen_candidate < 0) {
            double least = std::numeric_limits<double>::infinity();
            int shallowest = -1;
            for (size_t k = 0; k < rr.candidates.size(); ++k)
              if (usable[k] && d.candidates[k].penetration < least) least = d.candidates[k].penetration, shallowest = int(k);
            add_flag(d, "no_stable_candidate",
                     shallowest >= 0 ? fmt::format("none of the {} candidates passed (shallowest #{} penetrates {:.3f} m); "
                                                   "the input shape is kept", rr.candidates.size(), shallowest, least)
                                     : fmt::format("none of the {} candidates has a usable mesh", rr.candidates.size()));
            add_flag(d, "resample_failed", "");
            continue;
          }
        } else {
          if (rr.candidates.size() == 1) chosen = rr.candidates[0];
          const std::string p = mesh_problem(chosen.mesh);
          SIMU_CHECK(p.empty(), "resampled mesh: {}", p);
          SIMU_CHECK(chosen.R.allFinite() && chosen.scale.allFinite() && chosen.scale.minCoeff() > 0,
                     "resampled pose is not finite");
          chosen_shape = decompose(chosen.mesh, cfg.collision);
        }
        o.shape = chosen_shape;
        o.canonical = chosen.mesh;
        o.visual_ok = chosen.mesh.V.rows() >= 4 && std::abs(signed_volume(chosen.mesh)) * chosen.scale.prod() > 1e-9;
        o.R = chosen.R;
        o.s = chosen.scale;
        o.t = d.obb_target.center;  // paper: translation := centre of the stretched OBB
        d.resampled = true;
        d.t_resampled = o.t, d.R_resampled = o.R, d.s_resampled = o.s;
      } catch (const std::exception& e) {
        add_flag(d, "resample_failed", e.what());
      }
    }
  }
  const auto t2 = clock::now();
  res.seconds_resample = std::chrono::duration<double>(t2 - t1).count();

  // 5. Final composition: sequential penetration resolution, then one joint settle.
  std::vector<int> final_live;
  for (size_t i = 0; i < n; ++i)
    if (objs[i].simulate) final_live.push_back(static_cast<int>(i));
  const std::vector<int> final_order = sequential_order(c, final_live);
  std::vector<int> placed2;
  for (int i : final_order) {
    Diagnostics& d = res.diagnostics[i];
    try {
      World w = build_world(c, placed2, {i}, false);
      int iters = 0;
      double depth = 0;
      std::string why;
      const Vec3 before = objs[i].t;
      if (!resolve_penetration(c, w, i, &d.dt_final_pen, &iters, &depth, &why)) {
        objs[i].t = before;
        add_flag(d, "final_penetration", why);
      }
    } catch (const std::exception& e) {
      add_flag(d, "final_penetration", e.what());
    }
    placed2.push_back(i);
  }
  std::vector<int> visual;
  for (size_t i = 0; i < n; ++i)
    if (objs[i].usable && !objs[i].simulate) visual.push_back(static_cast<int>(i));
  const auto t_pen_done = clock::now();
  log::debug("final penetration pass: {:.3f} s", std::chrono::duration<double>(t_pen_done - t2).count());
  int buffer_factor = 1;
  if (!final_order.empty()) {
    try {
      // Joint settle for T_settle (stops early once every body is at rest), recorded per object.
      const SettleRun run = joint_settle(c, final_order, cfg.final_settle_time, cfg.settle_rest_distance);
      buffer_factor = run.buffer_factor;
      if (run.full) log::warn("final settle: contact buffers still full at {}x", buffer_factor);
      log::debug("final settle: {:.3f} s ({:.2f} s simulated)", std::chrono::duration<double>(clock::now() - t_pen_done).count(),
                 run.simulated);
      for (size_t k = 0; k < final_order.size(); ++k) {
        const int i = final_order[k];
        Diagnostics& d = res.diagnostics[i];
        d.final_settle = run.rec[k];
        if (run.reset) {
          add_flag(d, "solver_reset", "MuJoCo reset the data during the final settle; pre-settle poses kept");
          d.reverted = true;
          continue;
        }
        d.settle_displacement = run.rec[k].displacement;
        if (!run.t[k].allFinite() || !(d.settle_displacement <= cfg.divergence_bound)) {
          d.reverted = true;
          add_flag(d, "reverted", fmt::format("moved {:.3f} m in the final settle (> {:.2f} m): pre-settle pose kept",
                                              d.settle_displacement, cfg.divergence_bound));
          continue;
        }
        objs[i].t = run.t[k];
        objs[i].R = run.R[k];
      }
    } catch (const std::exception& e) {
      log::warn("final settle failed: {}", e.what());
      for (int i : final_order) add_flag(res.diagnostics[i], "settle_failed", e.what());
    }
  }
  for (size_t i = 0; i < n; ++i)
    if (!objs[i].simulate) {
      res.diagnostics[i].final_settle.category = metric_category(scene.objects[i].dof);
      res.diagnostics[i].final_settle.physics_disabled = true;
    }
  // The final MJCF: free objects dynamic, anchored ones on their pins, disabled ones visual only.
  try {
    build_world(c, {}, final_order, true, &res.mjcf, visual, std::max(1, buffer_factor), false, /*visuals=*/true);
  } catch (const std::exception& e) {
    log::warn("final MJCF does not compile: {}", e.what());
  }
  res.seconds_final = std::chrono::duration<double>(clock::now() - t2).count();

  // Evaluation settle of the final scene (supplementary "Metrics": 5 s under gravity).
  if (cfg.metrics_settle_time > 0) {
    res.evaluation = evaluate_settle(c, final_order, cfg.metrics_settle_time);
  } else {
    // No separate settle: the metrics of the final settle.
    res.evaluation.objects.clear();
    for (size_t i = 0; i < n; ++i) res.evaluation.objects.push_back(res.diagnostics[i].final_settle);
    res.evaluation.metrics = physics_metrics(res.evaluation.objects, cfg.metrics);
  }
  for (size_t i = 0; i < n && i < res.evaluation.objects.size(); ++i) {
    res.diagnostics[i].evaluation = res.evaluation.objects[i];
    res.diagnostics[i].evaluation.physics_disabled = res.diagnostics[i].evaluation.physics_disabled || res.diagnostics[i].physics_disabled;
  }
  res.evaluation.metrics = physics_metrics([&] {
    std::vector<SettleRecord> v;
    for (const auto& d : res.diagnostics) v.push_back(d.evaluation);
    return v;
  }(), cfg.metrics, res.evaluation.ran ? res.evaluation.scene_peak_energy : -1);
  res.seconds_metrics = res.evaluation.seconds;

  // "After" column: the final scene after the evaluation settle.
  {
    std::vector<Mesh> world(n);
    std::vector<const Mesh*> ptrs(n, nullptr);
    for (size_t i = 0; i < n; ++i)
      if (objs[i].usable) {
        const bool settled = i < res.evaluation.t.size();  // else no evaluation settle: the final poses
        world[i] = transform_mesh(objs[i].canonical, (settled ? res.evaluation.R[i] : objs[i].R) * objs[i].s.asDiagonal(),
                                  settled ? res.evaluation.t[i] : objs[i].t);
        ptrs[i] = &world[i];
      }
    PhysicsEvaluation ev = res.evaluation;
    ev.objects.clear();
    for (const auto& d : res.diagnostics) ev.objects.push_back(d.evaluation);
    try {
      res.after = headline_metrics(scene, ptrs, ev, cfg.metrics);
    } catch (const std::exception& e) {
      log::warn("headline metrics (after): {}", e.what());
    }
  }

  // Corrected scene: final poses, scales and meshes (and each object's final OBB for the report).
  res.meshes.assign(n, Mesh{});
  for (size_t i = 0; i < n; ++i) {
    if (!objs[i].usable) continue;
    res.meshes[i] = objs[i].canonical;
    try {
      res.diagnostics[i].obb_final = object_obb(objs[i].canonical, objs[i].s, objs[i].R, objs[i].t, scene.gravity);
    } catch (const std::exception&) {
    }
    scene.objects[i].t = objs[i].t;
    scene.objects[i].R = objs[i].R;
    scene.objects[i].scale = objs[i].s;
  }

  // 6. Outputs, written into a staging folder beside out_dir and moved into place at the end: a
  // failed run leaves the previous output as it was.
  if (!out_dir.empty() && cfg.write_outputs) write_outputs(res, objs, out_dir, cfg);
  return res;
}

}  // namespace simu::physics
