// Scene file parsing and writing (format: docs/scene_format.md).
#include "pipeline/physics/scene.h"

#include <cmath>
#include <filesystem>
#include <set>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"

namespace simu::physics {

namespace stdfs = std::filesystem;
using nlohmann::json;

bool Camera::valid() const {
  return std::isfinite(fx) && std::isfinite(fy) && fx > 0 && fy > 0 && width > 0 && height > 0 &&
         std::isfinite(cx) && std::isfinite(cy) && R_world_cam.allFinite() && t_world_cam.allFinite();
}

const char* to_string(PoseDof d) {
  switch (d) {
    case PoseDof::Free: return "free";
    case PoseDof::PointAnchored: return "point_anchored";
    case PoseDof::LineAnchored: return "line_anchored";
  }
  return "free";
}

std::optional<PoseDof> parse_pose_dof(const std::string& s) {
  if (s == "free") return PoseDof::Free;
  if (s == "point_anchored" || s == "point-anchored") return PoseDof::PointAnchored;
  if (s == "line_anchored" || s == "line-anchored") return PoseDof::LineAnchored;
  return std::nullopt;
}

int pin_count(PoseDof d) { return d == PoseDof::Free ? 0 : (d == PoseDof::PointAnchored ? 1 : 2); }

int Scene::find_object(const std::string& id) const {
  for (size_t i = 0; i < objects.size(); ++i)
    if (objects[i].id == id) return static_cast<int>(i);
  return -1;
}

Mesh transform_mesh(const Mesh& canonical, const Mat3& linear, const Vec3& t) {
  Mesh m = canonical;
  for (Eigen::Index i = 0; i < m.V.rows(); ++i) m.V.row(i) = (linear * canonical.V.row(i).transpose() + t).transpose();
  return m;
}

Mesh world_mesh(const Mesh& canonical, const SceneObject& o) { return transform_mesh(canonical, o.linear(), o.t); }

namespace {

// Reads a 3-vector (JSON array of 3 numbers); throws naming `what`.
Vec3 read_vec3(const json& j, const std::string& what) {
  SIMU_CHECK(j.is_array() && j.size() == 3, "{}: expected an array of 3 numbers, got {}", what, j.dump());
  Vec3 v;
  for (int i = 0; i < 3; ++i) {
    SIMU_CHECK(j[i].is_number(), "{}: element {} is not a number (got {})", what, i, j[i].dump());
    v[i] = j[i].get<double>();
  }
  SIMU_CHECK(v.allFinite(), "{}: non-finite value", what);
  return v;
}

// Reads a 3x3 matrix as 3 rows of 3 numbers (or 9 numbers row-major).
Mat3 read_mat3(const json& j, const std::string& what) {
  Mat3 m;
  if (j.is_array() && j.size() == 9) {
    for (int k = 0; k < 9; ++k) {
      SIMU_CHECK(j[k].is_number(), "{}: element {} is not a number", what, k);
      m(k / 3, k % 3) = j[k].get<double>();
    }
  } else {
    SIMU_CHECK(j.is_array() && j.size() == 3, "{}: expected 3 rows of 3 numbers, got {}", what, j.dump());
    for (int r = 0; r < 3; ++r) m.row(r) = read_vec3(j[r], fmt::format("{}[{}]", what, r)).transpose();
  }
  SIMU_CHECK(m.allFinite(), "{}: non-finite value", what);
  return m;
}

// Checks that R is a rotation (orthonormal, det +1) within 1e-3 and re-orthonormalises it.
Mat3 checked_rotation(const Mat3& R, const std::string& what) {
  const double orth = (R.transpose() * R - Mat3::Identity()).cwiseAbs().maxCoeff();
  SIMU_CHECK(orth < 1e-3 && R.determinant() > 0, "{}: not a rotation (|R^T R - I| = {:.3g}, det = {:.3g})", what, orth,
             R.determinant());
  Eigen::JacobiSVD<Mat3> svd(R, Eigen::ComputeFullU | Eigen::ComputeFullV);
  return svd.matrixU() * svd.matrixV().transpose();
}

// Scale: a positive number or 3 positive numbers.
Vec3 read_scale(const json& j, const std::string& what) {
  Vec3 s;
  if (j.is_number()) {
    s.setConstant(j.get<double>());
  } else {
    s = read_vec3(j, what);
  }
  SIMU_CHECK(s.allFinite() && s.minCoeff() > 0, "{}: scale must be positive and finite, got [{}, {}, {}]", what, s[0], s[1],
             s[2]);
  return s;
}

std::string resolve(const std::string& base_dir, const std::string& p) {
  if (p.empty()) return p;
  stdfs::path path(p);
  if (path.is_absolute()) return path.lexically_normal().string();
  return (stdfs::path(base_dir) / path).lexically_normal().string();
}

std::string relativize(const std::string& out_dir, const std::string& p) {
  if (p.empty() || out_dir.empty()) return p;
  const auto rel = stdfs::path(p).lexically_relative(stdfs::absolute(out_dir).lexically_normal());
  if (rel.empty() || *rel.begin() == "..") return p;
  return rel.string();
}

Plane read_plane(const json& j, const std::string& what) {
  SIMU_CHECK(j.is_object(), "{}: expected an object with point and normal", what);
  Plane p;
  if (j.contains("id")) p.id = j.at("id").get<std::string>();
  SIMU_CHECK(j.contains("normal"), "{}: missing key 'normal'", what);
  p.normal = read_vec3(j.at("normal"), what + ".normal");
  SIMU_CHECK(p.normal.norm() > 1e-9, "{}.normal: zero vector", what);
  p.normal.normalize();
  if (j.contains("point")) {
    p.point = read_vec3(j.at("point"), what + ".point");
  } else {
    // n.x + offset = 0 form.
    SIMU_CHECK(j.contains("offset"), "{}: needs 'point' or 'offset'", what);
    p.point = -j.at("offset").get<double>() * p.normal;
  }
  return p;
}

json plane_json(const Plane& p) {
  json j;
  if (!p.id.empty()) j["id"] = p.id;
  j["point"] = {p.point[0], p.point[1], p.point[2]};
  j["normal"] = {p.normal[0], p.normal[1], p.normal[2]};
  return j;
}

json vec_json(const Vec3& v) { return json::array({v[0], v[1], v[2]}); }
json mat_json(const Mat3& m) {
  json j = json::array();
  for (int r = 0; r < 3; ++r) j.push_back(json::array({m(r, 0), m(r, 1), m(r, 2)}));
  return j;
}
json scale_json(const Vec3& s) {
  if (s[0] == s[1] && s[1] == s[2]) return s[0];
  return vec_json(s);
}

const std::set<std::string> kObjectKeys = {"id", "label", "mesh", "mask", "scale", "R", "t", "dof", "wall", "density", "gt_box"};
const std::set<std::string> kTopKeys = {"format", "image", "depth", "camera", "gravity", "gravity_magnitude", "floor", "walls", "bases", "objects"};

SceneObject read_object(const json& j, const std::string& base_dir, const std::string& what) {
  SceneObject o;
  if (!j.is_object()) {
    o.error = fmt::format("{}: expected an object, got {}", what, j.dump().substr(0, 80));
    return o;
  }
  if (j.contains("id") && j["id"].is_string()) o.id = j["id"].get<std::string>();
  // Each field below may throw simu::Error; it becomes the object's error, never the scene's.
  try {
    SIMU_CHECK(!o.id.empty(), "{}: missing string key 'id'", what);
    if (j.contains("label")) o.label = j.at("label").get<std::string>();
    SIMU_CHECK(j.contains("mesh") && j["mesh"].is_string(), "{}: missing string key 'mesh'", what);
    o.mesh_path = resolve(base_dir, j["mesh"].get<std::string>());
    if (j.contains("mask") && !j["mask"].is_null()) o.mask_path = resolve(base_dir, j["mask"].get<std::string>());
    if (j.contains("scale")) o.scale = read_scale(j["scale"], what + ".scale");
    if (j.contains("R")) o.R = checked_rotation(read_mat3(j["R"], what + ".R"), what + ".R");
    SIMU_CHECK(j.contains("t"), "{}: missing key 't'", what);
    o.t = read_vec3(j["t"], what + ".t");
    if (j.contains("dof")) {
      const auto d = parse_pose_dof(j["dof"].get<std::string>());
      SIMU_CHECK(d.has_value(), "{}.dof: expected free, point_anchored or line_anchored, got {}", what, j["dof"].dump());
      o.dof = *d;
    }
    if (j.contains("wall")) o.wall_id = j["wall"].get<std::string>();
    if (j.contains("density")) {
      o.density = j["density"].get<double>();
      SIMU_CHECK(std::isfinite(o.density) && o.density > 0, "{}.density: must be positive", what);
    }
    if (j.contains("gt_box") && !j["gt_box"].is_null()) {
      Box3 b;
      b.min = read_vec3(j["gt_box"].at("min"), what + ".gt_box.min");
      b.max = read_vec3(j["gt_box"].at("max"), what + ".gt_box.max");
      SIMU_CHECK((b.max - b.min).minCoeff() >= 0, "{}.gt_box: min > max", what);
      o.gt_box = b;
    }
  } catch (const std::exception& e) {
    o.error = e.what();
  }
  for (auto it = j.begin(); it != j.end(); ++it)
    if (!kObjectKeys.count(it.key())) o.extra[it.key()] = it.value();
  return o;
}

}  // namespace

// One function on purpose (~90 lines): it reads the top-level keys of docs/scene_format.md in the
// document's order, each with its own check and error naming the key.
Scene scene_from_json(const json& j, const std::string& base_dir, const std::string& what) {
  SIMU_CHECK(j.is_object(), "{}: top level must be a JSON object", what);
  Scene s;
  try {
    if (j.contains("image") && !j["image"].is_null()) s.image_path = resolve(base_dir, j["image"].get<std::string>());
    if (j.contains("depth") && !j["depth"].is_null()) s.depth_path = resolve(base_dir, j["depth"].get<std::string>());
    // Camera: intrinsics, image size, optional pose.
    if (j.contains("camera")) {
      const auto& c = j["camera"];
      SIMU_CHECK(c.is_object(), "{}.camera: expected an object", what);
      for (const char* k : {"fx", "fy", "cx", "cy", "width", "height"})
        SIMU_CHECK(c.contains(k), "{}.camera: missing key '{}'", what, k);
      s.camera.fx = c["fx"].get<double>();
      s.camera.fy = c["fy"].get<double>();
      s.camera.cx = c["cx"].get<double>();
      s.camera.cy = c["cy"].get<double>();
      s.camera.width = c["width"].get<int>();
      s.camera.height = c["height"].get<int>();
      if (c.contains("R_world_cam")) s.camera.R_world_cam = checked_rotation(read_mat3(c["R_world_cam"], what + ".camera.R_world_cam"), what + ".camera.R_world_cam");
      if (c.contains("t_world_cam")) s.camera.t_world_cam = read_vec3(c["t_world_cam"], what + ".camera.t_world_cam");
      SIMU_CHECK(s.camera.valid(), "{}.camera: intrinsics must be positive and finite", what);
    }
    // Gravity direction (normalised) and magnitude.
    if (j.contains("gravity")) {
      s.gravity = read_vec3(j["gravity"], what + ".gravity");
      SIMU_CHECK(s.gravity.norm() > 1e-9, "{}.gravity: zero vector", what);
      s.gravity.normalize();
    }
    if (j.contains("gravity_magnitude")) {
      SIMU_CHECK(j["gravity_magnitude"].is_number(), "{}.gravity_magnitude: expected a number (m/s^2), got {}", what,
                 j["gravity_magnitude"].dump());
      s.gravity_magnitude = j["gravity_magnitude"].get<double>();
      // Positive and physical: 0 leaves nothing to measure, a negative one is gravity reversed (give the
      // direction in 'gravity'), and beyond 1000 m/s^2 (~100 g) the 1/480 s step no longer resolves a fall.
      SIMU_CHECK(std::isfinite(s.gravity_magnitude) && s.gravity_magnitude > 0 && s.gravity_magnitude <= 1000,
                 "{}.gravity_magnitude: got {}, expected a magnitude in (0, 1000] m/s^2 (Earth: 9.81; the direction "
                 "goes in 'gravity')", what, s.gravity_magnitude);
    }
    if (j.contains("floor") && !j["floor"].is_null()) s.floor = read_plane(j["floor"], what + ".floor");
    if (j.contains("walls")) {
      SIMU_CHECK(j["walls"].is_array(), "{}.walls: expected an array", what);
      for (size_t k = 0; k < j["walls"].size(); ++k) {
        Plane p = read_plane(j["walls"][k], fmt::format("{}.walls[{}]", what, k));
        if (p.id.empty()) p.id = fmt::format("wall{}", k);
        s.walls.push_back(p);
      }
    }
  } catch (const nlohmann::json::exception& e) {
    fail("{}: malformed value ({})", what, e.what());
  }
  // Fixed bases: a bad entry is kept with its error (skipped by the probe).
  if (j.contains("bases")) {
    SIMU_CHECK(j["bases"].is_array(), "{}.bases: expected an array", what);
    for (size_t k = 0; k < j["bases"].size(); ++k) {
      const auto& b = j["bases"][k];
      const std::string w = fmt::format("{}.bases[{}]", what, k);
      BaseBody base;
      try {
        SIMU_CHECK(b.is_object(), "{}: expected an object", w);
        base.id = b.value("id", fmt::format("base{}", k));
        SIMU_CHECK(b.contains("mesh"), "{}: missing key 'mesh'", w);
        base.mesh_path = resolve(base_dir, b["mesh"].get<std::string>());
        if (b.contains("scale")) base.scale = read_scale(b["scale"], w + ".scale");
        if (b.contains("R")) base.R = checked_rotation(read_mat3(b["R"], w + ".R"), w + ".R");
        if (b.contains("t")) base.t = read_vec3(b["t"], w + ".t");
      } catch (const std::exception& e) {
        base.error = e.what();
      }
      s.bases.push_back(base);
    }
  }
  // Objects: each entry parsed on its own.
  if (j.contains("objects")) {
    SIMU_CHECK(j["objects"].is_array(), "{}.objects: expected an array", what);
    std::set<std::string> seen;
    for (size_t k = 0; k < j["objects"].size(); ++k) {
      SceneObject o = read_object(j["objects"][k], base_dir, fmt::format("{}.objects[{}]", what, k));
      if (o.id.empty()) o.id = fmt::format("object{}", k);
      if (!seen.insert(o.id).second) {
        if (o.error.empty()) o.error = fmt::format("{}.objects[{}]: duplicate id '{}'", what, k, o.id);
        o.id = fmt::format("{}#{}", o.id, k);
      }
      s.objects.push_back(std::move(o));
    }
  }
  for (auto it = j.begin(); it != j.end(); ++it)
    if (!kTopKeys.count(it.key())) s.extra[it.key()] = it.value();
  return s;
}

json scene_to_json(const Scene& s, const std::string& out_dir) {
  json j;
  j["format"] = "simuscene/1";
  if (!s.image_path.empty()) j["image"] = relativize(out_dir, s.image_path);
  if (!s.depth_path.empty()) j["depth"] = relativize(out_dir, s.depth_path);
  if (s.camera.valid()) {
    json c = {{"fx", s.camera.fx}, {"fy", s.camera.fy}, {"cx", s.camera.cx}, {"cy", s.camera.cy},
              {"width", s.camera.width}, {"height", s.camera.height}};
    if (!s.camera.R_world_cam.isIdentity(0)) c["R_world_cam"] = mat_json(s.camera.R_world_cam);
    if (!s.camera.t_world_cam.isZero(0)) c["t_world_cam"] = vec_json(s.camera.t_world_cam);
    j["camera"] = c;
  }
  j["gravity"] = vec_json(s.gravity);
  j["gravity_magnitude"] = s.gravity_magnitude;
  if (s.floor) j["floor"] = plane_json(*s.floor);
  j["walls"] = json::array();
  for (const auto& w : s.walls) j["walls"].push_back(plane_json(w));
  j["bases"] = json::array();
  for (const auto& b : s.bases) {
    if (!b.error.empty()) continue;
    j["bases"].push_back({{"id", b.id}, {"mesh", relativize(out_dir, b.mesh_path)}, {"scale", scale_json(b.scale)},
                          {"R", mat_json(b.R)}, {"t", vec_json(b.t)}});
  }
  j["objects"] = json::array();
  for (const auto& o : s.objects) {
    json e = o.extra.is_object() ? o.extra : json::object();
    e["id"] = o.id;
    if (!o.label.empty()) e["label"] = o.label;
    e["mesh"] = relativize(out_dir, o.mesh_path);
    if (!o.mask_path.empty()) e["mask"] = relativize(out_dir, o.mask_path);
    e["scale"] = scale_json(o.scale);
    e["R"] = mat_json(o.R);
    e["t"] = vec_json(o.t);
    e["dof"] = to_string(o.dof);
    if (!o.wall_id.empty()) e["wall"] = o.wall_id;
    e["density"] = o.density;
    if (o.gt_box) e["gt_box"] = {{"min", vec_json(o.gt_box->min)}, {"max", vec_json(o.gt_box->max)}};
    j["objects"].push_back(e);
  }
  if (s.extra.is_object())
    for (auto it = s.extra.begin(); it != s.extra.end(); ++it) j[it.key()] = it.value();
  return j;
}

Scene load_scene(const std::string& path) {
  const std::string text = fs::read_file(path);
  json j;
  try {
    j = json::parse(text);
  } catch (const json::exception& e) {  // parse_error, and out_of_range for a number like 1E2682402853032
    fail_hint("see docs/scene_format.md", "{}: not valid JSON ({})", path, e.what());
  }
  const auto dir = stdfs::absolute(stdfs::path(path)).parent_path().string();
  Scene s = scene_from_json(j, dir, path);
  s.path = path;
  return s;
}

void save_scene(const Scene& s, const std::string& path) {
  const auto dir = stdfs::absolute(stdfs::path(path)).parent_path().string();
  fs::atomic_write(path, scene_to_json(s, dir).dump(2) + "\n");
}

}  // namespace simu::physics
