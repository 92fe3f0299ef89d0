// Synthetic scenes on disk: the probe scene of a synthetic scene, the scene directory writer and reader,
// OBJ writing.
#include "pipeline/physics/synthetic.h"


#include "common/error.h"
#include "common/fs.h"
#include "pipeline/physics/camera.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/metrics.h"
#include "pipeline/physics/overlay.h"
#include "pipeline/physics/probe.h"

#include <Eigen/Geometry>

#include <cmath>
#include <filesystem>
#include <fmt/format.h>
#include <limits>
#include <sstream>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#endif

namespace simu::physics {

namespace {
// Places a canonical mesh in the world: x = R (s .* v) + t.
Mesh place(const Mesh& m, const Vec3& s, const Mat3& R, const Vec3& t) { return transform_mesh(m, R * s.asDiagonal(), t); }
nlohmann::json mat_json(const Mat3& R) {
  return nlohmann::json::array({{R(0, 0), R(0, 1), R(0, 2)}, {R(1, 0), R(1, 1), R(1, 2)}, {R(2, 0), R(2, 1), R(2, 2)}});
}
nlohmann::json vec_json(const Vec3& v) { return nlohmann::json::array({v.x(), v.y(), v.z()}); }
}  // namespace

void write_obj(const std::string& path, const Mesh& m) {
  std::ostringstream os;
  os.precision(9);
  os << "# simuscene synthetic mesh\n";
  for (Eigen::Index i = 0; i < m.V.rows(); ++i) os << "v " << m.V(i, 0) << ' ' << m.V(i, 1) << ' ' << m.V(i, 2) << '\n';
  for (Eigen::Index f = 0; f < m.F.rows(); ++f)
    os << "f " << m.F(f, 0) + 1 << ' ' << m.F(f, 1) + 1 << ' ' << m.F(f, 2) + 1 << '\n';
  const auto parent = std::filesystem::path(path).parent_path();
  if (!parent.empty()) std::filesystem::create_directories(parent);
  simu::fs::atomic_write(path, os.str());
}

Scene to_probe_scene(const SyntheticScene& s, const std::string& dir) {
  namespace sfs = std::filesystem;
  Scene sc;
  sc.path = (sfs::path(dir) / "scene.json").string();
  sc.image_path = (sfs::path(dir) / "rgb.png").string();
  if (!s.depth.empty()) sc.depth_path = (sfs::path(dir) / "depth.png").string();
  sc.camera = s.camera;
  sc.gravity = s.gravity;
  sc.floor = s.floor;
  sc.walls = s.walls;
  for (const auto& b : s.bases) {
    BaseBody bb;
    bb.id = b.id;
    bb.mesh_path = (sfs::path(dir) / "meshes" / (b.id + ".obj")).string();
    bb.scale = b.scale, bb.R = b.R, bb.t = b.t;
    sc.bases.push_back(bb);
  }
  for (const auto& o : s.objects) {
    SceneObject so;
    so.id = o.id;
    so.label = o.label;
    so.mesh_path = (sfs::path(dir) / "meshes" / (o.id + ".obj")).string();
    so.mask_path = (sfs::path(dir) / "masks" / (o.id + ".png")).string();
    so.scale = o.pred_scale, so.R = o.pred_R, so.t = o.pred_t;
    so.dof = o.dof;
    so.wall_id = o.wall_id;
    so.gt_box = o.gt_box;
    nlohmann::json syn;
    syn["error"] = to_string(o.error);
    syn["magnitude"] = o.magnitude;
    if (o.dof == PoseDof::Free) syn["expected_branch"] = to_string(expected_branch(o.error));
    syn["support_y"] = o.support_y;
    syn["gt"] = {{"mesh", "meshes/" + o.id + "_gt.obj"},
                 {"scale", vec_json(o.gt_scale)},
                 {"R", mat_json(o.gt_R)},
                 {"t", vec_json(o.gt_t)}};
    so.extra["synthetic"] = syn;
    sc.objects.push_back(so);
  }
  sc.extra["synthetic_layout"] = s.layout;
  return sc;
}

void write_scene_dir(const SyntheticScene& s, const std::string& dir_in) {
  namespace sfs = std::filesystem;
  // Absolute, so that the scene file's paths are written relative to it.
  const std::string dir = sfs::absolute(dir_in).lexically_normal().string();
  sfs::create_directories(sfs::path(dir) / "meshes");
  sfs::create_directories(sfs::path(dir) / "masks");
  for (const auto& b : s.bases) write_obj((sfs::path(dir) / "meshes" / (b.id + ".obj")).string(), b.mesh);
  for (const auto& o : s.objects) {
    write_obj((sfs::path(dir) / "meshes" / (o.id + ".obj")).string(), o.pred_mesh);
    write_obj((sfs::path(dir) / "meshes" / (o.id + "_gt.obj")).string(), o.gt_mesh);
    write_mask((sfs::path(dir) / "masks" / (o.id + ".png")).string(), o.modal_mask);
  }
#ifdef SIMU_HAVE_OPENCV
  // A flat-shaded picture of the ground truth (labels coloured, darker with depth) as the "image".
  {
    const LabelImage img = render_truth_labels(s);
    cv::Mat rgb(s.camera.height, s.camera.width, CV_8UC3, cv::Scalar(200, 200, 200));
    for (int r = 0; r < img.height; ++r)
      for (int c = 0; c < img.width; ++c) {
        const int l = img.label[size_t(r) * img.width + c];
        if (l < 0) continue;
        const double shade = std::clamp(1.3 - 0.2 * img.depth[size_t(r) * img.width + c], 0.4, 1.0);
        std::array<uint8_t, 3> col = l < int(s.bases.size()) ? std::array<uint8_t, 3>{60, 100, 140}
                                                             : overlay_color(l - int(s.bases.size()));
        rgb.at<cv::Vec3b>(r, c) = cv::Vec3b(uint8_t(col[0] * shade), uint8_t(col[1] * shade), uint8_t(col[2] * shade));
      }
    std::vector<uchar> buf;
    cv::imencode(".png", rgb, buf);
    simu::fs::atomic_write((sfs::path(dir) / "rgb.png").string(),
                           std::string_view(reinterpret_cast<const char*>(buf.data()), buf.size()));
    if (!s.depth.empty()) {
      cv::Mat d(s.camera.height, s.camera.width, CV_16U);
      for (int r = 0; r < d.rows; ++r)
        for (int c = 0; c < d.cols; ++c) {
          const float z = s.depth[size_t(r) * d.cols + c];
          d.at<uint16_t>(r, c) = std::isfinite(z) ? uint16_t(std::min(65535.0, std::round(z * 1000.0))) : 0;
        }
      cv::imencode(".png", d, buf);
      simu::fs::atomic_write((sfs::path(dir) / "depth.png").string(),
                             std::string_view(reinterpret_cast<const char*>(buf.data()), buf.size()));
    }
  }
#endif
  save_scene(to_probe_scene(s, dir), (sfs::path(dir) / "scene.json").string());
}

SyntheticScene load_synthetic_scene(const std::string& scene_json) {
  namespace sfs = std::filesystem;
  const Scene sc = load_scene(scene_json);
  const sfs::path dir = sfs::absolute(scene_json).parent_path();
  SyntheticScene s;
  s.name = dir.filename().string();
  s.layout = sc.extra.value("synthetic_layout", std::string());
  s.camera = sc.camera;
  s.gravity = sc.gravity;
  SIMU_CHECK(sc.floor.has_value(), "{}: a synthetic scene needs a floor", scene_json);
  s.floor = *sc.floor;
  s.walls = sc.walls;
  for (const BaseBody& b : sc.bases) {
    SIMU_CHECK(b.error.empty(), "{}: base {}: {}", scene_json, b.id, b.error);
    SyntheticBase sb;
    sb.id = b.id, sb.mesh = read_mesh(b.mesh_path), sb.scale = b.scale, sb.R = b.R, sb.t = b.t;
    s.bases.push_back(std::move(sb));
  }
  auto vec = [&](const nlohmann::json& j, const std::string& what) {
    SIMU_CHECK(j.is_array() && j.size() == 3, "{}: {} is not a 3-vector", scene_json, what);
    return Vec3(j[0].get<double>(), j[1].get<double>(), j[2].get<double>());
  };
  for (const SceneObject& so : sc.objects) {
    SIMU_CHECK(so.error.empty(), "{}: object {}: {}", scene_json, so.id, so.error);
    SIMU_CHECK(so.extra.contains("synthetic"), "{}: object {} has no \"synthetic\" record", scene_json, so.id);
    const nlohmann::json& syn = so.extra["synthetic"];
    const std::string what = "object " + so.id + ".synthetic";
    SyntheticObject o;
    o.id = so.id, o.label = so.label, o.dof = so.dof, o.wall_id = so.wall_id;
    o.pred_mesh = read_mesh(so.mesh_path);
    o.pred_scale = so.scale, o.pred_R = so.R, o.pred_t = so.t;
    const auto err = parse_injected_error(syn.value("error", std::string("none")));
    SIMU_CHECK(err.has_value(), "{}: {}.error: unknown value {}", scene_json, what, syn.value("error", std::string()));
    o.error = *err;
    o.magnitude = syn.value("magnitude", 0.0);
    o.support_y = syn.value("support_y", 0.0);
    SIMU_CHECK(syn.contains("gt"), "{}: {}.gt missing", scene_json, what);
    const nlohmann::json& gt = syn["gt"];
    o.gt_mesh = read_mesh((dir / gt.at("mesh").get<std::string>()).string());
    o.gt_scale = vec(gt.at("scale"), what + ".gt.scale");
    for (int r = 0; r < 3; ++r) o.gt_R.row(r) = vec(gt.at("R").at(r), what + ".gt.R").transpose();
    o.gt_t = vec(gt.at("t"), what + ".gt.t");
    if (so.gt_box) o.gt_box = *so.gt_box;
    else o.gt_box = world_aabb(place(o.gt_mesh, o.gt_scale, o.gt_R, o.gt_t));
    o.modal_mask = read_mask(so.mask_path);
    SIMU_CHECK(o.modal_mask.width == s.camera.width && o.modal_mask.height == s.camera.height,
               "{}: mask {} is {}x{}, the camera {}x{}", scene_json, so.mask_path, o.modal_mask.width,
               o.modal_mask.height, s.camera.width, s.camera.height);
    s.objects.push_back(std::move(o));
  }
  return s;
}

}  // namespace simu::physics
