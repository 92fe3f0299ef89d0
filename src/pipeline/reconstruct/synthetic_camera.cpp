#include "pipeline/reconstruct/synthetic_camera.h"

#include "common/error.h"
#include "common/fs.h"
#include "pipeline/physics/camera.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/raster.h"

#include <fmt/format.h>
#include <nlohmann/json.hpp>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

#include <cmath>
#include <filesystem>
#include <random>

namespace simu::reconstruct {

namespace {
constexpr double kPi = 3.14159265358979323846;
const Mat3 kFlip = Vec3(-1, -1, 1).asDiagonal();  // OpenCV <-> PyTorch3D camera

physics::Mesh placed(const physics::Mesh& m, const Vec3& s, const Mat3& R, const Vec3& t) {
  physics::Mesh out = m;
  for (Eigen::Index i = 0; i < m.V.rows(); ++i) out.V.row(i) = (R * s.cwiseProduct(m.V.row(i).transpose()) + t).transpose();
  return out;
}
nlohmann::json vj(const Vec3& v) { return {v.x(), v.y(), v.z()}; }
nlohmann::json mj(const Mat3& R) {
  return {{R(0, 0), R(0, 1), R(0, 2)}, {R(1, 0), R(1, 1), R(1, 2)}, {R(2, 0), R(2, 1), R(2, 2)}};
}
}  // namespace

Mask CameraScene::mask_of_label(int value) const {
  Mask m(K.width, K.height);
  for (size_t i = 0; i < labels.size(); ++i) m.data[i] = labels[i] == value;
  return m;
}

namespace {

// An object of the camera scene: its canonical mesh and ground-truth pose (world frame).
CameraObject camera_object(const std::string& id, const std::string& label, const physics::Mesh& mesh,
                           const Vec3& scale, const Mat3& R, const Vec3& t) {
  CameraObject o;
  o.id = id;
  o.label = label;
  o.canonical = mesh.V;
  o.faces = mesh.F;
  o.gt_scale = scale;
  o.gt_R = R;
  o.gt_t = t;
  return o;
}

// The generator's bases (labelled "table") then its objects, with their ground-truth poses (world frame).
void collect_objects(const physics::SyntheticScene& src, CameraScene& s) {
  for (const auto& b : src.bases) {
    s.objects.push_back(camera_object(b.id, "table", b.mesh, b.scale, b.R, b.t));
    s.objects.back().is_base = true;
  }
  for (const auto& so : src.objects) {
    s.objects.push_back(camera_object(so.id, so.label, so.gt_mesh, so.gt_scale, so.gt_R, so.gt_t));
    s.objects.back().dof = so.dof;
  }
}

// Joint shaded render of `world` from the camera: label image (0 = nothing, k + 1 = world[k]), Lambert-shaded
// RGB with a fixed colour per label, depth and the camera-frame point map (NaN where nothing was hit).
void render_photo(const physics::Camera& cam, const std::vector<physics::Mesh>& world, CameraScene& s) {
  std::vector<const physics::Mesh*> ptrs;
  for (auto& m : world) ptrs.push_back(&m);
  const physics::ShadedImage img = physics::render_shaded(cam, ptrs, 0.35);
  const int W = cam.width, H = cam.height;
  s.labels.assign(size_t(W) * H, 0);
  s.depth = img.labels.depth;
  s.rgb.assign(size_t(W) * H * 3, 0);
  for (size_t i = 0; i < s.labels.size(); ++i) {
    const int l = img.labels.label[i];
    s.labels[i] = l < 0 ? 0 : l + 1;
    if (l < 0) continue;
    // A fixed colour per label value, times the Lambert shade.
    const uint32_t h = uint32_t(l + 1) * 2654435761u;
    const double base[3] = {double(80 + (h & 0x7f)), double(80 + ((h >> 8) & 0x7f)), double(80 + ((h >> 16) & 0x7f))};
    for (int ch = 0; ch < 3; ++ch) s.rgb[i * 3 + ch] = uint8_t(std::min(255.0, base[ch] * (0.3 + img.shade[i])));
  }
  s.points.width = W;
  s.points.height = H;
  s.points.p.assign(size_t(W) * H, Vec3::Constant(std::nan("")));
  for (int r = 0; r < H; ++r)
    for (int c = 0; c < W; ++c) {
      const double z = s.depth[size_t(r) * W + c];
      if (std::isfinite(z)) s.points.p[size_t(r) * W + c] = Vec3((c - cam.cx) / cam.fx * z, (r - cam.cy) / cam.fy * z, z);
    }
}

}  // namespace

CameraScene generate_camera_scene(const CameraSceneConfig& cfg, uint64_t seed, const std::string& name) {
  CameraScene s;
  physics::SyntheticConfig gc = cfg.generator;
  gc.layout = "tabletop";
  s.source = physics::generate_scene(gc, seed, name);
  const auto& src = s.source;
  const physics::Camera& cam = src.camera;
  s.K = Pinhole{cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height};
  s.R_world_cam = cam.R_world_cam;
  s.t_world_cam = cam.t_world_cam;
  const Mat3 Rcw = cam.R_world_cam.transpose();
  auto to_cam = [&](const Vec3& p) { return Vec3(Rcw * (p - cam.t_world_cam)); };
  std::mt19937_64 rng(seed * 0x2545F4914F6CDD1DULL + 77);
  std::uniform_real_distribution<double> U(0, 1);
  auto R = [&](double a, double b) { return a + (b - a) * U(rng); };
  auto sign = [&]() { return U(rng) < 0.5 ? -1.0 : 1.0; };

  // Room planes (world frame: y down, floor y = floor_y, back wall z = wall_z, left wall x = left_wall_x).
  const double fy = src.floor.point.y(), wz = src.walls.at(0).point.z(), lx = cfg.left_wall_x, top = -1.5;
  std::vector<physics::Mesh> world;
  world.push_back(physics::quad_mesh(Vec3(lx, fy, 0.2), Vec3(3, fy, 0.2), Vec3(3, fy, wz), Vec3(lx, fy, wz)));      // floor
  world.push_back(physics::quad_mesh(Vec3(lx, top, wz), Vec3(3, top, wz), Vec3(3, fy, wz), Vec3(lx, fy, wz)));      // back wall
  world.push_back(physics::quad_mesh(Vec3(lx, top, 0.2), Vec3(lx, top, wz), Vec3(lx, fy, wz), Vec3(lx, fy, 0.2)));  // left wall
  // Objects (bases first) and the photo.
  collect_objects(src, s);
  for (auto& o : s.objects) world.push_back(placed(physics::Mesh{o.canonical, o.faces}, o.gt_scale, o.gt_R, o.gt_t));
  render_photo(cam, world, s);
  // Ground truth in the camera frame.
  const Vec3 up_w(0, -1, 0);
  s.up = Rcw * up_w;
  s.floor = NamedPlane{"floor", PlaneFit{to_cam(Vec3(0, fy, 1)), s.up, 0, 0}};
  s.back_wall = NamedPlane{"back_wall", PlaneFit{to_cam(Vec3(0, 0, wz)), Rcw * Vec3(0, 0, -1), 0, 0}};
  s.left_wall = NamedPlane{"left_wall", PlaneFit{to_cam(Vec3(lx, 0, 1)), Rcw * Vec3(1, 0, 0), 0, 0}};
  for (size_t i = 0; i < s.objects.size(); ++i) {
    CameraObject& o = s.objects[i];
    o.label_value = int(i) + 4;
    o.mask = s.mask_of_label(o.label_value);
    o.amodal_pixels = int64_t(physics::render_silhouette(cam, world[3 + i]).count());
    o.gt_R = Rcw * o.gt_R;
    o.gt_t = to_cam(o.gt_t);
    // SAM 3D-like errors.
    const double se = o.is_base ? sign() * cfg.table_scale_err : sign() * R(cfg.scale_err_min, cfg.scale_err_max);
    o.scale_error = 1 + se;
    o.lift_scale = o.gt_scale * o.scale_error;
    const double dist = o.gt_t.norm();
    o.ray_error = o.is_base ? 0.0 : sign() * R(cfg.ray_err_min, cfg.ray_err_max) * dist;
    o.lift_t = o.gt_t + o.ray_error * o.gt_t / dist + (o.is_base ? Vec3(cfg.table_lift_m * s.up) : Vec3(Vec3::Zero()));
    const double az = R(-kPi, kPi), el = R(-kPi / 2, kPi / 2);
    const Vec3 axis(std::cos(el) * std::cos(az), std::sin(el), std::cos(el) * std::sin(az));
    o.rotation_error = o.is_base ? cfg.table_rotation_err_deg : R(0, cfg.rotation_err_max_deg);
    o.lift_R = Eigen::AngleAxisd(o.rotation_error * kPi / 180, axis).toRotationMatrix() * o.gt_R;
  }
  return s;
}

Sam3dPose sam3d_pose_from_scene(const Mat3& R, const Vec3& scale, const Vec3& t) {
  // Column form of SAM 3D: p3d = Rq^T (scale .* v) + translation; OpenCV p = F p3d.
  // Scene: p = R (scale .* c) + t  ->  Rq^T = F R, translation = F t.
  Sam3dPose p;
  const Mat3 Rq = (kFlip * R).transpose();
  const Eigen::Quaterniond q(Rq);
  p.rotation_wxyz = Eigen::Vector4d(q.w(), q.x(), q.y(), q.z());
  p.scale = scale;
  p.translation = kFlip * t;
  return p;
}

ScenePoseOut scene_pose_from_sam3d_mesh(const Sam3dPose& pose, const Vec3& centre, double factor) {
  SIMU_CHECK(factor > 0 && std::isfinite(factor), "SAM 3D pose: canonical factor {} is not positive", factor);
  const Eigen::Quaterniond q(pose.rotation_wxyz[0], pose.rotation_wxyz[1], pose.rotation_wxyz[2], pose.rotation_wxyz[3]);
  SIMU_CHECK(std::abs(q.norm() - 1) < 1e-3, "SAM 3D pose: rotation quaternion has norm {} (1 expected)", q.norm());
  const Mat3 Rq = q.normalized().toRotationMatrix();
  // v = c / factor + centre:  p3d = Rq^T (scale .* (c / factor)) + Rq^T (scale .* centre) + translation.
  ScenePoseOut out;
  out.R = kFlip * Rq.transpose();
  out.scale = pose.scale / factor;
  out.t = kFlip * (Rq.transpose() * pose.scale.cwiseProduct(centre) + pose.translation);
  return out;
}

std::string canonical_up_axis(const CameraObject& o) { return o.label == "clock" ? "+z" : "-y"; }

void write_camera_scene_lift(const CameraScene& s, const std::string& dir) {
  namespace sfs = std::filesystem;
  sfs::create_directories(sfs::path(dir) / "lift");
  const int W = s.K.width, H = s.K.height;
  nlohmann::json K = {{"fx", s.K.fx}, {"fy", s.K.fy}, {"cx", s.K.cx}, {"cy", s.K.cy}, {"width", W}, {"height", H}};
  fs::atomic_write((sfs::path(dir) / "K.json").string(), K.dump(2) + "\n");
  nlohmann::json objs = nlohmann::json::array(), truth = nlohmann::json::array();
  objs.push_back({{"label_value", 1}, {"id", "floor"}, {"label", "floor"}, {"role", "floor"}});
  objs.push_back({{"label_value", 2}, {"id", "back_wall"}, {"label", "wall"}, {"role", "wall"}});
  objs.push_back({{"label_value", 3}, {"id", "left_wall"}, {"label", "wall"}, {"role", "wall"}});
  for (const auto& o : s.objects) {
    physics::Mesh m{o.canonical, o.faces};
    physics::write_obj((sfs::path(dir) / "lift" / (o.id + ".obj")).string(), m);
    const Sam3dPose p = sam3d_pose_from_scene(o.lift_R, o.lift_scale, o.lift_t);
    const nlohmann::json pose = {{"rotation_wxyz", {p.rotation_wxyz[0], p.rotation_wxyz[1], p.rotation_wxyz[2], p.rotation_wxyz[3]}},
                                 {"translation", vj(p.translation)},
                                 {"scale", vj(p.scale)}};
    fs::atomic_write((sfs::path(dir) / "lift" / (o.id + ".json")).string(), pose.dump(2) + "\n");
    nlohmann::json e = {{"label_value", o.label_value}, {"id", o.id},     {"label", o.label},
                        {"dof", physics::to_string(o.dof)}, {"pins", physics::pin_count(o.dof)},
                        {"base", o.is_base},        {"mesh", "lift/" + o.id + ".obj"}, {"pose", "lift/" + o.id + ".json"},
                        {"up_axis", canonical_up_axis(o)}};
    objs.push_back(e);
    truth.push_back({{"id", o.id}, {"R", mj(o.gt_R)}, {"t", vj(o.gt_t)}, {"scale", vj(o.gt_scale)},
                     {"scale_error", o.scale_error}, {"ray_error", o.ray_error}, {"rotation_error_deg", o.rotation_error}});
  }
  fs::atomic_write((sfs::path(dir) / "objects.json").string(), nlohmann::json({{"objects", objs}}).dump(2) + "\n");
  const nlohmann::json tj = {{"frame", "OpenCV camera"},
                             {"up", vj(s.up)},
                             {"floor", {{"point", vj(s.floor.plane.point)}, {"normal", vj(s.floor.plane.normal)}}},
                             {"back_wall", {{"point", vj(s.back_wall.plane.point)}, {"normal", vj(s.back_wall.plane.normal)}}},
                             {"left_wall", {{"point", vj(s.left_wall.plane.point)}, {"normal", vj(s.left_wall.plane.normal)}}},
                             {"objects", truth}};
  fs::atomic_write((sfs::path(dir) / "truth.json").string(), tj.dump(2) + "\n");
}

void write_camera_scene(const CameraScene& s, const std::string& dir) {
#ifndef SIMU_HAVE_OPENCV
  (void)s;
  fail("write_camera_scene {}: needs OpenCV (PNG writing); write_camera_scene_lift writes the rest", dir);
#else
  namespace sfs = std::filesystem;
  write_camera_scene_lift(s, dir);
  const int W = s.K.width, H = s.K.height;
  cv::Mat rgb(H, W, CV_8UC3), lab(H, W, CV_16UC1), dep(H, W, CV_16UC1);
  for (int r = 0; r < H; ++r)
    for (int c = 0; c < W; ++c) {
      const size_t i = size_t(r) * W + c;
      rgb.at<cv::Vec3b>(r, c) = cv::Vec3b(s.rgb[i * 3 + 2], s.rgb[i * 3 + 1], s.rgb[i * 3]);  // BGR
      lab.at<uint16_t>(r, c) = uint16_t(s.labels[i]);
      const double z = s.depth[i];
      dep.at<uint16_t>(r, c) = std::isfinite(z) ? uint16_t(std::lround(std::min(65.0, z) * 1000)) : 0;
    }
  auto write = [&](const std::string& name, const cv::Mat& m) {
    const std::string p = (sfs::path(dir) / name).string();
    SIMU_CHECK(cv::imwrite(p, m), "write_camera_scene: cannot write {}", p);
  };
  write("image.png", rgb);
  write("labels.png", lab);
  write("depth.png", dep);
#endif
}

}  // namespace simu::reconstruct
