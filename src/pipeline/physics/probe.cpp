// The physics probe's algorithm (paper Sec. 3.3-3.5; supplementary "Gravity-Based Diagnostics",
// "Sequential Composition", "Metrics"): run_probe strings together the named phases below --
//   diagnose  sequential penetration resolution, gravity diagnostics and the Diagnosis (rho, eta);
//   correct   the gravity-axis stretch (applied at once, later objects rest on it), or the resample
//             hand-off, one resampler call and the choice among its candidates;
//   compose   the final sequential penetration pass, the joint settle, the final MJCF;
//   evaluate  the evaluation settles of the input and of the final scene and their headline metrics.
// The MuJoCo world is probe_world.cpp / probe_settle.cpp (probe_world.h), reporting
// probe_report.cpp and pictures.cpp (see probe.h).
#include "pipeline/physics/probe.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#endif

#include <fmt/ranges.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <limits>

#include "common/error.h"
#include "common/log.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/probe_world.h"
#include "pipeline/physics/raster.h"

namespace simu::physics {

namespace stdfs = std::filesystem;
using namespace probe_detail;

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

namespace {

using Clock = std::chrono::steady_clock;

// The decision parameters of the geometry half (geometry.h) from the probe's config.
CorrectionConfig correction_config(const ProbeConfig& cfg) {
  CorrectionConfig cc;
  cc.resample_threshold = cfg.rho_threshold;
  return cc;
}

// World meshes of the usable objects for scoring: at the poses of `ev` where it has them, else at
// the objects' working poses; nullptr for objects without geometry.
struct PosedMeshes {
  std::vector<Mesh> world;
  std::vector<const Mesh*> ptrs;
};
void pose_meshes(const std::vector<Obj>& objs, const PhysicsEvaluation& ev, PosedMeshes* out) {
  const size_t n = objs.size();
  out->world.assign(n, Mesh{});
  out->ptrs.assign(n, nullptr);
  for (size_t i = 0; i < n; ++i)
    if (objs[i].usable) {
      const bool settled = i < ev.t.size();  // else no evaluation settle: the working poses
      out->world[i] = transform_mesh(objs[i].canonical, (settled ? ev.R[i] : objs[i].R) * objs[i].s.asDiagonal(),
                                     settled ? ev.t[i] : objs[i].t);
      out->ptrs[i] = &out->world[i];
    }
}

// ---------------------------------------------------------------------------------------------
// Evaluate (before): the input scene settled exactly like the final one will be (anchored objects
// pinned at their input pose), scored for the "before" column of the headline metrics.
void evaluate_input_scene(Ctx& c, ProbeResult& res) {
  const size_t n = c.objs.size();
  std::vector<int> live_in;
  for (size_t i = 0; i < n; ++i) {
    if (!c.objs[i].simulate) continue;
    if (c.scene.objects[i].dof != PoseDof::Free) {
      Diagnostics scratch;
      place_pins(c, static_cast<int>(i), scratch);
    }
    live_in.push_back(static_cast<int>(i));
  }
  res.input_evaluation = evaluate_settle(c, live_in, c.cfg.metrics_settle_time);
  PosedMeshes posed;
  pose_meshes(c.objs, res.input_evaluation, &posed);
  try {
    res.before = headline_metrics(c.scene, posed.ptrs, res.input_evaluation, c.cfg.metrics);
  } catch (const std::exception& e) {
    log::warn("headline metrics (before): {}", e.what());
  }
}

// ---------------------------------------------------------------------------------------------
// Diagnose.

// Takes an object out of the physics at its pre-simulation pose, flagged with why.
void take_out_of_physics(Obj& o, Diagnostics& d, const std::string& why) {
  d.physics_disabled = true;
  d.branch = ProbeBranch::Disabled;
  add_flag(d, "physics_disabled", why);
  o.t = d.t_pre, o.R = d.R_pre;
  o.simulate = false;
}

// The simulated part of the diagnosis of object i, with the objects placed before it static:
// penetration resolution, then the gravity diagnostic (free: fall until the first contact;
// anchored: pins at the pose after the push, settled on them). A failure takes it out of the physics.
void simulate_diagnostics(Ctx& c, const std::vector<int>& placed, int i, Diagnostics& d) {
  Obj& o = c.objs[i];
  const SceneObject& so = c.scene.objects[i];
  std::string why;
  try {
    World w = build_world(c, placed, {i}, false, nullptr, {}, 1, /*detect=*/true);
    bool ok = resolve_penetration(c, w, i, &d.dt_pen, &d.pen_iterations, &d.pen_max_depth, &why);
    if (ok && !c.cfg.gravity_diagnostics) {
      // Penetration resolution only: no drop, no pins; the object stays where the push left it.
    } else if (ok && so.dof == PoseDof::Free) {
      ok = fall_until_contact(c, w, i, &d.dt_grv, &d.sim_time, &why);
      if (!ok && why.rfind("no contact", 0) == 0) add_flag(d, "no_support", "");
    } else if (ok) {
      // Pins at the current (post-penetration) pose, paired with the wall.
      place_pins(c, i, d);
      World wp = build_world(c, placed, {i}, true, nullptr, {}, 1, /*detect=*/true);
      ok = settle_on_pins(c, wp, i, &d.dt_grv, &d.dR_grv, &d.sim_time, &why);
    }
    if (!ok) take_out_of_physics(o, d, why);
  } catch (const std::exception& e) {
    take_out_of_physics(o, d, e.what());
  }
}

// ---------------------------------------------------------------------------------------------
// Correct by stretch (supplementary equations; anti-gravity face fixed): the canonical mesh, scale
// and pose of object i become the stretched ones. The stretch is affine in the canonical frame, so
// the collision hulls are mapped instead of decomposed anew where that works.
void stretch_object(Ctx& c, int i, const Diagnostics& d, const CorrectionConfig& cc) {
  Obj& o = c.objs[i];
  const StretchResult st =
      gravity_axis_stretch(o.canonical.V, d.s_pre, d.R_pre, d.t_pre, d.dR_grv * d.R_pre, d.diagnosis, cc);
  if (st.mesh_changed) {
    Mesh m = o.canonical;
    m.V = st.canonical;
    auto mapped = map_shape(o.canonical, m, o.shape, c.cfg.collision);
    o.shape = mapped ? std::move(*mapped) : decompose(m, c.cfg.collision);
    o.canonical = m;
  }
  o.s = st.scale;
  o.R = st.R;
  o.t = st.t;
}

// The decision for a simulated object i through the geometry half (geometry.h): the Diagnosis from
// its pre-simulation OBB and the diagnostic displacements (gravity-most-aligned axis, rho, eta), the
// desired OBB B_str and the branch: wall-anchored objects keep their geometry and constrained pose,
// rho >= threshold asks for a resample (the object stays where the diagnostic left it until then),
// as does an id of ProbeConfig::force_resample (flagged "forced_resample"; diagnosis.branch keeps what
// the rule said), else the stretch is applied now. Returns whether the object needs resampling. A
// degenerate OBB or non-finite numbers keep the diagnostic pose, flagged, without a correction.
bool decide_and_stretch(Ctx& c, int i, Diagnostics& d) {
  try {
    const CorrectionConfig cc = correction_config(c.cfg);
    const Obb obb_pre = object_obb(c.objs[i].canonical, d.s_pre, d.R_pre, d.t_pre, c.scene.gravity);
    d.diagnosis.obb_pre = obb_pre;  // kept when diagnose() throws
    d.diagnosis = diagnose(obb_pre, c.scene.gravity, d.dt_pen, d.dt_grv, cc);
    d.obb_target = stretched_obb(d.diagnosis, cc);
    const auto& forced = c.cfg.force_resample;
    const bool force = std::find(forced.begin(), forced.end(), c.scene.objects[i].id) != forced.end();
    if (c.scene.objects[i].dof != PoseDof::Free) {
      d.branch = ProbeBranch::Anchored;
      if (force) add_flag(d, "forced_resample_ignored", "decision.force_resample: anchored objects keep their geometry");
    } else if (d.diagnosis.branch == Branch::Resample || force) {
      d.branch = ProbeBranch::Resample;
      if (d.diagnosis.branch != Branch::Resample)
        add_flag(d, "forced_resample", fmt::format("decision.force_resample: resampled although rho {:.3f} < {}",
                                                   d.diagnosis.rho, c.cfg.rho_threshold));
      return true;
    } else {
      d.branch = ProbeBranch::Stretch;
      stretch_object(c, i, d, cc);
    }
  } catch (const std::exception& e) {
    add_flag(d, "decision_failed", e.what());
  }
  return false;
}

// Diagnose (and correct by stretch) every simulated object in the sequential order, each against the
// objects placed before it. Fills res.order; returns the objects placed (in order) and, in
// *needs_resample, those that asked for a new shape.
std::vector<int> diagnose_in_order(Ctx& c, ProbeResult& res, std::vector<int>* needs_resample,
                                   const ProbeProgress& progress) {
  std::vector<int> live;
  for (size_t i = 0; i < c.objs.size(); ++i)
    if (c.objs[i].simulate) live.push_back(static_cast<int>(i));
  res.order = sequential_order(c, live);
  std::vector<int> placed;
  int done = 0;
  for (int i : res.order) {
    Diagnostics& d = res.diagnostics[i];
    d.order = done;
    simulate_diagnostics(c, placed, i, d);
    if (c.objs[i].simulate) {
      if (c.cfg.gravity_diagnostics && decide_and_stretch(c, i, d)) needs_resample->push_back(i);
      placed.push_back(i);
    }
    ++done;
    if (progress) {
      std::string status = fmt::format("{} rho={:.3f}", to_string(d.branch), d.diagnosis.rho);
      if (!d.flags.empty()) status += " [" + fmt::format("{}", fmt::join(d.flags, ",")) + "]";
      progress(done, static_cast<int>(res.order.size()), c.scene.objects[i].id, status);
    }
  }
  return placed;
}

// ---------------------------------------------------------------------------------------------
// Correct by resampling.

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

// The hand-off of every object that needs resampling (one that cannot be built is flagged and
// handed over with its id and target OBB only).
void build_requests(const Ctx& c, ProbeResult& res, const std::vector<int>& needs_resample) {
  const CorrectionConfig cc = correction_config(c.cfg);
  for (int i : needs_resample) {
    try {
      res.resample_requests.push_back(make_request(c.scene, i, res.diagnostics[i], res.diagnostics[i].diagnosis, cc));
    } catch (const std::exception& e) {
      add_flag(res.diagnostics[i], "handoff_failed", e.what());
      ProbeResampleRequest r;
      r.object_index = i, r.object_id = c.scene.objects[i].id, r.target_obb = res.diagnostics[i].obb_target;
      res.resample_requests.push_back(r);
    }
  }
}

// Best-of-N: settles every usable candidate at the target OBB's centre with the objects placed
// before object i static and picks the one that moved least among those that passed (every
// candidate's figures go to d.candidates). Returns false when none passed: the object keeps its
// input shape where the diagnostic left it, flagged.
bool choose_candidate(const Ctx& c, const std::vector<int>& placed, int i, Diagnostics& d, const ProbeResampleResult& rr,
                      ProbeShapeCandidate* chosen, CollisionShape* chosen_shape) {
  const auto at = std::find(placed.begin(), placed.end(), i);
  const std::vector<int> statics(placed.begin(), at);
  double best = std::numeric_limits<double>::infinity();
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
      shape = decompose(cand.mesh, c.cfg.collision);
      rec = settle_candidate(c, statics, i, cand, shape, d.obb_target.center);
      rec.world = transform_mesh(cand.mesh, cand.R * cand.scale.asDiagonal(), d.obb_target.center);
      usable[k] = true;
    }
    if (rec.ok && rec.displacement < best) {
      best = rec.displacement;
      d.chosen_candidate = static_cast<int>(k);
      *chosen = cand;
      *chosen_shape = shape;
    }
    d.candidates.push_back(rec);
  }
  if (d.chosen_candidate >= 0) return true;
  // None passed its checks: nothing is a replacement; every candidate's figures stay in the report.
  double least = std::numeric_limits<double>::infinity();
  int shallowest = -1;
  for (size_t k = 0; k < rr.candidates.size(); ++k)
    if (usable[k] && d.candidates[k].penetration < least) least = d.candidates[k].penetration, shallowest = int(k);
  add_flag(d, "no_stable_candidate",
           shallowest >= 0 ? fmt::format("none of the {} candidates passed (shallowest #{} penetrates {:.3f} m); "
                                         "the input shape is kept", rr.candidates.size(), shallowest, least)
                           : fmt::format("none of the {} candidates has a usable mesh", rr.candidates.size()));
  add_flag(d, "resample_failed", "");
  return false;
}

// Replaces object i's shape by what the resampler returned (the best of its candidates when there
// are two or more), placed at the centre of the stretched OBB (paper: translation := that centre).
void apply_resample_result(Ctx& c, const std::vector<int>& placed, int i, Diagnostics& d, const ProbeResampleResult& rr) {
  Obj& o = c.objs[i];
  d.resample_message = rr.message;
  d.crop_box = rr.crop_box;
  d.has_crop_box = rr.has_crop_box;
  try {
    ProbeShapeCandidate chosen{rr.message, rr.mesh, rr.R, rr.scale};
    CollisionShape chosen_shape;
    if (rr.candidates.size() >= 2) {
      if (!choose_candidate(c, placed, i, d, rr, &chosen, &chosen_shape)) return;
    } else {
      if (rr.candidates.size() == 1) chosen = rr.candidates[0];
      const std::string p = mesh_problem(chosen.mesh);
      SIMU_CHECK(p.empty(), "resampled mesh: {}", p);
      SIMU_CHECK(chosen.R.allFinite() && chosen.scale.allFinite() && chosen.scale.minCoeff() > 0,
                 "resampled pose is not finite");
      chosen_shape = decompose(chosen.mesh, c.cfg.collision);
    }
    o.shape = chosen_shape;
    o.canonical = chosen.mesh;
    o.visual_ok = chosen.mesh.V.rows() >= 4 && std::abs(signed_volume(chosen.mesh)) * chosen.scale.prod() > 1e-9;
    o.R = chosen.R;
    o.s = chosen.scale;
    o.t = d.obb_target.center;
    d.resampled = true;
    d.t_resampled = o.t, d.R_resampled = o.R, d.s_resampled = o.s;
  } catch (const std::exception& e) {
    add_flag(d, "resample_failed", e.what());
  }
}

// The hand-off for the whole scene, ONE resampler call for every object that needs a new shape, and
// each returned shape applied (without a resampler only the hand-off is made, flagged).
void correct_by_resampling(Ctx& c, ProbeResult& res, const std::vector<int>& placed,
                           const std::vector<int>& needs_resample, const ResampleFn& resampler) {
  build_requests(c, res, needs_resample);
  if (needs_resample.empty()) return;
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
    if (!resampler) {
      add_flag(d, "needs_resample", "no resampler: hand-off written, object kept at its diagnostic pose");
      continue;
    }
    if (r >= results.size() || !results[r].ok) {
      add_flag(d, "resample_failed", r < results.size() ? results[r].message : "resampler returned too few results");
      continue;
    }
    apply_resample_result(c, placed, i, d, results[r]);
  }
}

// ---------------------------------------------------------------------------------------------
// Compose.

// Sequential penetration resolution of the corrected objects, each with the ones before it static;
// a failed push keeps the object's pose, flagged.
void final_penetration_pass(Ctx& c, ProbeResult& res, const std::vector<int>& final_order) {
  std::vector<int> placed;
  for (int i : final_order) {
    Diagnostics& d = res.diagnostics[i];
    try {
      World w = build_world(c, placed, {i}, false);
      int iters = 0;
      double depth = 0;
      std::string why;
      const Vec3 before = c.objs[i].t;
      if (!resolve_penetration(c, w, i, &d.dt_final_pen, &iters, &depth, &why)) {
        c.objs[i].t = before;
        add_flag(d, "final_penetration", why);
      }
    } catch (const std::exception& e) {
      add_flag(d, "final_penetration", e.what());
    }
    placed.push_back(i);
  }
}

// The joint settle for T_settle (stops early once every body is at rest), recorded per object; an
// object moving more than the divergence bound (or a solver reset) keeps its pre-settle pose.
// Returns the contact-buffer multiplier that sufficed.
int final_settle(Ctx& c, ProbeResult& res, const std::vector<int>& final_order, Clock::time_point since) {
  int buffer_factor = 1;
  if (final_order.empty()) return buffer_factor;
  const ProbeConfig& cfg = c.cfg;
  try {
    const SettleRun run = joint_settle(c, final_order, cfg.final_settle_time, cfg.settle_rest_distance);
    buffer_factor = run.buffer_factor;
    if (run.full) log::warn("final settle: contact buffers still full at {}x", buffer_factor);
    log::debug("final settle: {:.3f} s ({:.2f} s simulated)", std::chrono::duration<double>(Clock::now() - since).count(),
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
      c.objs[i].t = run.t[k];
      c.objs[i].R = run.R[k];
    }
  } catch (const std::exception& e) {
    log::warn("final settle failed: {}", e.what());
    for (int i : final_order) add_flag(res.diagnostics[i], "settle_failed", e.what());
  }
  return buffer_factor;
}

// Final composition: the sequential penetration pass and the joint settle over the simulated
// objects, then the final MJCF (free objects dynamic, anchored ones on their pins, disabled ones
// visual only). Returns the objects in their final sequential order.
std::vector<int> compose(Ctx& c, ProbeResult& res, Clock::time_point t2) {
  const size_t n = c.objs.size();
  std::vector<int> final_live;
  for (size_t i = 0; i < n; ++i)
    if (c.objs[i].simulate) final_live.push_back(static_cast<int>(i));
  const std::vector<int> final_order = sequential_order(c, final_live);
  final_penetration_pass(c, res, final_order);
  std::vector<int> visual;
  for (size_t i = 0; i < n; ++i)
    if (c.objs[i].usable && !c.objs[i].simulate) visual.push_back(static_cast<int>(i));
  const auto t_pen_done = Clock::now();
  log::debug("final penetration pass: {:.3f} s", std::chrono::duration<double>(t_pen_done - t2).count());
  const int buffer_factor = final_settle(c, res, final_order, t_pen_done);
  for (size_t i = 0; i < n; ++i)
    if (!c.objs[i].simulate) {
      res.diagnostics[i].final_settle.category = metric_category(c.scene.objects[i].dof);
      res.diagnostics[i].final_settle.physics_disabled = true;
    }
  try {
    build_world(c, {}, final_order, true, &res.mjcf, visual, std::max(1, buffer_factor), false, /*visuals=*/true);
  } catch (const std::exception& e) {
    log::warn("final MJCF does not compile: {}", e.what());
  }
  return final_order;
}

// ---------------------------------------------------------------------------------------------
// Evaluate (after): the evaluation settle of the final scene (supplementary "Metrics": 5 s under
// gravity; without it the final settle's records), per-object records (physics-disabled objects
// count as such), the physics metrics over them and the headline metrics of the settled scene.
void evaluate_final_scene(Ctx& c, ProbeResult& res, const std::vector<int>& final_order) {
  const ProbeConfig& cfg = c.cfg;
  const size_t n = c.objs.size();
  if (cfg.metrics_settle_time > 0) {
    res.evaluation = evaluate_settle(c, final_order, cfg.metrics_settle_time);
  } else {
    res.evaluation.objects.clear();
    for (size_t i = 0; i < n; ++i) res.evaluation.objects.push_back(res.diagnostics[i].final_settle);
    res.evaluation.metrics = physics_metrics(res.evaluation.objects, cfg.metrics);
  }
  for (size_t i = 0; i < n && i < res.evaluation.objects.size(); ++i) {
    res.diagnostics[i].evaluation = res.evaluation.objects[i];
    res.diagnostics[i].evaluation.physics_disabled = res.diagnostics[i].evaluation.physics_disabled || res.diagnostics[i].physics_disabled;
  }
  std::vector<SettleRecord> records;
  for (const auto& d : res.diagnostics) records.push_back(d.evaluation);
  res.evaluation.metrics = physics_metrics(records, cfg.metrics, res.evaluation.ran ? res.evaluation.scene_peak_energy : -1);
  res.seconds_metrics = res.evaluation.seconds;
  PosedMeshes posed;
  pose_meshes(c.objs, res.evaluation, &posed);
  PhysicsEvaluation ev = res.evaluation;
  ev.objects = records;
  try {
    res.after = headline_metrics(c.scene, posed.ptrs, ev, cfg.metrics);
  } catch (const std::exception& e) {
    log::warn("headline metrics (after): {}", e.what());
  }
}

// The corrected scene: final poses, scales and meshes (and each object's final OBB for the report).
void store_corrected_scene(const Ctx& c, ProbeResult& res) {
  const size_t n = c.objs.size();
  res.meshes.assign(n, Mesh{});
  for (size_t i = 0; i < n; ++i) {
    const Obj& o = c.objs[i];
    if (!o.usable) continue;
    res.meshes[i] = o.canonical;
    try {
      res.diagnostics[i].obb_final = object_obb(o.canonical, o.s, o.R, o.t, c.scene.gravity);
    } catch (const std::exception&) {
    }
    res.scene.objects[i].t = o.t;
    res.scene.objects[i].R = o.R;
    res.scene.objects[i].scale = o.s;
  }
}

}  // namespace

ProbeResult run_probe(const Scene& scene_in, const ProbeConfig& cfg, const std::string& out_dir,
                      const ResampleFn& resampler, const ProbeProgress& progress) {
  cfg.validate();  // a config built in code is checked as a loaded one is
  const auto t0 = Clock::now();
  ProbeResult res;
  res.scene = scene_in;
  const size_t n = res.scene.objects.size();
  res.diagnostics.resize(n);
  std::vector<Obj> objs(n);
  Ctx c{res.scene, cfg, objs, {}, {}};
  if (!out_dir.empty() && cfg.write_outputs && !cfg.overwrite && stdfs::exists(out_dir))
    fail_hint("pass --overwrite (probe) or choose another --out", "output folder {} already exists; not overwritten", out_dir);
  for (const auto& id : cfg.force_resample) {
    const bool known = std::any_of(res.scene.objects.begin(), res.scene.objects.end(),
                                   [&](const SceneObject& o) { return o.id == id; });
    if (!known) {
      std::vector<std::string> ids;
      for (const auto& o : res.scene.objects) ids.push_back(o.id);
      fail("key 'decision.force_resample': no object '{}' in the scene (objects: {})", id, fmt::join(ids, ", "));
    }
  }

  load_inputs(c, res.diagnostics);
  if (cfg.evaluate_input && cfg.metrics_settle_time > 0) evaluate_input_scene(c, res);
  // Diagnose (and stretch) object by object, then resample what needs it: one call for the scene.
  std::vector<int> needs_resample;
  const std::vector<int> placed = diagnose_in_order(c, res, &needs_resample, progress);
  const auto t1 = Clock::now();
  res.seconds_probe = std::chrono::duration<double>(t1 - t0).count();
  correct_by_resampling(c, res, placed, needs_resample, resampler);
  const auto t2 = Clock::now();
  res.seconds_resample = std::chrono::duration<double>(t2 - t1).count();
  const std::vector<int> final_order = compose(c, res, t2);
  res.seconds_final = std::chrono::duration<double>(Clock::now() - t2).count();
  evaluate_final_scene(c, res, final_order);
  store_corrected_scene(c, res);

  // Outputs, written into a staging folder beside out_dir and moved into place at the end: a
  // failed run leaves the previous output as it was.
  if (!out_dir.empty() && cfg.write_outputs) write_outputs(res, objs, out_dir, cfg);
  return res;
}

}  // namespace simu::physics
