// Mask PNG I/O and the overlay image (OpenCV imgcodecs/imgproc).
#include "pipeline/physics/overlay.h"

#include "common/error.h"
#include "common/fs.h"
#include "pipeline/physics/camera.h"

#include <cmath>
#include <filesystem>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#endif

namespace simu::physics {

std::array<uint8_t, 3> overlay_color(int i) {
  static const uint8_t table[10][3] = {{75, 25, 230}, {75, 180, 60}, {25, 225, 255}, {200, 130, 0}, {48, 130, 245},
                                       {180, 30, 145}, {240, 240, 70}, {230, 50, 240}, {60, 245, 210}, {212, 190, 250}};
  const auto& c = table[((i % 10) + 10) % 10];
  return {c[0], c[1], c[2]};
}

#ifdef SIMU_HAVE_OPENCV

namespace {

// PNG bytes of an image, written atomically.
void write_png(const std::string& path, const cv::Mat& img) {
  std::vector<uchar> buf;
  SIMU_CHECK(cv::imencode(".png", img, buf), "could not encode PNG for {}", path);
  const auto parent = std::filesystem::path(path).parent_path();
  if (!parent.empty()) std::filesystem::create_directories(parent);
  simu::fs::atomic_write(path, std::string_view(reinterpret_cast<const char*>(buf.data()), buf.size()));
}

// Draws the 12 edges of a box whose both end points are in front of the camera.
void draw_box(cv::Mat& img, const Camera& cam, const Obb& b, const cv::Scalar& color, bool dashed) {
  const auto c = b.corners();
  for (int i = 0; i < 8; ++i)
    for (int a = 0; a < 3; ++a) {
      const int j = i | (1 << a);
      if (j == i) continue;
      const Projection p = project(cam, c[i]), q = project(cam, c[j]);
      if (!p.in_front() || !q.in_front()) continue;
      const int segments = dashed ? 12 : 1;
      for (int s = 0; s < segments; s += dashed ? 2 : 1) {
        const double t0 = double(s) / segments, t1 = double(s + 1) / segments;
        const cv::Point a0(int(std::lround(p.u + t0 * (q.u - p.u))), int(std::lround(p.v + t0 * (q.v - p.v))));
        const cv::Point a1(int(std::lround(p.u + t1 * (q.u - p.u))), int(std::lround(p.v + t1 * (q.v - p.v))));
        cv::line(img, a0, a1, color, 1, cv::LINE_AA);
      }
    }
}

cv::Mat to_mat(const BinaryMask& m) {
  cv::Mat out(m.height, m.width, CV_8U);
  for (int r = 0; r < m.height; ++r)
    for (int c = 0; c < m.width; ++c) out.at<uint8_t>(r, c) = m.at(r, c) ? 255 : 0;
  return out;
}

}  // namespace

BinaryMask read_mask(const std::string& path) {
  SIMU_CHECK(std::filesystem::exists(path), "mask file {} does not exist", path);
  cv::Mat img = cv::imread(path, cv::IMREAD_UNCHANGED);
  SIMU_CHECK(!img.empty(), "could not read mask image {} (expected an image file OpenCV can decode)", path);
  if (img.channels() > 1) {
    std::vector<cv::Mat> ch;
    cv::split(img, ch);
    cv::Mat any = ch[0] != 0;
    for (size_t k = 1; k < ch.size() && k < 3; ++k) any |= (ch[k] != 0);
    img = any;
  }
  BinaryMask m(img.cols, img.rows);
  cv::Mat nz = img != 0;
  for (int r = 0; r < img.rows; ++r)
    for (int c = 0; c < img.cols; ++c) m.at(r, c) = nz.at<uint8_t>(r, c) ? 1 : 0;
  return m;
}

void write_mask(const std::string& path, const BinaryMask& mask) { write_png(path, to_mat(mask)); }

void write_overlay_png(const std::string& path, const Camera& cam, const std::string& image_path,
                       const std::vector<OverlayItem>& items) {
  SIMU_CHECK(cam.width > 0 && cam.height > 0, "overlay: invalid camera size {}x{}", cam.width, cam.height);
  // Background: the scene image (resized to the camera size) or grey.
  cv::Mat img;
  if (!image_path.empty() && std::filesystem::exists(image_path)) img = cv::imread(image_path, cv::IMREAD_COLOR);
  if (img.empty()) img = cv::Mat(cam.height, cam.width, CV_8UC3, cv::Scalar(96, 96, 96));
  if (img.cols != cam.width || img.rows != cam.height) cv::resize(img, img, cv::Size(cam.width, cam.height));
  // Masks: 50% tint with the object colour.
  for (size_t i = 0; i < items.size(); ++i) {
    const BinaryMask* m = items[i].mask;
    if (!m || m->width != cam.width || m->height != cam.height) continue;
    const auto col = overlay_color(int(i));
    for (int r = 0; r < m->height; ++r)
      for (int c = 0; c < m->width; ++c)
        if (m->at(r, c)) {
          auto& px = img.at<cv::Vec3b>(r, c);
          for (int k = 0; k < 3; ++k) px[k] = uint8_t((px[k] + col[k]) / 2);
        }
  }
  // Auxiliary masks: white contours; boxes: wireframes; labels.
  for (size_t i = 0; i < items.size(); ++i) {
    const auto col = overlay_color(int(i));
    const cv::Scalar color(col[0], col[1], col[2]);
    const OverlayItem& it = items[i];
    if (it.aux_mask && it.aux_mask->width == cam.width && it.aux_mask->height == cam.height) {
      std::vector<std::vector<cv::Point>> contours;
      cv::findContours(to_mat(*it.aux_mask), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
      cv::drawContours(img, contours, -1, cv::Scalar(255, 255, 255), 1);
    }
    if (it.obb) draw_box(img, cam, *it.obb, color, false);
    if (it.obb_target) draw_box(img, cam, *it.obb_target, color, true);
    if (!it.label.empty() && it.mask) {
      const auto b = it.mask->bbox();
      if (b[0] >= 0)
        cv::putText(img, it.label, cv::Point(b[0], std::max(10, b[1] - 2)), cv::FONT_HERSHEY_SIMPLEX, 0.35, color, 1,
                    cv::LINE_AA);
    }
  }
  write_png(path, img);
}

#else

BinaryMask read_mask(const std::string& path) {
  simu::fail_hint("configure with SIMU_WITH_OPENCV=ON", "cannot read mask {}: built without OpenCV", path);
}
void write_mask(const std::string& path, const BinaryMask&) {
  simu::fail_hint("configure with SIMU_WITH_OPENCV=ON", "cannot write mask {}: built without OpenCV", path);
}
void write_overlay_png(const std::string& path, const Camera&, const std::string&, const std::vector<OverlayItem>&) {
  simu::fail_hint("configure with SIMU_WITH_OPENCV=ON", "cannot write overlay {}: built without OpenCV", path);
}

#endif

}  // namespace simu::physics
