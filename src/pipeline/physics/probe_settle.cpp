// What the probe simulates in a world: contacts, penetration resolution, the gravity diagnostics,
// the joint and evaluation settles, one best-of-N candidate's settle (probe_world.h).
#include "pipeline/physics/probe_world.h"

#include <mujoco/mujoco.h>

#include <algorithm>
#include <chrono>
#include <cmath>

#include "common/log.h"
#include "pipeline/physics/mesh.h"

namespace simu::physics {
namespace probe_detail {

namespace {

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

// The start of a joint settle (build_world ran mj_forward): per object its record's category and
// deepest contact, its pose (t0, run->R) and its body position (last, for the rest test).
void start_records(const Ctx& c, const World& w, const std::vector<int>& objects, SettleRun* run, std::vector<Vec3>* t0,
                   std::vector<Vec3>* last) {
  const size_t n = objects.size();
  const std::vector<double> depth0 = deepest_contacts(w, c.objs.size());
  run->rec.assign(n, SettleRecord{});
  run->t.assign(n, Vec3::Zero());
  run->R.assign(n, Mat3::Identity());
  for (size_t k = 0; k < n; ++k) {
    const int i = objects[k];
    SettleRecord& r = run->rec[k];
    r.category = metric_category(c.scene.objects[i].dof);
    r.initial_penetration = depth0[i];
    r.initially_penetrating = depth0[i] > c.cfg.metrics.penetration_depth;
    get_pose(w, w.obj_body[i], &(*t0)[k], &run->R[k]);
    (*last)[k] = Eigen::Map<const Vec3>(w.data->xpos + 3 * w.obj_body[i]);
  }
}

// Kinetic energy of each object and of the scene at one step (velocities of the state the step
// started from): the per-object and the scene peaks.
void record_kinetic_energy(const World& w, const std::vector<int>& objects, SettleRun* run) {
  double total = 0;
  for (size_t k = 0; k < objects.size(); ++k) {
    const double e = body_kinetic_energy(w.model.get(), w.data.get(), w.obj_body[objects[k]]);
    run->rec[k].peak_kinetic_energy = std::max(run->rec[k].peak_kinetic_energy, e);
    total += e;
  }
  run->scene_peak = std::max(run->scene_peak, total);
}

}  // namespace

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

bool fall_until_contact(const Ctx& c, World& w, int i, Vec3* dt, double* time, std::string* why) {
  Obj& o = c.objs[i];
  const int body = w.obj_body[i];
  const mjModel* m = w.model.get();
  mjData* d = w.data.get();
  start_at_pose(c, w, i);
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

bool settle_on_pins(const Ctx& c, World& w, int i, Vec3* dt, Mat3* dR, double* time, std::string* why) {
  Obj& o = c.objs[i];
  const int body = w.obj_body[i];
  const mjModel* m = w.model.get();
  mjData* d = w.data.get();
  start_at_pose(c, w, i);
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

SettleRun joint_settle(const Ctx& c, const std::vector<int>& objects, double duration, double rest_distance) {
  SettleRun run;
  const size_t n = objects.size();
  bool full = true;
  World w;
  for (run.buffer_factor = 1; full; run.buffer_factor *= 2) {
    w = build_world(c, {}, objects, true, nullptr, {}, run.buffer_factor);
    const mjModel* m = w.model.get();
    mjData* d = w.data.get();
    std::vector<Vec3> t0(n), last(n);
    start_records(c, w, objects, &run, &t0, &last);
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
      record_kinetic_energy(w, objects, &run);
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
      start_at_pose(c, w, i);
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

}  // namespace probe_detail

PhysicsEvaluation evaluate_physics(const Scene& scene_in, const ProbeConfig& cfg, double settle_time) {
  using namespace probe_detail;
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

}  // namespace simu::physics
