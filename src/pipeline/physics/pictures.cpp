// Probe pictures: before/after, side view, resample candidates (see pictures.h).
#include "pipeline/physics/pictures.h"

#include <cctype>
#include <algorithm>
#include <cmath>
#include <filesystem>

#include <fmt/ranges.h>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "pipeline/physics/camera.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/overlay.h"
#include "pipeline/physics/raster.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#endif

namespace simu::physics {

#ifdef SIMU_HAVE_OPENCV

namespace {

constexpr int kMinHeight = 480;  // every view is rendered at least this many pixels high

void write_png(const std::string& path, const cv::Mat& img) {
  std::vector<uchar> buf;
  SIMU_CHECK(cv::imencode(".png", img, buf), "could not encode PNG for {}", path);
  fs::atomic_write(path, std::string_view(reinterpret_cast<const char*>(buf.data()), buf.size()));
}

cv::Scalar color_of(int i) {
  const auto c = overlay_color(i);
  return cv::Scalar(c[0], c[1], c[2]);
}

// Text with a dark outline so it reads on any background; scale relative to the panel height.
void label(cv::Mat& img, const std::string& text, cv::Point at, const cv::Scalar& color, double scale) {
  const int thick = std::max(1, int(std::lround(2 * scale)));
  at.x = std::clamp(at.x, 2, std::max(2, img.cols - 10));
  at.y = std::clamp(at.y, int(20 * scale), std::max(int(20 * scale), img.rows - 4));
  cv::putText(img, text, at, cv::FONT_HERSHEY_SIMPLEX, scale, cv::Scalar(20, 20, 20), thick + 3, cv::LINE_AA);
  cv::putText(img, text, at, cv::FONT_HERSHEY_SIMPLEX, scale, color, thick, cv::LINE_AA);
}

// The camera scaled by an integer factor k (pixel centres kept consistent).
Camera scaled(const Camera& c, int k) {
  Camera s = c;
  s.fx *= k, s.fy *= k;
  s.cx = (c.cx + 0.5) * k - 0.5, s.cy = (c.cy + 0.5) * k - 0.5;
  s.width = c.width * k, s.height = c.height * k;
  return s;
}

// A square of side 2 * half on a plane, centred at the foot of `near` on it (two triangles).
Mesh plane_quad(const Plane& p, const Vec3& near, double half) {
  const Vec3 n = p.normal.normalized();
  const Vec3 u = n.unitOrthogonal(), v = n.cross(u);
  const Vec3 c = near - p.distance(near) * n;
  Mesh m;
  m.V.resize(4, 3);
  m.V.row(0) = (c - half * u - half * v).transpose();
  m.V.row(1) = (c + half * u - half * v).transpose();
  m.V.row(2) = (c + half * u + half * v).transpose();
  m.V.row(3) = (c - half * u + half * v).transpose();
  m.F.resize(2, 3);
  m.F << 0, 1, 2, 0, 2, 3;
  return m;
}

// Scene geometry for the renders: objects (final pose) first, then bases and the floor (grey).
struct Geometry {
  std::vector<Mesh> objects;  // per scene object (empty: none)
  std::vector<Mesh> env;      // bases, floor
  Vec3 lo = Vec3::Constant(1e300), hi = Vec3::Constant(-1e300);
};
Geometry scene_geometry(const ProbeResult& r) {
  Geometry g;
  const Scene& s = r.scene;
  g.objects.resize(s.objects.size());
  for (size_t i = 0; i < s.objects.size(); ++i) {
    if (i >= r.meshes.size() || r.meshes[i].empty()) continue;
    g.objects[i] = world_mesh(r.meshes[i], s.objects[i]);
    g.lo = g.lo.cwiseMin(g.objects[i].V.colwise().minCoeff().transpose());
    g.hi = g.hi.cwiseMax(g.objects[i].V.colwise().maxCoeff().transpose());
  }
  for (const auto& b : s.bases) {
    if (!b.error.empty()) continue;
    try {
      const Mesh m = read_mesh(b.mesh_path);
      g.env.push_back(transform_mesh(m, b.R * b.scale.asDiagonal(), b.t));
      g.lo = g.lo.cwiseMin(g.env.back().V.colwise().minCoeff().transpose());
      g.hi = g.hi.cwiseMax(g.env.back().V.colwise().maxCoeff().transpose());
    } catch (const std::exception& e) {
      log::debug("pictures: base {}: {}", b.id, e.what());
    }
  }
  if (!(g.lo.array() <= g.hi.array()).all()) g.lo = Vec3::Constant(-1), g.hi = Vec3::Constant(1);
  if (s.floor) g.env.push_back(plane_quad(*s.floor, 0.5 * (g.lo + g.hi), 2.0 * (g.hi - g.lo).norm() + 0.5));
  return g;
}

// Shaded render: object k in its colour, environment in grey, background `bg`.
cv::Mat shaded_view(const Camera& cam, const std::vector<const Mesh*>& objects, const std::vector<int>& colors,
                    const std::vector<const Mesh*>& env, const cv::Scalar& bg) {
  std::vector<const Mesh*> all = objects;
  all.insert(all.end(), env.begin(), env.end());
  const ShadedImage sh = render_shaded(cam, all, 0.35);
  cv::Mat img(cam.height, cam.width, CV_8UC3, bg);
  for (int y = 0; y < cam.height; ++y)
    for (int x = 0; x < cam.width; ++x) {
      const size_t p = size_t(y) * cam.width + x;
      const int l = sh.labels.label[p];
      if (l < 0) continue;
      const cv::Scalar base = l < int(objects.size()) ? color_of(colors[l]) : cv::Scalar(190, 190, 185);
      const double f = sh.shade[p];
      img.at<cv::Vec3b>(y, x) = cv::Vec3b(cv::saturate_cast<uchar>(base[0] * f), cv::saturate_cast<uchar>(base[1] * f),
                                          cv::saturate_cast<uchar>(base[2] * f));
    }
  return img;
}

cv::Point centroid(const BinaryMask& m, int k) {
  double sx = 0, sy = 0, n = 0;
  for (int y = 0; y < m.height; ++y)
    for (int x = 0; x < m.width; ++x)
      if (m.at(y, x)) sx += x, sy += y, ++n;
  return n ? cv::Point(int(sx / n * k), int(sy / n * k)) : cv::Point(-1, -1);
}

// The short tag drawn on the object in the views; the legend pairs it with the object's id.
std::string tag(size_t i) { return std::to_string(i); }

std::string legend_line(const ProbeResult& r, size_t i) {
  const auto& d = r.diagnostics[i];
  std::string s = fmt::format("{} {}: {}", tag(i), r.scene.objects[i].id, to_string(d.branch));
  if (d.branch == ProbeBranch::Stretch || d.branch == ProbeBranch::Resample) s += fmt::format(" rho {:.2f}", d.diagnosis.rho);
  if (d.branch == ProbeBranch::Resample) s += d.resampled ? " (replaced)" : " (NOT replaced)";
  if (!d.evaluation.physics_disabled) s += fmt::format(", moves {:.1f} mm in 5 s", 1000 * d.evaluation.displacement);
  if (!d.flags.empty()) s += " [" + fmt::format("{}", fmt::join(d.flags, ",")) + "]";
  return s;
}

// What every picture of one probe run draws with: the scene, the camera scaled to at least
// kMinHeight rows (factor k), the font scale, the final geometry and the render lists.
struct Pictures {
  const ProbeResult& r;
  const Scene& s;
  size_t n;
  int k;
  Camera cam;
  double fs;  // font scale
  Geometry g;
  std::vector<const Mesh*> obj_ptrs, env_ptrs;
  std::vector<int> colors;  // scene object index of each entry of obj_ptrs
  explicit Pictures(const ProbeResult& res) : r(res), s(res.scene), n(res.scene.objects.size()) {
    k = std::max(1, int(std::ceil(double(kMinHeight) / s.camera.height)));
    cam = scaled(s.camera, k);
    fs = cam.height / 900.0 + 0.25;
    g = scene_geometry(r);
    for (size_t i = 0; i < n; ++i)
      if (!g.objects[i].empty()) obj_ptrs.push_back(&g.objects[i]), colors.push_back(int(i));
    for (const auto& m : g.env) env_ptrs.push_back(&m);
  }
  Pictures(const Pictures&) = delete;
  Pictures& operator=(const Pictures&) = delete;
};

// before_after.png: left input masks (over the dimmed image), right the final shaded meshes.
std::string write_before_after(const Pictures& p, const std::string& dir) {
  const ProbeResult& r = p.r;
  const Scene& s = p.s;
  const size_t n = p.n;
  const int k = p.k;
  const Camera& cam = p.cam;
  const double fs = p.fs;
  const auto& obj_ptrs = p.obj_ptrs;
  const auto& env_ptrs = p.env_ptrs;
  const auto& colors = p.colors;
  cv::Mat left(cam.height, cam.width, CV_8UC3, cv::Scalar(60, 60, 60));
  if (!s.image_path.empty() && std::filesystem::exists(s.image_path)) {
    cv::Mat im = cv::imread(s.image_path, cv::IMREAD_COLOR);
    if (!im.empty()) cv::resize(im, left, cv::Size(cam.width, cam.height), 0, 0, cv::INTER_NEAREST), left *= 0.45;
  }
  std::vector<cv::Point> left_at(n, cv::Point(-1, -1));
  for (size_t i = 0; i < n; ++i) {
    const auto& so = s.objects[i];
    if (so.mask_path.empty() || !std::filesystem::exists(so.mask_path)) continue;
    BinaryMask m;
    try {
      m = read_mask(so.mask_path);
    } catch (const std::exception&) {
      continue;
    }
    if (m.width != s.camera.width || m.height != s.camera.height) continue;
    cv::Mat big(m.height, m.width, CV_8U, m.data.data());
    cv::Mat up;
    cv::resize(big, up, cv::Size(cam.width, cam.height), 0, 0, cv::INTER_NEAREST);
    cv::Mat tint(cam.height, cam.width, CV_8UC3, color_of(int(i)));
    cv::Mat blend;
    cv::addWeighted(left, 0.3, tint, 0.7, 0, blend);
    blend.copyTo(left, up);
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(up, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
    cv::drawContours(left, contours, -1, cv::Scalar(255, 255, 255), std::max(1, k / 2));
    left_at[i] = centroid(m, k);
  }
  cv::Mat right = shaded_view(cam, obj_ptrs, colors, env_ptrs, cv::Scalar(70, 60, 50));
  const LabelImage lab = render_labels(cam, obj_ptrs);
  for (size_t i = 0; i < n; ++i) {
    if (left_at[i].x >= 0) label(left, tag(i), left_at[i], cv::Scalar(255, 255, 255), fs);
    const auto it = std::find(colors.begin(), colors.end(), int(i));
    if (it == colors.end()) continue;
    const cv::Point at = centroid(lab.mask_of(int(it - colors.begin())), 1);
    if (at.x >= 0) label(right, tag(i), at, cv::Scalar(255, 255, 255), fs);
  }
  label(left, "input masks", cv::Point(8, int(34 * fs)), cv::Scalar(255, 255, 255), fs);
  label(right, "final scene (shaded meshes)", cv::Point(8, int(34 * fs)), cv::Scalar(255, 255, 255), fs);
  // Legend: one line per object in its colour.
  const int line_h = int(38 * fs) + 6;
  cv::Mat legend(line_h * int(n + 1) + 10, 2 * cam.width + 8, CV_8UC3, cv::Scalar(30, 30, 30));
  for (size_t i = 0; i < n; ++i) {
    cv::rectangle(legend, cv::Rect(8, int(i) * line_h + 10, line_h - 10, line_h - 10), color_of(int(i)), cv::FILLED);
    label(legend, legend_line(r, i), cv::Point(line_h + 6, int(i + 1) * line_h - 2), cv::Scalar(240, 240, 240), fs * 0.8);
  }
  cv::Mat top(cam.height, 2 * cam.width + 8, CV_8UC3, cv::Scalar(255, 255, 255));
  left.copyTo(top(cv::Rect(0, 0, cam.width, cam.height)));
  right.copyTo(top(cv::Rect(cam.width + 8, 0, cam.width, cam.height)));
  cv::Mat out;
  cv::vconcat(top, legend, out);
  write_png(dir + "/before_after.png", out);
  return dir + "/before_after.png";
}

// side_view.png: horizontal view across the camera's line of sight, gravity down.
std::string write_side_view(const Pictures& p, const std::string& dir) {
  const Scene& s = p.s;
  const Geometry& g = p.g;
  const auto& obj_ptrs = p.obj_ptrs;
  const auto& env_ptrs = p.env_ptrs;
  const auto& colors = p.colors;
  const Vec3 gdir = s.gravity.normalized();
  Vec3 f = s.camera.R_world_cam.col(0);  // the camera's right axis ...
  f -= f.dot(gdir) * gdir;               // ... made horizontal
  if (f.norm() < 1e-6) f = gdir.unitOrthogonal();
  f.normalize();
  // Framed on the objects (the bases and the floor are drawn around them), seen from far away so
  // the view is nearly orthographic and the support surfaces are edge-on at the objects' height.
  Vec3 olo = Vec3::Constant(1e300), ohi = Vec3::Constant(-1e300);
  for (const auto& m : g.objects)
    if (!m.empty()) {
      olo = olo.cwiseMin(m.V.colwise().minCoeff().transpose());
      ohi = ohi.cwiseMax(m.V.colwise().maxCoeff().transpose());
    }
  if (!(olo.array() <= ohi.array()).all()) olo = g.lo, ohi = g.hi;
  const Vec3 c = 0.5 * (olo + ohi);
  const double radius = std::max(0.5 * (ohi - olo).norm(), 0.05);
  Camera side;
  side.width = 2 * kMinHeight, side.height = 3 * kMinHeight / 2;
  const double dist = 10 * radius;
  side.fx = side.fy = 0.5 * side.height * dist / (1.25 * radius);
  side.cx = 0.5 * (side.width - 1), side.cy = 0.5 * (side.height - 1);
  Mat3 R;
  R.col(2) = f, R.col(1) = gdir, R.col(0) = gdir.cross(f);  // x = y cross z (OpenCV axes)
  side.R_world_cam = R;
  side.t_world_cam = c - dist * f;
  cv::Mat img = shaded_view(side, obj_ptrs, colors, env_ptrs, cv::Scalar(70, 60, 50));
  const LabelImage lab = render_labels(side, obj_ptrs);
  const double sfs = side.height / 900.0 + 0.25;
  for (size_t j = 0; j < obj_ptrs.size(); ++j) {
    const cv::Point at = centroid(lab.mask_of(int(j)), 1);
    if (at.x >= 0) label(img, tag(colors[j]), at, cv::Scalar(255, 255, 255), sfs);
  }
  label(img, "final scene from the side (gravity down)", cv::Point(8, int(34 * sfs)), cv::Scalar(255, 255, 255), sfs);
  // Legend: tag -> id.
  for (size_t j = 0; j < obj_ptrs.size(); ++j)
    label(img, tag(colors[j]) + " " + s.objects[colors[j]].id, cv::Point(8, int((34 + 34 * (j + 1)) * sfs)),
          color_of(colors[j]), sfs * 0.8);
  write_png(dir + "/side_view.png", img);
  return dir + "/side_view.png";
}

// candidates_<id>.png for object i: input mask, then every candidate, the kept one marked.
std::string write_candidates(const Pictures& p, size_t i, const std::string& dir) {
  const Scene& s = p.s;
  const int k = p.k;
  const Camera& cam = p.cam;
  const double fs = p.fs;
  const auto& env_ptrs = p.env_ptrs;
  const Diagnostics& d = p.r.diagnostics[i];
  std::vector<cv::Mat> tiles;
  // Tile 0: the object's input mask over the dimmed image.
  cv::Mat t0(cam.height, cam.width, CV_8UC3, cv::Scalar(60, 60, 60));
  try {
    const BinaryMask m = read_mask(s.objects[i].mask_path);
    if (m.width == s.camera.width && m.height == s.camera.height)
      for (int y = 0; y < cam.height; ++y)
        for (int x = 0; x < cam.width; ++x)
          if (m.at(y / k, x / k)) t0.at<cv::Vec3b>(y, x) = cv::Vec3b(uchar(color_of(int(i))[0]), uchar(color_of(int(i))[1]), uchar(color_of(int(i))[2]));
  } catch (const std::exception&) {
  }
  label(t0, "input mask: " + s.objects[i].id, cv::Point(8, int(34 * fs)), cv::Scalar(255, 255, 255), fs);
  tiles.push_back(t0);
  for (size_t c = 0; c < d.candidates.size(); ++c) {
    const auto& cd = d.candidates[c];
    std::vector<const Mesh*> one;
    std::vector<int> col{int(i)};
    if (!cd.world.empty()) one.push_back(&cd.world);
    cv::Mat t = shaded_view(cam, one, col, env_ptrs, cv::Scalar(70, 60, 50));
    const bool kept = int(c) == d.chosen_candidate && d.resampled;
    std::string what = fmt::format("#{} ", c) + (cd.ok ? fmt::format("moved {:.1f} mm", 1000 * cd.displacement) : "FAILED");
    label(t, what, cv::Point(8, int(34 * fs)), kept ? cv::Scalar(80, 255, 80) : cv::Scalar(255, 255, 255), fs);
    if (!cd.ok && !cd.message.empty())
      label(t, cd.message.substr(0, 40), cv::Point(8, int(75 * fs)), cv::Scalar(200, 200, 255), fs * 0.85);
    if (kept) {
      cv::rectangle(t, cv::Rect(0, 0, t.cols, t.rows), cv::Scalar(80, 255, 80), std::max(4, 3 * k));
      label(t, "KEPT", cv::Point(8, t.rows - int(14 * fs)), cv::Scalar(80, 255, 80), fs * 1.5);
    }
    tiles.push_back(t);
  }
  cv::Mat row;
  cv::hconcat(tiles, row);
  const std::string title = d.resampled
                                ? fmt::format("{}: {} candidates, #{} kept (moved least)", s.objects[i].id, d.candidates.size(), d.chosen_candidate)
                                : fmt::format("{}: no candidate passed its checks; the input shape was kept", s.objects[i].id);
  cv::Mat head(int(50 * fs) + 10, row.cols, CV_8UC3, cv::Scalar(30, 30, 30));
  label(head, title, cv::Point(8, int(40 * fs)), cv::Scalar(240, 240, 240), fs);
  cv::Mat out;
  cv::vconcat(head, row, out);
  std::string safe;
  for (char ch : s.objects[i].id) safe += (std::isalnum(static_cast<unsigned char>(ch)) || ch == '-' || ch == '_') ? ch : '_';
  const std::string path = dir + "/candidates_" + safe + ".png";
  write_png(path, out);
  return path;
}

}  // namespace

void write_object_comparison_png(const std::string& path, const Camera& cam, const std::vector<uint8_t>& rgb,
                                 const BinaryMask& modal, const std::vector<MeshPanel>& panels,
                                 const std::vector<const Mesh*>& environment, const std::string& title) {
  SIMU_CHECK(cam.valid(), "picture {}: invalid camera", path);
  SIMU_CHECK(rgb.size() == size_t(cam.width) * cam.height * 3, "picture {}: the image has {} bytes, not {} x {} x 3",
             path, rgb.size(), cam.height, cam.width);
  SIMU_CHECK(modal.width == cam.width && modal.height == cam.height, "picture {}: the mask is {} x {}, the camera {} x {}",
             path, modal.width, modal.height, cam.width, cam.height);
  // The crop: the mask's and every silhouette's bounds, padded by a fifth (at least 8 pixels).
  std::array<int, 4> box = modal.bbox();
  auto grow = [&](const std::array<int, 4>& b) {
    if (b[0] < 0) return;
    if (box[0] < 0) box = b;
    box = {std::min(box[0], b[0]), std::min(box[1], b[1]), std::max(box[2], b[2]), std::max(box[3], b[3])};
  };
  for (const auto& p : panels)
    if (p.world_mesh && !p.world_mesh->empty()) grow(render_silhouette(cam, *p.world_mesh).bbox());
  if (box[0] < 0) box = {0, 0, cam.width - 1, cam.height - 1};
  // Square (as far as the image allows) so that captions fit: the shorter side grows about the centre,
  // shifted back inside the image.
  const int pad = std::max(8, std::max(box[2] - box[0], box[3] - box[1]) / 5);
  const int side = std::min(std::max(box[2] - box[0], box[3] - box[1]) + 1 + 2 * pad, std::min(cam.width, cam.height));
  auto span = [&](int lo, int hi, int limit) {
    const int len = std::max(hi - lo + 1 + 2 * pad, side);
    int a = (lo + hi + 1) / 2 - len / 2;
    a = std::clamp(a, 0, std::max(0, limit - len));
    return std::make_pair(a, std::min(limit - 1, a + len - 1));
  };
  const auto [c0, c1] = span(box[0], box[2], cam.width);
  const auto [r0, r1] = span(box[1], box[3], cam.height);
  const int k = std::clamp(int(std::ceil(240.0 / (r1 - r0 + 1))), 1, 6);
  const Camera view = scaled(cam, k);
  const cv::Rect crop(c0 * k, r0 * k, (c1 - c0 + 1) * k, (r1 - r0 + 1) * k);
  const double fs = std::max(0.45, crop.height / 480.0);
  std::vector<cv::Mat> tiles;
  // The input: the image (nearest-neighbour upscaled), the modal mask's outline in white.
  cv::Mat input(view.height, view.width, CV_8UC3);
  for (int y = 0; y < view.height; ++y)
    for (int x = 0; x < view.width; ++x) {
      const size_t p = (size_t(y / k) * cam.width + x / k) * 3;
      input.at<cv::Vec3b>(y, x) = cv::Vec3b(rgb[p + 2], rgb[p + 1], rgb[p]);  // RGB -> BGR
    }
  cv::Mat mask(view.height, view.width, CV_8UC1, cv::Scalar(0));
  for (int y = 0; y < view.height; ++y)
    for (int x = 0; x < view.width; ++x) mask.at<uchar>(y, x) = modal.at(y / k, x / k) ? 255 : 0;
  std::vector<std::vector<cv::Point>> contours;
  cv::findContours(mask, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
  cv::drawContours(input, contours, -1, cv::Scalar(255, 255, 255), std::max(1, k / 2));
  tiles.push_back(input(crop).clone());
  label(tiles.back(), "input", cv::Point(6, int(26 * fs)), cv::Scalar(255, 255, 255), fs);
  for (size_t i = 0; i < panels.size(); ++i) {
    std::vector<const Mesh*> one;
    if (panels[i].world_mesh && !panels[i].world_mesh->empty()) one.push_back(panels[i].world_mesh);
    const cv::Mat full = shaded_view(view, one, {int(i)}, environment, cv::Scalar(70, 60, 50));
    tiles.push_back(full(crop).clone());
    label(tiles.back(), panels[i].caption, cv::Point(6, int(26 * fs)), cv::Scalar(255, 255, 255), fs);
  }
  cv::Mat row;
  cv::hconcat(tiles, row);
  // The title line, the row widened (dark) when the title is longer.
  int base = 0;
  const int text_w = cv::getTextSize(title, cv::FONT_HERSHEY_SIMPLEX, fs, std::max(1, int(std::lround(2 * fs))), &base).width + 16;
  if (text_w > row.cols) cv::copyMakeBorder(row, row, 0, 0, 0, text_w - row.cols, cv::BORDER_CONSTANT, cv::Scalar(30, 30, 30));
  cv::Mat head(int(40 * fs) + 8, row.cols, CV_8UC3, cv::Scalar(30, 30, 30));
  label(head, title, cv::Point(6, int(30 * fs)), cv::Scalar(240, 240, 240), fs);
  cv::Mat out;
  cv::vconcat(head, row, out);
  write_png(path, out);
}

std::vector<std::string> write_probe_pictures(const ProbeResult& r, const std::string& dir) {
  SIMU_CHECK(r.scene.camera.valid(), "pictures need a valid camera");
  const Pictures p(r);
  std::vector<std::string> written;
  written.push_back(write_before_after(p, dir));
  written.push_back(write_side_view(p, dir));
  for (size_t i = 0; i < p.n; ++i)
    if (!r.diagnostics[i].candidates.empty()) written.push_back(write_candidates(p, i, dir));
  return written;
}

#else

std::vector<std::string> write_probe_pictures(const ProbeResult&, const std::string&) {
  fail("pictures need OpenCV (built with SIMU_WITH_OPENCV=OFF)");
}

void write_object_comparison_png(const std::string& path, const Camera&, const std::vector<uint8_t>&, const BinaryMask&,
                                 const std::vector<MeshPanel>&, const std::vector<const Mesh*>&, const std::string&) {
  fail("picture {}: pictures need OpenCV (built with SIMU_WITH_OPENCV=OFF)", path);
}

#endif

}  // namespace simu::physics
