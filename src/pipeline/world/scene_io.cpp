// World scenes on disk (the inputs of `lift` and the ground truth) and the families' contact sheet.
#include "pipeline/world/scene_io.h"

#include "common/error.h"
#include "common/fs.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/overlay.h"
#include "pipeline/world/parts.h"
#include "pipeline/world/rest.h"

#include <filesystem>
#include <fmt/format.h>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#endif

namespace simu::world {

namespace {

nlohmann::json vec_json(const Vec3& v) { return {v.x(), v.y(), v.z()}; }
nlohmann::json mat_json(const Mat3& R) {
  return {{R(0, 0), R(0, 1), R(0, 2)}, {R(1, 0), R(1, 1), R(1, 2)}, {R(2, 0), R(2, 1), R(2, 2)}};
}

#ifdef SIMU_HAVE_OPENCV
void write_mat_png(const std::string& path, const cv::Mat& img) {
  std::vector<uchar> buf;
  SIMU_CHECK(cv::imencode(".png", img, buf), "could not encode PNG for {}", path);
  fs::atomic_write(path, std::string_view(reinterpret_cast<const char*>(buf.data()), buf.size()));
}
// RGB bytes -> an OpenCV BGR image.
cv::Mat bgr_of(int W, int H, const std::vector<uint8_t>& rgb) {
  cv::Mat img(H, W, CV_8UC3);
  for (size_t i = 0; i < size_t(W) * H; ++i) {
    img.data[i * 3 + 0] = rgb[i * 3 + 2], img.data[i * 3 + 1] = rgb[i * 3 + 1], img.data[i * 3 + 2] = rgb[i * 3 + 0];
  }
  return img;
}
#endif

void need_opencv(const char* what) {
#ifndef SIMU_HAVE_OPENCV
  throw Error(fmt::format("{}: built without OpenCV, no PNG codec", what), "configure with SIMU_WITH_OPENCV=ON");
#else
  (void)what;
#endif
}

}  // namespace

nlohmann::json intrinsics_json(const physics::Camera& c) {
  return {{"fx", c.fx}, {"fy", c.fy}, {"cx", c.cx}, {"cy", c.cy}, {"width", c.width}, {"height", c.height},
          {"K", {{c.fx, 0.0, c.cx}, {0.0, c.fy, c.cy}, {0.0, 0.0, 1.0}}}};
}

nlohmann::json scene_gt_json(const WorldScene& s, const CorruptionRecord* corruption) {
  nlohmann::json j;
  j["name"] = s.name;
  j["seed"] = s.seed;
  j["split"] = to_string(s.split);
  j["camera"] = intrinsics_json(s.camera);
  j["camera"]["R_world_cam"] = mat_json(s.camera.R_world_cam);
  j["camera"]["t_world_cam"] = vec_json(s.camera.t_world_cam);
  j["gravity"] = vec_json(s.gravity);
  j["floor_y"] = s.floor_y, j["wall_z"] = s.wall_z, j["table_top_y"] = s.table_top_y;
  j["light"] = {{"direction", vec_json(s.light_dir)}, {"intensity", s.light}, {"ambient", s.ambient}};
  j["labels"] = {{"floor", kLabelFloor}, {"wall", kLabelWall}, {"table", kLabelTable}, {"first_object", kFirstObjectLabel}};
  j["removed"] = s.removed;
  j["objects"] = nlohmann::json::array();
  for (const auto& o : s.objects) {
    nlohmann::json occ = nlohmann::json::array();
    for (int k : o.occluders) occ.push_back(s.objects[size_t(k)].id);
    j["objects"].push_back({{"id", o.id},
                            {"label", o.label},
                            {"family", o.shape.family},
                            {"instance", o.shape.name},
                            {"instance_id", fmt::format("{:016x}", o.shape.id)},
                            {"instance_seed", o.shape.seed},
                            {"split", to_string(o.shape.split)},
                            {"held_out", o.shape.held_out},
                            {"closed", o.shape.closed},
                            {"rest", to_string(o.rest)},
                            {"on_floor", o.on_floor},
                            {"size_m", o.shape.size_m},
                            {"albedo", vec_json(o.shape.albedo)},
                            {"R", mat_json(o.R)},
                            {"scale", vec_json(o.scale)},
                            {"t", vec_json(o.t)},
                            {"R_cam", mat_json(o.R_cam)},
                            {"t_cam", vec_json(o.t_cam)},
                            {"modal_pixels", o.modal_pixels},
                            {"amodal_pixels", o.amodal_pixels},
                            {"visible_fraction", o.visible_fraction},
                            {"occluders", occ},
                            {"occluded_by_table", o.occluded_by_table},
                            {"target", o.target},
                            {"usable", o.usable},
                            {"mask", "masks/" + o.id + ".png"},
                            {"amodal_mask", "amodal/" + o.id + ".png"},
                            {"mesh", "meshes/" + o.shape.name + ".obj"}});
  }
  if (corruption)
    j["corruption"] = {{"scale", corruption->scale},
                       {"flying_pixels", corruption->flying_pixels},
                       {"missing_pixels", corruption->missing_pixels},
                       {"valid_before", corruption->valid_before},
                       {"valid_after", corruption->valid_after}};
  return j;
}

void write_scene_files(const WorldScene& s, const std::string& dir, const CorruptionRecord* corruption) {
  need_opencv("write_scene_files");
#ifdef SIMU_HAVE_OPENCV
  const int W = s.camera.width, H = s.camera.height;
  std::filesystem::create_directories(dir + "/masks");
  std::filesystem::create_directories(dir + "/amodal");
  std::filesystem::create_directories(dir + "/meshes");
  write_mat_png(dir + "/image.png", bgr_of(W, H, s.rgb));
  cv::Mat labels(H, W, CV_16UC1);
  for (size_t i = 0; i < size_t(W) * H; ++i) labels.at<uint16_t>(int(i / W), int(i % W)) = uint16_t(s.labels[i]);
  write_mat_png(dir + "/labels.png", labels);
  for (const auto& o : s.objects) {
    physics::write_mask(dir + "/masks/" + o.id + ".png", o.modal);
    physics::write_mask(dir + "/amodal/" + o.id + ".png", o.amodal);
    physics::write_mesh(o.shape.mesh, dir + "/meshes/" + o.shape.name + ".obj");
  }
  fs::atomic_write(dir + "/intrinsics.json", intrinsics_json(s.camera).dump(2) + "\n");
  fs::atomic_write(dir + "/gt.json", scene_gt_json(s, corruption).dump(2) + "\n");
#else
  (void)s, (void)dir, (void)corruption;
#endif
}

void write_png(const std::string& path, const Picture& p) {
  need_opencv("write_png");
#ifdef SIMU_HAVE_OPENCV
  write_mat_png(path, bgr_of(p.width, p.height, p.rgb));
#else
  (void)path, (void)p;
#endif
}

Picture family_contact_sheet(int per_family, int cell, uint64_t seed) {
  SIMU_CHECK(per_family >= 1 && per_family <= 16 && cell >= 32 && cell <= 1024,
             "family_contact_sheet: per_family {} (1..16) or cell {} (32..1024) out of range", per_family, cell);
  const auto& fams = families();
  Picture sheet;
  sheet.width = cell * per_family, sheet.height = cell * int(fams.size());
  sheet.rgb.assign(size_t(sheet.width) * sheet.height * 3, 0);
  for (size_t f = 0; f < fams.size(); ++f)
    for (int k = 0; k < per_family; ++k) {
      // The instance standing (or lying) alone on a grey floor, at unit size, seen from 30 degrees up.
      WorldScene s;
      s.name = fams[f];
      physics::Mesh floor;
      floor.V.resize(4, 3);
      floor.V << -20, 0.5, -20, 20, 0.5, -20, 20, 0.5, 20, -20, 0.5, 20;
      floor.F.resize(2, 3);
      floor.F << 0, 1, 2, 0, 2, 3;
      s.environment = {floor};
      s.environment_albedo = {Vec3::Constant(0.55)};
      WorldObject o;
      o.shape = make_shape(fams[f], next_instance_seed(fams[f], fams[f] == held_out_family() ? Split::Test : Split::Train,
                                                       seed + uint64_t(k) * 7919));
      const RestAnalysis a = analyse_rest(o.shape.mesh, o.shape.closed);
      const int face = a.stand >= 0 ? a.stand : pick_face(a, 0.5);
      o.R = rotation(0.6, Vec3::UnitY()) * (face >= 0 ? put_down(a.faces[size_t(face)].normal) : Mat3::Identity());
      o.scale = Vec3::Ones();
      o.t = Vec3::Zero();
      const physics::Mesh placed = object_world_mesh(o);
      o.t.y() = 0.5 - placed.V.col(1).maxCoeff();
      s.objects.push_back(o);
      const double elev = 0.52, dist = 2.4;
      const Vec3 back(0, -std::sin(elev), -std::cos(elev)), fwd = -back;
      const Vec3 right = Vec3(0, 1, 0).cross(fwd).normalized(), down = fwd.cross(right);
      s.camera.width = s.camera.height = cell;
      s.camera.fx = s.camera.fy = 0.5 * cell / std::tan(0.5 * 0.5);
      s.camera.cx = s.camera.cy = 0.5 * cell;
      s.camera.R_world_cam.col(0) = right, s.camera.R_world_cam.col(1) = down, s.camera.R_world_cam.col(2) = fwd;
      s.camera.t_world_cam = Vec3(0, o.t.y() * 0.5, 0) + dist * back;
      s.light_dir = Vec3(0.4, 1.0, 0.5).normalized();
      s.light = 0.8, s.ambient = 0.3;
      render_scene(s);
      for (int r = 0; r < cell; ++r)
        for (int c = 0; c < cell; ++c)
          for (int ch = 0; ch < 3; ++ch)
            sheet.rgb[(size_t(f * cell + r) * sheet.width + size_t(k * cell + c)) * 3 + ch] = s.rgb[(size_t(r) * cell + c) * 3 + ch];
    }
#ifdef SIMU_HAVE_OPENCV
  // Family names in the first cell of each row.
  cv::Mat img(sheet.height, sheet.width, CV_8UC3, sheet.rgb.data());
  for (size_t f = 0; f < fams.size(); ++f) {
    const std::string text = fams[f] == held_out_family() ? fams[f] + " (held out)" : fams[f];
    const cv::Point at(4, int(f) * cell + 14);
    cv::putText(img, text, at, cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(0, 0, 0), 3, cv::LINE_AA);
    cv::putText(img, text, at, cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(255, 255, 255), 1, cv::LINE_AA);
  }
#endif
  return sheet;
}

}  // namespace simu::world
