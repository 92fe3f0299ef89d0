// The reconstruct front end's steps (run.h): per-object preparation (masks, roles, brought meshes),
// the batched lift, refined poses, alignment, the first plane pass, the tabletop refinement, the
// re-extraction with the fitted meshes and the floor snap, walls for hanging objects, the composed
// scene and the probe. Inputs and the report are in run_io.cpp, the masks and point maps in run_masks.cpp.
#include "pipeline/reconstruct/run.h"

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "data/depth_io.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/reconstruct/icp_refine.h"
#include "pipeline/reconstruct/run_detail.h"
#include "pipeline/reconstruct/synthetic_camera.h"
#include "pipeline/resample/probe_resampler.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <ATen/Parallel.h>

#include <chrono>
#include <unistd.h>
#include <filesystem>
#include <limits>
#include <map>

namespace simu::reconstruct {

namespace sfs = std::filesystem;
using nlohmann::json;
using detail::dilate;
using detail::read_json_file;
using detail::sample_points;
using detail::to_mask;
using detail::to_point_map;
using detail::vec3_of;
using detail::vj;
using detail::write_mask;

namespace {
using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

// One object through the steps.
struct Work {
  ObjectSpec spec;
  ObjectReport rep;
  Mask mask;
  Points observed;
  physics::Mesh mesh;  // canonical
  Vec3 scale = Vec3::Ones();
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
  Vec3 up_axis = Vec3::Zero();  // canonical up axis (zero: unknown)
  // A lifted object's usable samples (mesh and pose each; step 2 keeps one): more than one with
  // several samples per object.
  struct Sample {
    physics::Mesh mesh;
    Vec3 scale;
    Mat3 R;
    Vec3 t;
    size_t index;  // in the lift's samples
  };
  std::vector<Sample> samples;
  bool ok = false;
  bool hanging() const { return spec.dof != physics::PoseDof::Free; }
  Points world() const { return place(mesh.V, scale, R, t); }
};

// The steps, in order, on shared state.
struct Run {
  const ReconstructInputs& in;
  const ReconstructOptions& opt;
  resample::Resampler* resampler;
  std::string out_dir;
  ReconstructResult res;
  PointMap pm;
  Pinhole K;
  std::vector<Work> objs;
  Points floor_pts = Points(0, 3);
  std::vector<WallInput> walls;
  std::map<std::string, Mask> wall_masks;  // wall entries' masks (a hanging object's ring may use them)
  Mask object_pixels;                      // union of the object (not floor / wall) masks

  Run(const ReconstructInputs& i, const ReconstructOptions& o, resample::Resampler* r, std::string dir)
      : in(i), opt(o), resampler(r), out_dir(std::move(dir)) {
    pm = to_point_map(in.lift.pointmap);
    const auto& c = in.lift.camera;
    K = Pinhole{c.fx, c.fy, c.cx, c.cy, c.width, c.height};
    object_pixels = Mask(K.width, K.height);
    res.messages = in.messages;
  }

  // Sidecar entries matched to the masks; masks without an entry become free objects.
  std::vector<ObjectSpec> resolve_specs() {
    std::map<std::string, size_t> mask_index;
    for (size_t i = 0; i < in.lift.objects.size(); ++i) mask_index[in.lift.objects[i].id] = i;
    std::map<std::string, bool> named;
    std::vector<ObjectSpec> resolved;
    for (auto& s : in.specs) {
      if (!mask_index.count(s.mask_id)) {
        ObjectReport r{s.id, s.label, s.role};
        r.skipped.push_back(fmt::format("input: the sidecar {} names mask '{}' (object '{}'), which the masks do not have",
                                        in.sidecar_name, s.mask_id, s.id));
        res.objects.push_back(r);
        continue;
      }
      named[s.mask_id] = true;
      resolved.push_back(s);
    }
    for (auto& o : in.lift.objects)
      if (!named.count(o.id)) {
        ObjectSpec s;
        s.mask_id = s.id = o.id;
        resolved.push_back(s);
        if (!in.sidecar_name.empty()) res.messages.push_back(fmt::format("mask '{}' has no sidecar entry: a free object", o.id));
      }
    return resolved;
  }

  // A brought mesh + SAM 3D pose -> canonical mesh and scene pose (throws naming the file).
  void load_brought_mesh(Work& w) {
    const ObjectSpec& s = w.spec;
    physics::Mesh m = physics::read_mesh(s.mesh);
    const std::string prob = physics::mesh_problem(m);
    SIMU_CHECK(prob.empty(), "{}: {}", s.mesh, prob);
    const Vec3 centre = physics::mesh_aabb(m).center();
    const double factor = physics::canonicalize(m);
    const json pj = read_json_file(s.pose);
    Sam3dPose p;
    const json& rq = pj.at("rotation_wxyz");
    SIMU_CHECK(rq.is_array() && rq.size() == 4, "{}: rotation_wxyz needs 4 numbers", s.pose);
    for (int k = 0; k < 4; ++k) p.rotation_wxyz[k] = rq[k].get<double>();
    p.translation = vec3_of(pj.at("translation"), s.pose + ": translation");
    p.scale = vec3_of(pj.at("scale"), s.pose + ": scale");
    const ScenePoseOut sp = scene_pose_from_sam3d_mesh(p, centre, factor);
    w.mesh = m;
    w.R = sp.R;
    w.scale = sp.scale;
    w.t = sp.t;
    if (!s.up_axis.empty()) w.up_axis = parse_axis(s.up_axis, s.id + ": up_axis");
    w.ok = true;
    w.rep.steps.push_back("byo_mesh");
  }

  // Masks, floor / wall points, brought meshes; objects to lift are queued into to_lift.
  void prepare(resample::LiftInputs& to_lift, std::vector<size_t>& lift_of) {
    const auto t0 = Clock::now();
    std::map<std::string, size_t> mask_index;
    for (size_t i = 0; i < in.lift.objects.size(); ++i) mask_index[in.lift.objects[i].id] = i;
    for (const auto& s : resolve_specs()) {
      const auto& lo = in.lift.objects[mask_index[s.mask_id]];
      Work w;
      w.spec = s;
      w.rep = ObjectReport{s.id, s.label, s.role};
      if (!lo.error.empty() || lo.mask.size(0) != K.height || lo.mask.size(1) != K.width) {
        w.rep.skipped.push_back(!lo.error.empty() ? "input: " + lo.error
                                                  : fmt::format("input: mask '{}' is {}x{}, the image {}x{}", s.id,
                                                                lo.mask.size(1), lo.mask.size(0), K.width, K.height));
        res.objects.push_back(w.rep);
        continue;
      }
      w.mask = to_mask(lo.mask);
      w.observed = masked_points(pm, w.mask, s.id);
      if (s.role == "floor" || s.role == "wall") {
        if (s.role == "floor") {
          Points n(floor_pts.rows() + w.observed.rows(), 3);
          n << floor_pts, w.observed;
          floor_pts = n;
        } else {
          walls.push_back({s.id, w.observed});
          wall_masks[s.id] = w.mask;
        }
        w.rep.used = true;
        res.objects.push_back(w.rep);
        continue;
      }
      for (size_t i = 0; i < w.mask.data.size(); ++i) object_pixels.data[i] |= w.mask.data[i];
      if (s.fit == "box") {
        // Fitted after the first plane pass (fit_boxes), not lifted.
      } else if (!s.mesh.empty()) {
        try {
          load_brought_mesh(w);
        } catch (const std::exception& e) {
          w.rep.skipped.push_back(fmt::format("mesh: object '{}': {}", s.id, e.what()));
        }
      } else if (resampler) {
        lift_of.push_back(objs.size());
        to_lift.objects.push_back({s.id, lo.mask, {}, ""});
      } else {
        w.rep.skipped.push_back(fmt::format("lift: object '{}' brings no mesh and no model is loaded (pass the model flags)", s.id));
      }
      objs.push_back(std::move(w));
    }
    res.timings["byo_meshes"] = since(t0);
  }

  // Step 1: one batched lift of the queued objects.
  void lift(const resample::LiftInputs& to_lift, const std::vector<size_t>& lift_of) {
    if (to_lift.objects.empty()) return;
    const auto t0 = Clock::now();
    const resample::LiftResult lr = resample::lift_objects(*resampler, to_lift, opt.lift);
    const Vec3 axis = opt.lift_up_axis.empty() ? Vec3(Vec3::Zero()) : parse_axis(opt.lift_up_axis, "lift_up_axis");
    for (size_t k = 0; k < lift_of.size(); ++k) {
      Work& w = objs[lift_of[k]];
      const auto& lo = lr.objects[k];
      if (!lo.ok) {
        w.rep.skipped.push_back("lift: " + lo.error);
        continue;
      }
      for (size_t sidx = 0; sidx < lo.samples.size(); ++sidx)
        if (lo.samples[sidx].ok)
          w.samples.push_back({lo.samples[sidx].mesh, lo.scene_poses[sidx].scale, lo.scene_poses[sidx].R,
                               lo.scene_poses[sidx].t, sidx});
      if (w.samples.empty()) continue;
      use_sample(w, 0);
      w.up_axis = axis;
      w.ok = true;
      w.rep.steps.push_back(w.samples.size() == 1 ? fmt::format("lifted (sample {})", w.samples[0].index)
                                                  : fmt::format("lifted ({} usable samples of {})", w.samples.size(),
                                                                lo.samples.size()));
    }
    res.timings["lift"] = since(t0);
    res.timings["lift_stages"] = {{"preprocess", lr.seconds.preprocess}, {"embed", lr.seconds.embed},
                                  {"sample", lr.seconds.sample},         {"decode", lr.seconds.decode},
                                  {"mesh", lr.seconds.mesh},             {"pose", lr.seconds.pose}};
  }

  // Sample c of a lifted object becomes its mesh and pose.
  static void use_sample(Work& w, size_t c) {
    const Work::Sample& s = w.samples[c];
    w.mesh.V = s.mesh.V;
    w.mesh.F = s.mesh.F;
    w.R = s.R;
    w.scale = s.scale;
    w.t = s.t;
  }

  // Refined poses (e.g. FoundationPose; scene convention in the camera frame) replace the rotation.
  void refined_poses() {
    for (auto& w : objs) {
      if (!w.ok || w.spec.refined_pose.empty()) continue;
      try {
        const json j = read_json_file(w.spec.refined_pose);
        const json& Rj = j.at("R");
        SIMU_CHECK(Rj.is_array() && Rj.size() == 3, "{}: R must be 3x3", w.spec.refined_pose);
        Mat3 R;
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c) R(r, c) = Rj.at(r).at(c).get<double>();
        SIMU_CHECK((R.transpose() * R - Mat3::Identity()).norm() < 1e-3 && R.determinant() > 0,
                   "{}: R is not a rotation", w.spec.refined_pose);
        w.R = R;
        if (j.contains("t")) w.t = vec3_of(j["t"], w.spec.refined_pose + ": t");
        // Every lifted sample takes the refined pose (step 2 chooses among them).
        for (auto& s : w.samples) {
          s.R = w.R;
          if (j.contains("t")) s.t = w.t;
        }
        w.rep.steps.push_back("refined_pose");
      } catch (const std::exception& e) {
        w.rep.skipped.push_back(fmt::format("refined_pose: {}", e.what()));
      }
    }
  }

  // Step 2: translation-scale alignment of every object (objects, and the samples of an object lifted
  // with several, in parallel on the intra-op threads: each alignment is independent and single-threaded).
  // Of several samples, the one with the lowest pose_score at its aligned pose (its lifted pose when it
  // could not be aligned) is kept.
  void align() {
    const auto t0 = Clock::now();
    struct Job {
      size_t k = 0, c = 0;  // object, sample
      AlignInput in;
      AlignResult r;
      double score = std::numeric_limits<double>::infinity();
      std::string error;
      double seconds = 0;
    };
    std::vector<Job> jobs;
    for (size_t k = 0; k < objs.size(); ++k) {
      Work& w = objs[k];
      if (!w.ok) continue;
      w.rep.s_before = w.scale.maxCoeff();
      w.rep.t_before = w.t;
      for (size_t c = 0; c < std::max<size_t>(1, w.samples.size()); ++c) {
        if (!w.samples.empty()) use_sample(w, c);
        Job j;
        j.k = k;
        j.c = c;
        AlignInput& ai = j.in;
        ai.id = w.spec.id;
        ai.canonical = w.mesh.V;
        ai.faces = w.mesh.F;
        ai.shape = w.scale / w.scale.maxCoeff();
        ai.s_init = w.scale.maxCoeff();
        ai.R_init = w.R;
        ai.t_init = w.t;
        ai.observed = w.observed;
        ai.mask = w.mask;
        ai.K = K;
        ai.depth = &pm;
        jobs.push_back(std::move(j));
      }
      if (!w.samples.empty()) use_sample(w, 0);
    }
    at::parallel_for(0, int64_t(jobs.size()), 1, [&](int64_t b, int64_t e) {
      for (int64_t i = b; i < e; ++i) {
        Job& j = jobs[size_t(i)];
        const auto tk = Clock::now();
        try {
          if (opt.do_align) j.r = align_translation_scale(j.in, opt.align);
          if (objs[j.k].samples.size() > 1)
            j.score = j.r.ok ? pose_score(j.in, j.in.R_init, j.r.s, j.r.t) : pose_score(j.in, j.in.R_init, j.in.s_init, j.in.t_init);
        } catch (const std::exception& ex) {
          j.error = ex.what();
        }
        j.seconds = since(tk);
      }
    });
    // Per object: the kept sample (the first of the lowest score) and its alignment.
    std::map<size_t, const Job*> kept;
    for (const Job& j : jobs) {
      SIMU_CHECK(j.error.empty(), "{}", j.error);
      auto it = kept.find(j.k);
      if (it == kept.end() || j.score < it->second->score) kept[j.k] = &j;
    }
    for (const auto& [k, jp] : kept) {
      const Job& j = *jp;
      Work& w = objs[k];
      if (w.samples.size() > 1) {
        use_sample(w, j.c);
        w.rep.s_before = w.scale.maxCoeff();
        w.rep.t_before = w.t;
        std::vector<std::string> scores;
        for (const Job& o : jobs)
          if (o.k == k) scores.push_back(fmt::format("{:.3f}", o.score));
        w.rep.steps.push_back(fmt::format("kept sample {} of {} by its agreement with the depth and mask (scores {})",
                                          w.samples[j.c].index, w.samples.size(), fmt::join(scores, ", ")));
      }
      if (!opt.do_align) continue;
      if (!j.r.ok) {
        w.rep.skipped.push_back("align: " + j.r.message + " (no valid depth: kept the lifted pose)");
        continue;
      }
      w.scale = j.r.s * j.in.shape;
      w.t = j.r.t;
      w.rep.steps.push_back(fmt::format("aligned (start rho {}, {:.2f} s)", j.r.candidates[size_t(j.r.best)].rho, j.seconds));
    }
    res.timings["align"] = since(t0);
  }

  // The mesh-derived up: the mean of the objects' canonical up axes in the world (zero when none is known).
  Vec3 mesh_up() const {
    Vec3 sum = Vec3::Zero();
    for (const auto& w : objs)
      if (w.ok && w.up_axis.norm() > 0) sum += (w.R * w.up_axis).normalized();
    return sum.norm() > 1e-6 ? Vec3(sum.normalized()) : Vec3(Vec3::Zero());
  }

  // Step 3: floor and walls from their masks (first pass), up by the paper's priority.
  void first_planes() {
    const auto t0 = Clock::now();
    res.planes_first = fit_planes(floor_pts, walls, sample_points(pm, 7, nullptr), mesh_up(), opt.planes);
    res.planes = res.planes_first;
    res.timings["planes"] = since(t0);
  }

  // Step 4a: bases with "fit": "box", fitted to their mask's depth (support_box.h).
  void fit_boxes() {
    const auto t0 = Clock::now();
    for (auto& w : objs) {
      if (w.spec.fit != "box") continue;
      TabletopInput ti;
      ti.id = w.spec.id;
      ti.points = &pm;
      ti.mask = w.mask;
      ti.K = K;
      ti.up = res.planes.up;
      if (res.planes.floor) ti.floor = res.planes.floor->plane;
      const SupportBoxResult b = fit_support_box(ti, opt.tabletop, opt.support_box);
      if (!b.ok) {
        w.rep.skipped.push_back(fmt::format("fit box: base '{}': {} (left out of the scene)", w.spec.id, b.message));
        continue;
      }
      w.mesh.V = b.canonical;
      w.mesh.F = b.faces;
      w.scale = b.scale;
      w.R = b.R;
      w.t = b.t;
      w.ok = true;
      w.rep.steps.push_back(fmt::format("fitted box ({:.2f} x {:.2f} x {:.2f} m, {} points)", b.extents.x(), b.extents.y(),
                                        b.extents.z(), b.points));
    }
    res.timings["fit_boxes"] = since(t0);
  }

  // Step 4b: tabletop refinement of lifted table / desk objects.
  void tabletop() {
    const auto t0 = Clock::now();
    for (auto& w : objs) {
      if (!w.ok || !opt.do_tabletop || !is_table_label(w.spec.label) || w.spec.fit == "box") continue;
      TabletopInput ti;
      ti.id = w.spec.id;
      ti.canonical = w.mesh.V;
      ti.faces = w.mesh.F;
      ti.scale = w.scale;
      ti.R = w.R;
      ti.t = w.t;
      ti.points = &pm;
      ti.mask = w.mask;
      ti.K = K;
      ti.up = res.planes.up;
      if (res.planes.floor) ti.floor = res.planes.floor->plane;
      const TabletopResult tr = refine_tabletop(ti, opt.tabletop);
      if (!tr.ok) {
        w.rep.skipped.push_back("tabletop: " + tr.message);
        continue;
      }
      w.scale = tr.scale;
      w.R = tr.R;
      w.t = tr.t;
      w.rep.steps.push_back(fmt::format("tabletop (yaw {:.2f} deg, scale x{:.3f})", tr.theta_deg, std::exp(tr.log_s)));
    }
    res.timings["tabletop"] = since(t0);
  }

  // Step 5: the plane stack re-extracted with the fitted meshes (their up axes as the mesh-derived up;
  // the fallback floor from the point map without the objects' pixels), then the floor offset snapped
  // to the lowest vertex of the union of the fitted standing meshes.
  void reextract_planes() {
    const auto t0 = Clock::now();
    res.mesh_up = mesh_up();
    res.planes = fit_planes(floor_pts, walls, sample_points(pm, 7, &object_pixels), res.mesh_up, opt.planes);
    if (res.mesh_up.norm() > 0 && angle_deg(res.mesh_up, res.planes.up) > 10)
      res.messages.push_back(fmt::format("the fitted meshes' up is {:.1f} deg from the chosen up (from {})",
                                         angle_deg(res.mesh_up, res.planes.up), res.planes.up_source));
    if (opt.do_floor_snap) {
      std::vector<Points> resting;
      for (auto& w : objs)
        if (w.ok && !w.hanging()) resting.push_back(w.world());
      res.floor_snap = snap_floor_to_meshes(res.planes, resting, opt.planes.max_floor_snap);
      if (res.floor_snap != 0)
        res.messages.push_back(fmt::format("floor snapped by {:+.4f} m along up to the lowest fitted-mesh vertex", res.floor_snap));
    }
    res.timings["reextract"] = since(t0);
  }

  // A wall fitted to the depth in a ring around a hanging object's mask (other objects' pixels left out).
  std::optional<NamedPlane> wall_around(const Work& w, const Vec3& centre) {
    const Mask ring = dilate(w.mask, opt.hang_wall_ring_px);
    std::vector<Vec3> v;
    for (size_t i = 0; i < ring.data.size(); ++i)
      if (ring.data[i] && !object_pixels.data[i] && PointMap::valid(pm.p[i])) v.push_back(pm.p[i]);
    Points P(Eigen::Index(v.size()), 3);
    for (size_t i = 0; i < v.size(); ++i) P.row(Eigen::Index(i)) = v[i].transpose();
    RansacConfig rc;
    rc.threshold = opt.planes.wall_threshold;
    rc.iterations = opt.planes.iterations;
    rc.seed = opt.planes.seed + 7;
    rc.min_inliers = opt.planes.min_support;
    // Facing the camera: the normal within 60 degrees of the horizontal direction to the camera.
    Vec3 to_cam = -centre - (-centre).dot(res.planes.up) * res.planes.up;
    if (to_cam.norm() < 1e-9) return std::nullopt;
    rc.axis = to_cam.normalized();
    rc.max_angle_deg = 60;
    auto f = ransac_plane(P, rc);
    if (!f) return std::nullopt;
    Vec3 n = f->normal - f->normal.dot(res.planes.up) * res.planes.up;  // rectified: perpendicular to up
    if (n.norm() < 1e-6) return std::nullopt;
    n.normalize();
    if (n.dot(-f->point) < 0) n = -n;
    f->normal = n;
    if (f->distance(centre) <= 0) return std::nullopt;  // the object must hang in front of it
    return NamedPlane{w.spec.id + "_wall", *f};
  }

  // Every hanging object gets its wall (collider and anchor): the sidecar's, else the nearest fitted wall
  // behind it within hang_wall_max_gap, else one fitted to the depth around its mask.
  void hanging_walls() {
    for (auto& w : objs) {
      if (!w.ok || w.spec.base || !w.hanging()) continue;
      const Points W = w.world();
      const Vec3 centre = W.colwise().mean().transpose();
      if (!w.spec.wall.empty()) {
        bool found = false;
        for (const auto& p : res.planes.walls) found |= p.id == w.spec.wall;
        if (found) {
          w.rep.wall = w.spec.wall;
          continue;
        }
        w.rep.skipped.push_back(fmt::format("wall: the sidecar names wall '{}', which was not fitted: looking for another",
                                            w.spec.wall));
      }
      // The nearest fitted wall behind the object: the mesh's vertex nearest to it within the gap.
      int best = -1;
      double best_gap = opt.hang_wall_max_gap;
      for (size_t k = 0; k < res.planes.walls.size(); ++k) {
        const PlaneFit& p = res.planes.walls[k].plane;
        if (p.distance(centre) <= 0) continue;
        double gap = 1e300;
        for (Eigen::Index i = 0; i < W.rows(); ++i) gap = std::min(gap, std::abs(p.distance(W.row(i).transpose())));
        if (gap <= best_gap) best_gap = gap, best = int(k);
      }
      if (best >= 0) {
        w.rep.wall = res.planes.walls[size_t(best)].id;
        continue;
      }
      if (auto p = wall_around(w, centre)) {
        res.planes.walls.push_back(*p);
        w.rep.wall = p->id;
        res.messages.push_back(fmt::format("hanging object '{}': no fitted wall within {} m behind it; wall '{}' fitted to "
                                           "the depth around its mask ({} inliers)",
                                           w.spec.id, opt.hang_wall_max_gap, p->id, p->plane.inliers));
        continue;
      }
      w.rep.skipped.push_back(fmt::format("wall: hanging object '{}' has no fitted wall within {} m and no plane fits the "
                                          "depth around its mask: the probe picks the nearest wall, if any",
                                          w.spec.id, opt.hang_wall_max_gap));
    }
  }

  // Step 6a: the pre-simulation scene (world = the OpenCV camera), its meshes and masks.
  void compose() {
    physics::Scene sc;
    sc.camera = in.lift.camera;
    sc.camera.R_world_cam = Mat3::Identity();
    sc.camera.t_world_cam = Vec3::Zero();
    sc.image_path = in.image_path;
    // The point map goes with the scene: the probe's in-process resampling lifts from it (depth_path).
    if (in.lift.pointmap.defined() && in.lift.pointmap.numel() > 0) {
      sc.depth_path = (sfs::path(out_dir) / "input" / "pointmap.npy").string();
      data::write_npy(sc.depth_path, in.lift.pointmap.to(torch::kCPU, torch::kFloat32).contiguous());
    }
    sc.gravity = -res.planes.up;
    if (res.planes.floor) sc.floor = physics::Plane{"floor", res.planes.floor->plane.point, res.planes.floor->plane.normal};
    for (auto& w : res.planes.walls) sc.walls.push_back(physics::Plane{w.id, w.plane.point, w.plane.normal});
    const sfs::path idir = sfs::path(out_dir) / "input";
    for (auto& w : objs) {
      w.rep.s_after = w.scale.maxCoeff();
      w.rep.t_after = w.t;
      if (w.ok) {
        const std::string mp = (idir / "meshes" / (w.spec.id + ".obj")).string();
        physics::write_mesh(w.mesh, mp);
        if (w.spec.base) {
          sc.bases.push_back(physics::BaseBody{w.spec.id, mp, w.scale, w.R, w.t, ""});
        } else {
          const std::string kp = (idir / "masks" / (w.spec.id + ".png")).string();
          physics::SceneObject o;
          o.id = w.spec.id;
          o.label = w.spec.label;
          o.mesh_path = mp;
          if (write_mask(w.mask, kp)) o.mask_path = kp;
          o.scale = w.scale;
          o.R = w.R;
          o.t = w.t;
          o.dof = w.spec.dof;
          o.wall_id = w.rep.wall;
          if (auto it = opt.gt_boxes.find(w.spec.id); it != opt.gt_boxes.end()) o.gt_box = it->second;
          sc.objects.push_back(o);
        }
        w.rep.used = true;
      }
      res.objects.push_back(w.rep);
    }
    sc.extra["reconstruct"] = {{"frame", "world = the OpenCV camera of the photo (x right, y down, z forward, metres)"},
                               {"up", vj(res.planes.up)},
                               {"up_source", res.planes.up_source}};
    const std::string scene_path = (idir / "scene.json").string();
    physics::save_scene(sc, scene_path);
    res.scene = physics::load_scene(scene_path);
  }

  // ReconstructOptions::align_resampled: the resampler's candidates get the alignment's scale.
  physics::ResampleFn align_resampled(physics::ResampleFn inner) {
    return [this, inner](const std::vector<physics::ProbeResampleRequest>& requests) {
      auto out = inner(requests);
      for (size_t k = 0; k < requests.size() && k < out.size(); ++k) {
        const Work* w = nullptr;
        for (const auto& o : objs)
          if (o.spec.id == requests[k].object_id) w = &o;
        if (!w || !out[k].ok || w->observed.rows() == 0) continue;
        auto fit = [&](const physics::Mesh& mesh, const Mat3& R, Vec3& scale) {
          AlignInput ai;
          ai.id = w->spec.id;
          ai.canonical = mesh.V;
          ai.faces = mesh.F;
          ai.shape = scale / scale.maxCoeff();
          ai.s_init = scale.maxCoeff();
          ai.R_init = R;
          ai.t_init = requests[k].target_obb.center;
          ai.observed = w->observed;
          ai.mask = w->mask;
          ai.K = K;
          ai.depth = &pm;
          const AlignResult ar = align_translation_scale(ai, opt.align);
          if (ar.ok) scale = ar.s * ai.shape;
        };
        for (auto& c : out[k].candidates) fit(c.mesh, c.R, c.scale);
        fit(out[k].mesh, out[k].R, out[k].scale);
      }
      return out;
    };
  }

  // Step 6b: the probe (in-process resampling when a model is loaded).
  void probe() {
    if (!opt.run_probe) return;
    const auto t0 = Clock::now();
    physics::ResampleFn fn;
    if (resampler) {
      resample::ProbeResamplerOptions ro;
      ro.seed = opt.lift.seed;
      ro.preprocess = opt.lift.preprocess;
      fn = resample::make_probe_resample_fn(*resampler, res.scene, ro);
      if (opt.align_resampled) fn = align_resampled(fn);
    }
    res.probe = physics::run_probe(res.scene, opt.probe, (sfs::path(out_dir) / "probe").string(), fn);
    res.timings["probe"] = since(t0);
  }
};
}  // namespace

ReconstructResult reconstruct(const ReconstructFiles& files, const ReconstructOptions& opt, resample::Resampler* resampler,
                              const std::string& out_dir) {
  resample::check_output_dir(out_dir, opt.overwrite);
  const auto t0 = Clock::now();
  const ReconstructInputs in = load_reconstruct_inputs(files);
  const double load = since(t0);
  ReconstructResult res = reconstruct(in, opt, resampler, out_dir);
  res.timings["load"] = load;
  res.timings["total"] = res.timings.value("total", 0.0) + load;
  fs::atomic_write((sfs::path(out_dir) / "reconstruct_report.json").string(),
                   detail::report_json(res, opt.run_probe).dump(2) + "\n");
  return res;
}

namespace {
ReconstructResult reconstruct_into(const ReconstructInputs& in, const ReconstructOptions& opt, resample::Resampler* resampler,
                                   const std::string& out_dir);
}  // namespace

ReconstructResult reconstruct(const ReconstructInputs& in, const ReconstructOptions& opt, resample::Resampler* resampler,
                              const std::string& out_dir) {
  resample::check_output_dir(out_dir, opt.overwrite);
  // Everything is written into "<out>.tmp-<pid>" and moved into place at the end (fs::replace_dir): a
  // failed run leaves an earlier output as it was; temporaries of dead runs are removed first.
  const sfs::path final_dir = sfs::absolute(out_dir).lexically_normal();
  sfs::create_directories(final_dir.parent_path());
  fs::remove_stale_temps(final_dir.string());
  const std::string stage = final_dir.string() + ".tmp-" + std::to_string(::getpid());
  fs::remove_tree(stage);
  sfs::create_directories(sfs::path(stage) / "input" / "meshes");
  sfs::create_directories(sfs::path(stage) / "input" / "masks");
  try {
    ReconstructResult res = reconstruct_into(in, opt, resampler, stage);
    fs::replace_dir(stage, final_dir.string());
    // The in-memory scene and pictures named the staging folder.
    res.scene = physics::load_scene((final_dir / "input" / "scene.json").string());
    if (res.probe)
      for (auto& f : res.probe->pictures)
        if (f.rfind(stage, 0) == 0) f = final_dir.string() + f.substr(stage.size());
    return res;
  } catch (...) {
    try {
      fs::remove_tree(stage);
    } catch (...) {
    }
    throw;
  }
}

namespace {
// The steps of reconstruct(), writing into dir (the staging folder).
ReconstructResult reconstruct_into(const ReconstructInputs& in, const ReconstructOptions& opt, resample::Resampler* resampler,
                                   const std::string& out_dir) {
  const auto t_all = Clock::now();
  Run run(in, opt, resampler, out_dir);
  resample::LiftInputs to_lift;
  to_lift.rgb = in.lift.rgb;
  to_lift.pointmap = in.lift.pointmap;
  to_lift.camera = in.lift.camera;
  std::vector<size_t> lift_of;
  run.prepare(to_lift, lift_of);
  run.lift(to_lift, lift_of);
  run.refined_poses();
  run.align();
  run.first_planes();
  run.fit_boxes();
  run.tabletop();
  run.reextract_planes();
  run.hanging_walls();
  for (auto& m : run.res.planes.messages) run.res.messages.push_back(m);
  run.compose();
  run.probe();
  run.res.timings["total"] = since(t_all);
  fs::atomic_write((sfs::path(out_dir) / "reconstruct_report.json").string(),
                   detail::report_json(run.res, opt.run_probe).dump(2) + "\n");
  return std::move(run.res);
}
}  // namespace

}  // namespace simu::reconstruct
