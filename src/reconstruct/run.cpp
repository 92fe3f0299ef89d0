#include "reconstruct/run.h"

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "physics/mesh.h"
#include "resample/probe_resampler.h"
#include "reconstruct/synthetic_camera.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>

namespace simu::reconstruct {

namespace sfs = std::filesystem;
using nlohmann::json;

namespace {
double since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}
json vj(const Vec3& v) { return {v.x(), v.y(), v.z()}; }
Vec3 vec3_of(const json& j, const std::string& what) {
  if (j.is_number()) return Vec3::Constant(j.get<double>());
  SIMU_CHECK(j.is_array() && j.size() == 3, "{}: expected 3 numbers (or one for an isotropic scale), got {}", what, j.dump());
  Vec3 v;
  for (int k = 0; k < 3; ++k) {
    SIMU_CHECK(j[k].is_number(), "{}: element {} is not a number", what, k);
    v[k] = j[k].get<double>();
  }
  SIMU_CHECK(v.allFinite(), "{}: not finite", what);
  return v;
}
json read_json_file(const std::string& path) {
  std::ifstream f(path);
  SIMU_CHECK(f.good(), "{}: cannot open", path);
  try {
    return json::parse(f);
  } catch (const std::exception& e) {
    fail("{}: not valid JSON ({})", path, e.what());
  }
}
std::string resolve(const std::string& p, const std::string& base) {
  if (p.empty() || sfs::path(p).is_absolute()) return p;
  return (sfs::path(base) / p).lexically_normal().string();
}
PointMap to_point_map(const torch::Tensor& pm) {
  const auto t = pm.to(torch::kCPU, torch::kFloat64).contiguous();
  PointMap m;
  m.height = int(t.size(0));
  m.width = int(t.size(1));
  m.p.resize(size_t(m.width) * m.height);
  const double* d = t.data_ptr<double>();
  for (size_t i = 0; i < m.p.size(); ++i) {
    m.p[i] = Vec3(d[3 * i], d[3 * i + 1], d[3 * i + 2]);
    if (!PointMap::valid(m.p[i])) m.p[i] = Vec3::Constant(std::nan(""));
  }
  return m;
}
Mask to_mask(const torch::Tensor& t) {
  const auto m = (t.to(torch::kCPU, torch::kFloat32) > 0).to(torch::kUInt8).contiguous();
  Mask out(int(m.size(1)), int(m.size(0)));
  std::memcpy(out.data.data(), m.data_ptr<uint8_t>(), out.data.size());
  return out;
}
void write_mask(const Mask& m, const std::string& path) {
#ifdef SIMU_HAVE_OPENCV
  cv::Mat img(m.height, m.width, CV_8UC1);
  for (int r = 0; r < m.height; ++r)
    for (int c = 0; c < m.width; ++c) img.at<uint8_t>(r, c) = m.at(r, c) ? 255 : 0;
  SIMU_CHECK(cv::imwrite(path, img), "{}: cannot write the mask", path);
#else
  (void)m;
  (void)path;
#endif
}
}  // namespace

json ObjectReport::to_json() const {
  return {{"id", id}, {"label", label}, {"role", role}, {"used", used}, {"steps", steps}, {"skipped", skipped},
          {"scale_before", s_before}, {"scale_after", s_after}, {"t_before", vj(t_before)}, {"t_after", vj(t_after)}};
}

std::vector<ObjectSpec> read_sidecar(const std::string& path, std::vector<std::string>* problems) {
  const json j = read_json_file(path);
  const json& arr = j.is_object() ? j.value("objects", json()) : j;
  SIMU_CHECK(arr.is_array(), "{}: expected {{\"objects\": [...]}} or a list of objects", path);
  const std::string base = sfs::path(path).parent_path().string();
  std::vector<ObjectSpec> out;
  static const std::vector<std::string> known = {"id", "label_value", "mask", "label", "role", "dof", "pins",
                                                 "base", "mesh", "pose", "refined_pose"};
  for (size_t i = 0; i < arr.size(); ++i) {
    const json& e = arr[i];
    const std::string what = fmt::format("{}: objects[{}]", path, i);
    SIMU_CHECK(e.is_object(), "{}: expected an object", what);
    for (auto it = e.begin(); it != e.end(); ++it)
      if (std::find(known.begin(), known.end(), it.key()) == known.end())
        fail("{}: unknown key '{}' (known: {})", what, it.key(), fmt::join(known, ", "));
    ObjectSpec s;
    // Which mask: label_value k of a label image ("label_<k>"), or a per-object mask's file stem.
    if (e.contains("label_value")) {
      SIMU_CHECK(e["label_value"].is_number_integer(), "{}: label_value must be an integer", what);
      s.mask_id = fmt::format("label_{}", e["label_value"].get<int64_t>());
    } else if (e.contains("mask")) {
      s.mask_id = e["mask"].get<std::string>();
    } else {
      SIMU_CHECK(e.contains("id"), "{}: needs label_value, mask or id", what);
      s.mask_id = e["id"].get<std::string>();
    }
    s.id = e.value("id", s.mask_id);
    s.label = e.value("label", std::string());
    s.role = e.value("role", std::string("object"));
    SIMU_CHECK(s.role == "object" || s.role == "floor" || s.role == "wall", "{}: role '{}' (object, floor, wall)", what, s.role);
    const std::string dof = e.value("dof", std::string("free"));
    if (dof == "free") s.dof = physics::PoseDof::Free;
    else if (dof == "point" || dof == "point_anchored") s.dof = physics::PoseDof::PointAnchored;
    else if (dof == "line" || dof == "line_anchored") s.dof = physics::PoseDof::LineAnchored;
    else fail("{}: dof '{}' (free, point, line)", what, dof);
    if (e.contains("pins")) {
      const int pins = e["pins"].get<int>();
      if (pins != physics::pin_count(s.dof))
        problems->push_back(fmt::format("{}: pins {} disagrees with dof {} ({} pins): the dof wins", what, pins, dof,
                                        physics::pin_count(s.dof)));
    }
    s.base = e.value("base", false);
    s.mesh = resolve(e.value("mesh", std::string()), base);
    s.pose = resolve(e.value("pose", std::string()), base);
    s.refined_pose = resolve(e.value("refined_pose", std::string()), base);
    SIMU_CHECK(s.mesh.empty() == s.pose.empty(), "{}: mesh and pose come together (bring your own lift)", what);
    out.push_back(s);
  }
  return out;
}

ReconstructResult reconstruct(const ReconstructFiles& files, const ReconstructOptions& opt, resample::Resampler* resampler,
                              const std::string& out_dir) {
  ReconstructResult res;
  resample::check_output_dir(out_dir, opt.overwrite);
  if (sfs::exists(out_dir)) sfs::remove_all(out_dir);
  sfs::create_directories(sfs::path(out_dir) / "input" / "meshes");
  sfs::create_directories(sfs::path(out_dir) / "input" / "masks");
  auto t_all = std::chrono::steady_clock::now();
  // ---- Inputs ----
  auto t0 = std::chrono::steady_clock::now();
  resample::LiftInputs in = resample::load_lift_inputs(files.lift);
  const PointMap pm = to_point_map(in.pointmap);
  const Pinhole K{in.camera.fx, in.camera.fy, in.camera.cx, in.camera.cy, in.camera.width, in.camera.height};
  std::map<std::string, size_t> mask_index;
  for (size_t i = 0; i < in.objects.size(); ++i) mask_index[in.objects[i].id] = i;
  std::vector<ObjectSpec> specs;
  if (!files.sidecar.empty()) specs = read_sidecar(files.sidecar, &res.messages);
  std::map<std::string, bool> named;
  std::vector<ObjectSpec> resolved;
  for (auto& s : specs) {
    if (!mask_index.count(s.mask_id)) {
      ObjectReport r{s.id, s.label, s.role};
      r.skipped.push_back(fmt::format("input: the sidecar {} names mask '{}' (object '{}'), which the masks do not have",
                                      files.sidecar, s.mask_id, s.id));
      res.objects.push_back(r);
      continue;
    }
    named[s.mask_id] = true;
    resolved.push_back(s);
  }
  for (auto& o : in.objects)
    if (!named.count(o.id)) {
      ObjectSpec s;
      s.mask_id = s.id = o.id;
      resolved.push_back(s);
      if (!files.sidecar.empty()) res.messages.push_back(fmt::format("mask '{}' has no sidecar entry: a free object", o.id));
    }
  res.timings["load"] = since(t0);

  // ---- Per object: mesh and initial pose (bring your own lift, or the port) ----
  struct Work {
    ObjectSpec spec;
    ObjectReport rep;
    Mask mask;
    Points observed;
    physics::Mesh mesh;  // canonical
    Vec3 scale = Vec3::Ones();
    Mat3 R = Mat3::Identity();
    Vec3 t = Vec3::Zero();
    bool ok = false;
  };
  std::vector<Work> objs;
  Points floor_pts(0, 3);
  std::vector<WallInput> walls;
  resample::LiftInputs to_lift;
  to_lift.rgb = in.rgb;
  to_lift.pointmap = in.pointmap;
  to_lift.camera = in.camera;
  std::vector<size_t> lift_of;
  t0 = std::chrono::steady_clock::now();
  for (const auto& s : resolved) {
    const auto& lo = in.objects[mask_index[s.mask_id]];
    Work w;
    w.spec = s;
    w.rep = ObjectReport{s.id, s.label, s.role};
    if (!lo.error.empty()) {
      w.rep.skipped.push_back("input: " + lo.error);
      res.objects.push_back(w.rep);
      continue;
    }
    if (lo.mask.size(0) != in.camera.height || lo.mask.size(1) != in.camera.width) {
      w.rep.skipped.push_back(fmt::format("input: mask '{}' is {}x{}, the image {}x{}", s.id, lo.mask.size(1), lo.mask.size(0),
                                          in.camera.width, in.camera.height));
      res.objects.push_back(w.rep);
      continue;
    }
    w.mask = to_mask(lo.mask);
    w.observed = masked_points(pm, w.mask, s.id);
    if (s.role == "floor") {
      Points n(floor_pts.rows() + w.observed.rows(), 3);
      n << floor_pts, w.observed;
      floor_pts = n;
      w.rep.used = true;
      res.objects.push_back(w.rep);
      continue;
    }
    if (s.role == "wall") {
      walls.push_back({s.id, w.observed});
      w.rep.used = true;
      res.objects.push_back(w.rep);
      continue;
    }
    if (!s.mesh.empty()) {
      try {
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
        w.ok = true;
        w.rep.steps.push_back("byo_mesh");
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
  if (!to_lift.objects.empty()) {
    t0 = std::chrono::steady_clock::now();
    const resample::LiftResult lr = resample::lift_objects(*resampler, to_lift, opt.lift);
    for (size_t k = 0; k < lift_of.size(); ++k) {
      Work& w = objs[lift_of[k]];
      const auto& lo = lr.objects[k];
      if (!lo.ok) {
        w.rep.skipped.push_back("lift: " + lo.error);
        continue;
      }
      for (size_t sidx = 0; sidx < lo.samples.size(); ++sidx)
        if (lo.samples[sidx].ok) {
          w.mesh.V = lo.samples[sidx].mesh.V;
          w.mesh.F = lo.samples[sidx].mesh.F;
          w.R = lo.scene_poses[sidx].R;
          w.scale = lo.scene_poses[sidx].scale;
          w.t = lo.scene_poses[sidx].t;
          w.ok = true;
          w.rep.steps.push_back(fmt::format("lifted (sample {})", sidx));
          break;
        }
    }
    res.timings["lift"] = since(t0);
  }
  // Refined poses (e.g. FoundationPose; scene convention in the camera frame) replace the rotation.
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
      w.rep.steps.push_back("refined_pose");
    } catch (const std::exception& e) {
      w.rep.skipped.push_back(fmt::format("refined_pose: {}", e.what()));
    }
  }
  // ---- Alignment ----
  t0 = std::chrono::steady_clock::now();
  for (auto& w : objs) {
    if (!w.ok) continue;
    w.rep.s_before = w.scale.maxCoeff();
    w.rep.t_before = w.t;
    if (!opt.do_align) continue;
    AlignInput ai;
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
    const AlignResult ar = align_translation_scale(ai, opt.align);
    if (!ar.ok) {
      w.rep.skipped.push_back("align: " + ar.message + " (no valid depth: kept the lifted pose)");
      continue;
    }
    w.scale = ar.s * ai.shape;
    w.t = ar.t;
    w.rep.steps.push_back(fmt::format("aligned (start rho {})", ar.candidates[size_t(ar.best)].rho));
  }
  res.timings["align"] = since(t0);
  // ---- Planes ----
  t0 = std::chrono::steady_clock::now();
  Points all(0, 3);
  {
    std::vector<Vec3> v;
    for (size_t i = 0; i < pm.p.size(); i += 7)
      if (PointMap::valid(pm.p[i])) v.push_back(pm.p[i]);
    all.resize(Eigen::Index(v.size()), 3);
    for (size_t i = 0; i < v.size(); ++i) all.row(Eigen::Index(i)) = v[i].transpose();
  }
  res.planes = fit_planes(floor_pts, walls, all, Vec3::Zero(), opt.planes);
  res.timings["planes"] = since(t0);
  // ---- Tabletop ----
  t0 = std::chrono::steady_clock::now();
  for (auto& w : objs) {
    if (!w.ok || !opt.do_tabletop || !is_table_label(w.spec.label)) continue;
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
  // ---- Floor snap (second pass) ----
  if (opt.do_floor_snap) {
    std::vector<Points> resting;
    for (auto& w : objs)
      if (w.ok && w.spec.dof == physics::PoseDof::Free) resting.push_back(place(w.mesh.V, w.scale, w.R, w.t));
    const double d = snap_floor_to_meshes(res.planes, resting, opt.planes.max_floor_snap);
    if (d != 0) res.messages.push_back(fmt::format("floor snapped by {:+.4f} m along up to the lowest fitted-mesh vertex", d));
  }
  for (auto& m : res.planes.messages) res.messages.push_back(m);
  // ---- Compose the pre-simulation scene (world = OpenCV camera) ----
  physics::Scene sc;
  sc.camera = in.camera;
  sc.camera.R_world_cam = Mat3::Identity();
  sc.camera.t_world_cam = Vec3::Zero();
  sc.image_path = sfs::absolute(files.lift.image).string();
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
        physics::BaseBody b;
        b.id = w.spec.id;
        b.mesh_path = mp;
        b.scale = w.scale;
        b.R = w.R;
        b.t = w.t;
        sc.bases.push_back(b);
      } else {
        const std::string kp = (idir / "masks" / (w.spec.id + ".png")).string();
        write_mask(w.mask, kp);
        physics::SceneObject o;
        o.id = w.spec.id;
        o.label = w.spec.label;
        o.mesh_path = mp;
        o.mask_path = kp;
        o.scale = w.scale;
        o.R = w.R;
        o.t = w.t;
        o.dof = w.spec.dof;
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
  // ---- Probe ----
  if (opt.run_probe) {
    t0 = std::chrono::steady_clock::now();
    physics::ResampleFn fn;
    if (resampler) {
      resample::ProbeResamplerOptions ro;
      ro.seed = opt.lift.seed;
      ro.preprocess = opt.lift.preprocess;
      fn = resample::make_probe_resample_fn(*resampler, res.scene, ro);
    }
    res.probe = physics::run_probe(res.scene, opt.probe, (sfs::path(out_dir) / "probe").string(), fn);
    res.timings["probe"] = since(t0);
  }
  res.timings["total"] = since(t_all);
  // ---- Report ----
  json objs_j = json::array(), skipped = json::array();
  for (auto& r : res.objects) {
    objs_j.push_back(r.to_json());
    for (auto& s : r.skipped) skipped.push_back({{"object", r.id}, {"why", s}});
  }
  json planes = {{"up", vj(res.planes.up)}, {"up_source", res.planes.up_source}, {"fallback_floor", res.planes.fallback}};
  if (res.planes.floor)
    planes["floor"] = {{"point", vj(res.planes.floor->plane.point)}, {"normal", vj(res.planes.floor->plane.normal)},
                       {"inliers", res.planes.floor->plane.inliers}};
  json wj = json::array();
  for (auto& w : res.planes.walls)
    wj.push_back({{"id", w.id}, {"point", vj(w.plane.point)}, {"normal", vj(w.plane.normal)}, {"inliers", w.plane.inliers}});
  planes["walls"] = wj;
  const json rep = {{"frame", "world = the OpenCV camera of the photo (x right, y down, z forward, metres)"},
                    {"gravity", vj(-res.planes.up)},
                    {"planes", planes},
                    {"objects", objs_j},
                    {"skipped", skipped},
                    {"messages", res.messages},
                    {"seconds", res.timings},
                    {"pre_simulation_scene", "input/scene.json"},
                    {"probe_dir", opt.run_probe ? "probe" : ""}};
  fs::atomic_write((sfs::path(out_dir) / "reconstruct_report.json").string(), rep.dump(2) + "\n");
  return res;
}

}  // namespace simu::reconstruct
