// A reconstruction scored against a shape-world scene's ground truth in the GT world.
#include "pipeline/reconstruct/gt_compare.h"

#include <fmt/format.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <limits>

#include "common/error.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/solid_voxels.h"

namespace simu::reconstruct {

using physics::Camera;
using physics::Mat3;
using physics::PlacedShape;
using physics::Vec3;
using nlohmann::json;

namespace {

// A JSON value at `key` of `j`, or an error naming the file and the key.
const json& at(const json& j, const std::string& key, const std::string& what) {
  SIMU_CHECK(j.is_object() && j.contains(key), "{}: missing key '{}'", what, key);
  return j.at(key);
}

// Three numbers -> Vec3 (naming the key when malformed).
Vec3 vec3(const json& j, const std::string& what) {
  SIMU_CHECK(j.is_array() && j.size() == 3, "{}: expected 3 numbers", what);
  Vec3 v;
  for (int i = 0; i < 3; ++i) v[i] = j[i].get<double>();
  SIMU_CHECK(v.allFinite(), "{}: not finite", what);
  return v;
}

// Three rows of three numbers -> Mat3.
Mat3 mat3(const json& j, const std::string& what) {
  SIMU_CHECK(j.is_array() && j.size() == 3, "{}: expected a 3x3 matrix (3 rows)", what);
  Mat3 m;
  for (int r = 0; r < 3; ++r) m.row(r) = vec3(j[r], what).transpose();
  return m;
}

// A mean where an unset value counts 0 (null for no rows).
json mean_of(const std::vector<GtIouRow>& rows, std::optional<double> GtIouRow::*field) {
  if (rows.empty()) return nullptr;
  double s = 0;
  for (const auto& r : rows) s += (r.*field).value_or(0.0);
  return s / static_cast<double>(rows.size());
}

// An IoU cell of the table.
std::string cell(const std::optional<double>& v) { return v ? fmt::format("{:.3f}", *v) : std::string("-"); }

}  // namespace

WorldGt load_world_gt(const std::string& path) {
  std::ifstream f(path);
  SIMU_CHECK(f.good(), "{}: cannot open the ground truth (gt.json of `world scenes`)", path);
  json j;
  try {
    j = json::parse(f);
  } catch (const std::exception& e) {
    fail("{}: not valid JSON ({})", path, e.what());
  }
  WorldGt gt;
  gt.path = path;
  // The camera: intrinsics and its pose in the GT world.
  try {
    const json& c = at(j, "camera", path);
    gt.camera.fx = at(c, "fx", path + " camera").get<double>();
    gt.camera.fy = at(c, "fy", path + " camera").get<double>();
    gt.camera.cx = at(c, "cx", path + " camera").get<double>();
    gt.camera.cy = at(c, "cy", path + " camera").get<double>();
    gt.camera.width = at(c, "width", path + " camera").get<int>();
    gt.camera.height = at(c, "height", path + " camera").get<int>();
    gt.camera.R_world_cam = mat3(at(c, "R_world_cam", path + " camera"), path + " camera.R_world_cam");
    gt.camera.t_world_cam = vec3(at(c, "t_world_cam", path + " camera"), path + " camera.t_world_cam");
  } catch (const json::exception& e) {
    fail("{}: malformed camera ({})", path, e.what());
  }
  // The objects: canonical mesh and world pose.
  const auto dir = std::filesystem::path(path).parent_path();
  const json& objs = at(j, "objects", path);
  SIMU_CHECK(objs.is_array(), "{}: 'objects' is not a list", path);
  for (size_t i = 0; i < objs.size(); ++i) {
    const json& o = objs[i];
    const std::string what = fmt::format("{} objects[{}]", path, i);
    GtObject g;
    try {
      g.id = at(o, "id", what).get<std::string>();
      g.family = o.value("family", std::string());
      g.visible_fraction = o.value("visible_fraction", 1.0);
      g.shape.R = mat3(at(o, "R", what), what + ".R");
      g.shape.scale = vec3(at(o, "scale", what), what + ".scale");
      g.shape.t = vec3(at(o, "t", what), what + ".t");
      g.shape.canonical = physics::read_mesh((dir / at(o, "mesh", what).get<std::string>()).string());
    } catch (const json::exception& e) {
      fail("{}: malformed entry ({})", what, e.what());
    }
    SIMU_CHECK(!g.shape.canonical.empty(), "{}: the mesh of '{}' is empty", what, g.id);
    gt.objects.push_back(std::move(g));
  }
  return gt;
}

PlacedShape placed_in_gt_world(const physics::Mesh& canonical, const physics::SceneObject& o, const Camera& scene_camera,
                               const Camera& gt_camera) {
  // scene world -> camera (inverse of the scene camera's pose) -> GT world (the GT camera's pose).
  const Mat3 A = gt_camera.R_world_cam * scene_camera.R_world_cam.transpose();
  PlacedShape p;
  p.canonical = canonical;
  p.scale = o.scale;
  p.R = A * o.R;
  p.t = A * (o.t - scene_camera.t_world_cam) + gt_camera.t_world_cam;
  return p;
}

std::map<std::string, physics::Box3> gt_boxes_in_camera(const WorldGt& gt) {
  std::map<std::string, physics::Box3> boxes;
  const Mat3 Rt = gt.camera.R_world_cam.transpose();
  for (const auto& g : gt.objects) {
    const physics::Mesh w = g.shape.world();
    if (w.V.rows() == 0) continue;
    physics::Box3 b;
    b.min = Vec3::Constant(std::numeric_limits<double>::infinity());
    b.max = -b.min;
    for (Eigen::Index k = 0; k < w.V.rows(); ++k) {
      const Vec3 c = Rt * (Vec3(w.V.row(k).transpose()) - gt.camera.t_world_cam);
      b.min = b.min.cwiseMin(c);
      b.max = b.max.cwiseMax(c);
    }
    boxes[g.id] = b;
  }
  return boxes;
}

double world_iou(const PlacedShape& pred, const PlacedShape& gt, const physics::ShapeMetricsConfig& config) {
  const double gt_size = gt.size();
  SIMU_CHECK(gt_size > 0, "gt iou: the ground-truth mesh has no extent");
  SIMU_CHECK(pred.scale.allFinite() && pred.R.allFinite() && pred.t.allFinite(), "gt iou: the predicted pose is not finite");
  return physics::solid_iou(pred.world(), gt.world(), std::min(config.max_voxel, gt_size / config.voxels_across),
                            config.max_voxels)
      .iou;
}

physics::Scene settled_scene(const physics::Scene& scene, const json& probe_report, bool input) {
  physics::Scene s = scene;
  if (!probe_report.contains("objects") || !probe_report["objects"].is_array()) return s;
  const char* key = input ? "evaluation_input_pose" : "evaluation_pose";
  std::map<std::string, const json*> poses;
  for (const auto& o : probe_report["objects"])
    if (o.contains("id") && o.contains(key)) poses[o["id"].get<std::string>()] = &o[key];
  for (auto& o : s.objects) {
    const auto it = poses.find(o.id);
    if (it == poses.end()) continue;
    const std::string what = fmt::format("probe report object '{}' {}", o.id, key);
    try {
      o.R = mat3(it->second->at("R"), what + ".R");
      o.t = vec3(it->second->at("t"), what + ".t");
    } catch (const json::exception& e) {
      fail("{}: malformed ({})", what, e.what());
    }
  }
  return s;
}

std::map<std::string, ProbeOutcome> probe_outcomes(const json& report) {
  std::map<std::string, ProbeOutcome> out;
  if (!report.is_object() || !report.contains("objects") || !report["objects"].is_array()) return out;
  for (const json& o : report["objects"]) {
    if (!o.is_object() || !o.contains("id") || !o["id"].is_string()) continue;
    ProbeOutcome p;
    p.branch = o.value("branch", std::string());
    if (o.contains("resample") && o["resample"].is_object()) p.resampled = o["resample"].value("resampled", false);
    p.reverted = o.value("reverted", false);
    if (o.contains("flags") && o["flags"].is_array())
      for (const json& f : o["flags"]) p.forced = p.forced || f == "forced_resample";
    out[o["id"].get<std::string>()] = p;
  }
  return out;
}

std::vector<GtIouRow> compare_with_gt(const physics::Scene& before, const physics::Scene& after,
                                      const std::map<std::string, ProbeOutcome>& outcomes, const WorldGt& gt,
                                      const physics::ShapeMetricsConfig& config) {
  std::vector<GtIouRow> rows;
  for (const GtObject& g : gt.objects) {
    GtIouRow r;
    r.id = g.id;
    r.family = g.family;
    r.visible_fraction = g.visible_fraction;
    if (auto it = outcomes.find(g.id); it != outcomes.end()) r.probe = it->second;
    // The IoU of the object in one scene (unset, with a note, when it is not there or cannot be scored).
    auto score = [&](const physics::Scene& s, const char* which) -> std::optional<double> {
      const int k = s.find_object(g.id);
      if (k < 0) {
        r.note += fmt::format("{}not in the {} scene", r.note.empty() ? "" : "; ", which);
        return std::nullopt;
      }
      const physics::SceneObject& o = s.objects[k];
      try {
        SIMU_CHECK(o.error.empty(), "{}", o.error);
        const physics::Mesh m = physics::read_mesh(o.mesh_path);
        return world_iou(placed_in_gt_world(m, o, s.camera, gt.camera), g.shape, config);
      } catch (const std::exception& e) {
        r.note += fmt::format("{}{}: {}", r.note.empty() ? "" : "; ", which, e.what());
        return std::nullopt;
      }
    };
    r.before = score(before, "input");
    r.after = score(after, "final");
    rows.push_back(std::move(r));
  }
  return rows;
}

json gt_rows_json(const std::vector<GtIouRow>& rows, const std::string& gt_path) {
  json objs = json::array();
  for (const auto& r : rows)
    objs.push_back({{"id", r.id},
                    {"family", r.family},
                    {"visible_fraction", r.visible_fraction},
                    {"branch", r.probe.branch},
                    {"resampled", r.probe.resampled},
                    {"forced_resample", r.probe.forced},
                    {"reverted", r.probe.reverted},
                    {"gt_iou_before", r.before ? json(*r.before) : json(nullptr)},
                    {"gt_iou_after", r.after ? json(*r.after) : json(nullptr)},
                    {"note", r.note}});
  return {{"gt", gt_path},
          {"frame", "the ground truth's world (gt.json camera pose); voxel IoU of filled occupancies"},
          {"objects", objs},
          {"n", rows.size()},
          {"mean_before", mean_of(rows, &GtIouRow::before)},
          {"mean_after", mean_of(rows, &GtIouRow::after)}};
}

std::string format_gt_table(const std::vector<GtIouRow>& rows) {
  std::string s = fmt::format("  {:<22} {:<11} {:>7}  {:<30} {:>10} {:>10} {:>7}\n", "object", "family", "visible",
                              "probe", "IoU before", "IoU after", "change");
  for (const auto& r : rows) {
    // What the probe did, in words.
    std::string did = r.probe.branch.empty() ? "-" : r.probe.branch;
    if (r.probe.forced) did += ", forced";
    if (r.probe.branch == "resample") did += r.probe.resampled ? " (replaced)" : " (kept input)";
    if (r.probe.reverted) did += ", reverted";
    const std::string change = r.before && r.after ? fmt::format("{:+.3f}", *r.after - *r.before) : "-";
    s += fmt::format("  {:<22} {:<11} {:>6.0f}%  {:<30} {:>10} {:>10} {:>7}\n", r.id, r.family, 100 * r.visible_fraction,
                     did, cell(r.before), cell(r.after), change);
    if (!r.note.empty()) s += fmt::format("      note: {}\n", r.note);
  }
  const json mb = mean_of(rows, &GtIouRow::before), ma = mean_of(rows, &GtIouRow::after);
  if (!rows.empty())
    s += fmt::format("  {:<22} {:<11} {:>7}  {:<30} {:>10.3f} {:>10.3f} {:>+7.3f}\n", fmt::format("mean ({} objects)", rows.size()),
                     "", "", "", mb.get<double>(), ma.get<double>(), ma.get<double>() - mb.get<double>());
  return s;
}

}  // namespace simu::reconstruct
