// The reconstruct front end's inputs (files -> ReconstructInputs, the sidecar) and its report.
#include "pipeline/reconstruct/run_detail.h"

#include "common/error.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <filesystem>
#include <fstream>

namespace simu::reconstruct {

namespace sfs = std::filesystem;
using nlohmann::json;

namespace detail {

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

json report_json(const ReconstructResult& res, bool ran_probe) {
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
  planes["first_pass"] = {{"up", vj(res.planes_first.up)}, {"up_source", res.planes_first.up_source}};
  planes["mesh_up"] = vj(res.mesh_up);
  planes["floor_snap_m"] = res.floor_snap;
  return {{"frame", "world = the OpenCV camera of the photo (x right, y down, z forward, metres)"},
          {"gravity", vj(-res.planes.up)},
          {"planes", planes},
          {"objects", objs_j},
          {"skipped", skipped},
          {"messages", res.messages},
          {"seconds", res.timings},
          {"pre_simulation_scene", "input/scene.json"},
          {"probe_dir", ran_probe ? "probe" : ""}};
}

}  // namespace detail

namespace {
std::string resolve(const std::string& p, const std::string& base) {
  if (p.empty() || sfs::path(p).is_absolute()) return p;
  return (sfs::path(base) / p).lexically_normal().string();
}
}  // namespace

json ObjectReport::to_json() const {
  return {{"id", id},          {"label", label},          {"role", role},
          {"used", used},      {"steps", steps},          {"skipped", skipped},
          {"scale_before", s_before}, {"scale_after", s_after}, {"t_before", detail::vj(t_before)},
          {"t_after", detail::vj(t_after)}, {"wall", wall}};
}

Vec3 parse_axis(const std::string& axis, const std::string& what) {
  SIMU_CHECK(axis.size() == 2 && (axis[0] == '+' || axis[0] == '-') && axis[1] >= 'x' && axis[1] <= 'z',
             "{}: axis '{}' (expected +x, -x, +y, -y, +z or -z)", what, axis);
  Vec3 v = Vec3::Zero();
  v[axis[1] - 'x'] = axis[0] == '+' ? 1.0 : -1.0;
  return v;
}

std::vector<ObjectSpec> read_sidecar(const std::string& path, std::vector<std::string>* problems) {
  const json j = detail::read_json_file(path);
  const json& arr = j.is_object() ? j.value("objects", json()) : j;
  SIMU_CHECK(arr.is_array(), "{}: expected {{\"objects\": [...]}} or a list of objects", path);
  const std::string base = sfs::path(path).parent_path().string();
  std::vector<ObjectSpec> out;
  static const std::vector<std::string> known = {"id",   "label_value", "mask", "label",        "role",    "dof", "pins",
                                                 "base", "mesh",        "pose", "refined_pose", "up_axis", "wall",
                                                 "fit"};
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
    s.fit = e.value("fit", std::string("lift"));
    SIMU_CHECK(s.fit == "lift" || s.fit == "box", "{}: fit '{}' (lift, box)", what, s.fit);
    SIMU_CHECK(s.fit == "lift" || (s.base && s.role == "object"), "{}: fit 'box' is for fixed bases: it needs \"base\": true",
               what);
    s.mesh = resolve(e.value("mesh", std::string()), base);
    s.pose = resolve(e.value("pose", std::string()), base);
    s.refined_pose = resolve(e.value("refined_pose", std::string()), base);
    SIMU_CHECK(s.mesh.empty() == s.pose.empty(), "{}: mesh and pose come together (bring your own lift)", what);
    SIMU_CHECK(s.fit == "lift" || s.mesh.empty(), "{}: fit 'box' and a brought mesh exclude each other", what);
    s.up_axis = e.value("up_axis", std::string());
    if (!s.up_axis.empty()) parse_axis(s.up_axis, what + ": up_axis");
    s.wall = e.value("wall", std::string());
    if (!s.wall.empty() && s.dof == physics::PoseDof::Free)
      problems->push_back(fmt::format("{}: 'wall' given for a free object: ignored (only hanging objects hang)", what));
    out.push_back(s);
  }
  return out;
}

ReconstructInputs load_reconstruct_inputs(const ReconstructFiles& files) {
  ReconstructInputs in;
  in.lift = resample::load_lift_inputs(files.lift);
  if (!files.sidecar.empty()) in.specs = read_sidecar(files.sidecar, &in.messages);
  in.sidecar_name = files.sidecar;
  in.image_path = sfs::absolute(files.lift.image).string();
  return in;
}

}  // namespace simu::reconstruct
