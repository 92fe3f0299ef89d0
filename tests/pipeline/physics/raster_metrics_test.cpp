// Raster silhouettes / depth against analytic projections; IoU, ABO and physics metrics on
// hand-made inputs.
#include "pipeline/physics/camera.h"
#include "pipeline/physics/geometry.h"
#include "pipeline/physics/metrics.h"
#include "pipeline/physics/raster.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>

using namespace simu::physics;

namespace {

using Vec2 = Eigen::Vector2d;

Mesh world_box(const Vec3& e, const Mat3& R, const Vec3& c) {
  Obb b;
  b.extents = e, b.axes = R, b.center = c;
  return b.to_mesh();
}

Camera camera(int w, int h, double f, double cx, double cy) {
  Camera cam;
  cam.fx = cam.fy = f, cam.cx = cx, cam.cy = cy, cam.width = w, cam.height = h;
  return cam;
}

// Area and perimeter of the convex hull of 2D points (gift wrapping + shoelace), test-local.
std::pair<double, double> hull_area_perimeter(std::vector<Vec2> p) {
  std::vector<Vec2> h;
  size_t start = 0;
  for (size_t i = 1; i < p.size(); ++i)
    if (p[i].x() < p[start].x()) start = i;
  size_t cur = start;
  do {
    h.push_back(p[cur]);
    size_t next = (cur + 1) % p.size();
    for (size_t i = 0; i < p.size(); ++i) {
      const Vec2 a = p[next] - p[cur], b = p[i] - p[cur];
      if (a.x() * b.y() - a.y() * b.x() < 0) next = i;
    }
    cur = next;
  } while (cur != start && h.size() <= p.size());
  double area = 0, per = 0;
  for (size_t i = 0; i < h.size(); ++i) {
    const Vec2& a = h[i];
    const Vec2& b = h[(i + 1) % h.size()];
    area += a.x() * b.y() - a.y() * b.x();
    per += (b - a).norm();
  }
  return {std::abs(area) / 2, per};
}

}  // namespace

// A unit cube 5 m in front of the camera, centred on the optical axis: its silhouette is its front
// face, a square of side f / 4.5 pixels.
TEST(Raster, CubeSilhouetteAreaCentred) {
  const Camera cam = camera(400, 400, 400, 200.3, 199.6);
  const Mesh cube = world_box(Vec3::Ones(), Mat3::Identity(), Vec3(0, 0, 5));
  const BinaryMask m = render_silhouette(cam, cube);
  const double side = 400 / 4.5;
  EXPECT_NEAR(double(m.count()), side * side, 4 * side * 1.0);
  // Depth at the centre pixel is the front face's z (perspective-correct interpolation).
  const LabelImage img = render_labels(cam, {&cube});
  // A float32 depth buffer: ~10 fp32 roundings of the interpolated z <= 5 m.
  EXPECT_NEAR(img.depth[200 * 400 + 200], 4.5, 5 * simu::testing::gamma(10));
  EXPECT_EQ(img.label[200 * 400 + 200], 0);
  EXPECT_EQ(img.label[0], -1);
}

// A rotated, off-centre cube: silhouette area = area of the convex hull of its 8 projected corners.
TEST(Raster, CubeSilhouetteAreaRotated) {
  const Camera cam = camera(320, 240, 250, 160, 120);
  Obb b;
  b.extents = Vec3::Constant(0.4);
  b.axes = Eigen::AngleAxisd(0.6, Vec3(1, 2, -1).normalized()).toRotationMatrix();
  b.center = Vec3(0.3, -0.2, 2.5);
  const BinaryMask m = render_silhouette(cam, b.to_mesh());
  std::vector<Vec2> pts;
  for (const Vec3& c : b.corners()) pts.emplace_back(250 * c.x() / c.z() + 160, 250 * c.y() / c.z() + 120);
  const auto [area, per] = hull_area_perimeter(pts);
  EXPECT_GT(area, 1000);
  EXPECT_NEAR(double(m.count()), area, per * 1.0);
  // Depth at a pixel equals the ray's first hit on the box (plane of the nearest face).
  const Mesh mesh = b.to_mesh();
  const LabelImage img = render_labels(cam, {nullptr, &mesh});
  EXPECT_EQ(img.mask_of(0).count(), 0);
  EXPECT_EQ(img.mask_of(1).count(), m.count());
  int checked = 0;
  for (int r = 60; r < 180; r += 4)
    for (int c = 100; c < 260; c += 4) {
      // First hit of the pixel ray (direction with z = 1, so t is the depth) on the box (slab method).
      const Vec3 d = pixel_ray_camera(cam, c, r);
      const Vec3 o = b.axes.transpose() * (-b.center), dl = b.axes.transpose() * d;
      double t0 = 0, t1 = 1e30;
      for (int a = 0; a < 3; ++a) {
        double ta = (-0.2 - o(a)) / dl(a), tb = (0.2 - o(a)) / dl(a);
        if (ta > tb) std::swap(ta, tb);
        t0 = std::max(t0, ta), t1 = std::min(t1, tb);
      }
      if (t0 > t1 - 1e-3) continue;  // miss or grazing
      EXPECT_NEAR(img.depth[r * 320 + c], t0, 5 * simu::testing::gamma(10)) << "pixel " << c << "," << r;  // as above
      ++checked;
    }
  EXPECT_GT(checked, 50);
}

// Near-plane clipping: a box straddling the camera plane still covers the pixels in front.
TEST(Raster, NearPlaneClipping) {
  const Camera cam = camera(100, 100, 50, 50, 50);
  const Mesh slab = world_box(Vec3(0.4, 0.4, 4), Mat3::Identity(), Vec3(0, 0, 0));  // z in [-2, 2]
  const BinaryMask m = render_silhouette(cam, slab);
  // Every pixel looks through the side walls/front face of the box: the whole image is covered.
  EXPECT_EQ(m.count(), 100 * 100);
}

// Z-buffer: a near box occludes a far one; the far box's visible mask is its silhouette minus the
// near one's, and the label image tells them apart.
TEST(Raster, ZBufferOcclusion) {
  const Camera cam = camera(200, 200, 200, 100.2, 100.1);
  const Mesh near = world_box(Vec3(0.3, 0.3, 0.3), Mat3::Identity(), Vec3(0.1, 0, 2));
  const Mesh far = world_box(Vec3(0.6, 0.6, 0.6), Mat3::Identity(), Vec3(0, 0, 4));
  const LabelImage img = render_labels(cam, {&far, &near});
  const BinaryMask sf = render_silhouette(cam, far), sn = render_silhouette(cam, near);
  const BinaryMask vf = img.mask_of(0), vn = img.mask_of(1);
  int64_t bad = 0;
  for (size_t i = 0; i < vf.data.size(); ++i) bad += vf.data[i] != (sf.data[i] && !sn.data[i]);
  EXPECT_EQ(bad, 0);
  EXPECT_EQ(vn.count(), sn.count());
  EXPECT_GT(vf.count(), 0);
}

// IoU on hand-made rectangles: two 10x10 squares overlapping by 5 columns -> 50 / 150.
TEST(Metrics, MaskIou) {
  BinaryMask a(30, 20), b(30, 20);
  for (int r = 0; r < 10; ++r)
    for (int c = 0; c < 10; ++c) a.at(r, c) = 1, b.at(r, c + 5) = 1;
  EXPECT_NEAR(mask_iou(a, b), 50.0 / 150.0, simu::testing::kFp64Short);
  EXPECT_NEAR(mask_iou(a, a), 1.0, simu::testing::kFp64Short);
  EXPECT_EQ(mask_iou(BinaryMask(30, 20), BinaryMask(30, 20)), 0.0);
  EXPECT_THROW(mask_iou(a, BinaryMask(3, 3)), simu::Error);
}

TEST(Metrics, BoxIou) {
  Box3 a{Vec3(0, 0, 0), Vec3(1, 1, 1)}, b{Vec3(0.5, 0, 0), Vec3(1.5, 1, 1)}, c{Vec3(2, 2, 2), Vec3(3, 3, 3)};
  EXPECT_NEAR(box_iou(a, b), 0.5 / 1.5, simu::testing::kFp64Short);
  EXPECT_EQ(box_iou(a, c), 0.0);
  Box3 inner{Vec3(0, 0, 0), Vec3(0.5, 0.5, 0.5)};
  EXPECT_NEAR(box_iou(a, inner), 0.125, simu::testing::kFp64Short);
}

// ABO and IoU with the strict variants on a hand-made IoU matrix.
TEST(Metrics, OverlapAboFhFo) {
  // gt 0 (free): identity 0.6, best 0.8 via pred 2; gt 1 (hanging): identity 0.5;
  // gt 2 (free, prediction invalid): identity 0.9; gt 3 (fixed base): identity 1.0.
  const std::vector<std::vector<double>> iou = {
      {0.6, 0.1, 0.8, 0.0}, {0.0, 0.5, 0.0, 0.0}, {0.2, 0.0, 0.9, 0.0}, {0.0, 0.0, 0.0, 1.0}};
  const std::vector<bool> valid = {true, true, false, true};
  const std::vector<MetricCategory> cat = {MetricCategory::Free, MetricCategory::Hanging, MetricCategory::Free,
                                           MetricCategory::Fixed};
  const OverlapMetrics m = overlap_metrics(iou, valid, cat);
  EXPECT_NEAR(m.iou, (0.6 + 0.5 + 0.9 + 1.0) / 4, simu::testing::kFp64Chain);
  EXPECT_NEAR(m.abo, (0.8 + 0.5 + 0.9 + 1.0) / 4, simu::testing::kFp64Chain);
  EXPECT_EQ(m.n_fh, 3);
  EXPECT_EQ(m.n_fo, 2);
  // fh: gt0 best valid fh pred = 0.6 (pred 2 invalid), gt1 0.5, gt2 best valid = 0.2 (pred 0).
  EXPECT_NEAR(m.abo_fh, (0.6 + 0.5 + 0.2) / 3, simu::testing::kFp64Chain);
  EXPECT_NEAR(m.iou_fh, (0.6 + 0.5 + 0.0) / 3, simu::testing::kFp64Chain);
  // fo: only free predictions (0, 2); pred 2 invalid.
  EXPECT_NEAR(m.abo_fo, (0.6 + 0.2) / 2, simu::testing::kFp64Chain);
  EXPECT_NEAR(m.iou_fo, (0.6 + 0.0) / 2, simu::testing::kFp64Chain);
  EXPECT_NEAR(m.abo_fhfo(), 0.5 * (m.abo_fh + m.abo_fo), simu::testing::kFp64Short);
}

// Mask metrics through the renderer: a predicted box identical to the ground truth scores 1, a
// missing prediction 0 (denominator stays N_gt).
TEST(Metrics, MaskMetricsRendered) {
  const Camera cam = camera(160, 120, 150, 80.3, 60.2);
  const Mesh a = world_box(Vec3(0.3, 0.3, 0.3), Mat3::Identity(), Vec3(-0.3, 0, 2));
  const Mesh b = world_box(Vec3(0.3, 0.3, 0.3), Mat3::Identity(), Vec3(0.3, 0, 2));
  const std::vector<BinaryMask> gt = {render_silhouette(cam, a), render_silhouette(cam, b)};
  const OverlapMetrics m = mask_metrics(cam, {&a, nullptr}, gt, {true, true},
                                        {MetricCategory::Free, MetricCategory::Free});
  EXPECT_NEAR(m.iou, 0.5, simu::testing::kFp64Chain);
  EXPECT_NEAR(m.abo, 0.5, simu::testing::kFp64Chain);
  const OverlapMetrics bm = box_metrics({&a, &b}, {world_aabb(a), world_aabb(b)}, {true, true},
                                        {MetricCategory::Free, MetricCategory::Free});
  EXPECT_NEAR(bm.iou, 1.0, simu::testing::kFp64Chain);
}

// Stability, penetration ratio, mean displacement and peak energy on hand-made records.
TEST(Metrics, PhysicsMetrics) {
  std::vector<SettleRecord> r(5);
  r[0].displacement = 0.01;                                       // free, stable
  r[1].displacement = 0.08, r[1].peak_kinetic_energy = 2.0;       // free, unstable
  r[2].displacement = 0.2, r[2].initially_penetrating = true;     // free, excluded from stability
  r[2].max_penetration = 0.003;                                   // and penetrating (> 2 mm)
  r[3].category = MetricCategory::Hanging, r[3].displacement = 0.1, r[3].max_penetration = 0.002;  // not > 2 mm
  r[4].physics_disabled = true, r[4].displacement = 5;            // left out entirely
  const PhysicsMetrics m = physics_metrics(r);
  EXPECT_EQ(m.stability_count, 2);
  EXPECT_NEAR(m.stability, 50.0, simu::testing::kFp64Chain);
  EXPECT_EQ(m.evaluated_count, 4);
  EXPECT_NEAR(m.penetration_ratio, 25.0, simu::testing::kFp64Chain);
  EXPECT_NEAR(m.mean_displacement, (0.01 + 0.08 + 0.2 + 0.1) / 4, simu::testing::kFp64Chain);
  EXPECT_NEAR(m.peak_energy, 2.0, simu::testing::kFp64Short);
  EXPECT_NEAR(physics_metrics(r, {}, 7.5).peak_energy, 7.5, simu::testing::kFp64Short);
  EXPECT_TRUE(is_valid(r[0]));
  EXPECT_FALSE(is_valid(r[1]));  // unstable free object
  EXPECT_FALSE(is_valid(r[2]));  // penetrating
  EXPECT_TRUE(is_valid(r[3]));   // hanging, moved but not counted as unstable
}

#include "pipeline/physics/overlay.h"
#include "test_files.h"
#include "tolerance.h"

#include <filesystem>

// Mask PNG round trip and an overlay file with masks, boxes and an auxiliary mask.
TEST(Overlay, MaskRoundTripAndOverlay) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "built without OpenCV";
#endif
  const std::string dir = simu::testing::temp_dir("overlay");
  BinaryMask m(40, 30);
  for (int r = 5; r < 20; ++r)
    for (int c = 3; c < 17; ++c) m.at(r, c) = 1;
  write_mask(dir + "/m.png", m);
  const BinaryMask back = read_mask(dir + "/m.png");
  EXPECT_EQ(back.width, 40);
  EXPECT_EQ(back.data, m.data);
  EXPECT_THROW(read_mask(dir + "/missing.png"), simu::Error);
  const Camera cam = camera(40, 30, 30, 20, 15);
  Obb b;
  b.extents = Vec3::Constant(0.5), b.center = Vec3(0, 0, 3);
  OverlayItem it;
  it.label = "box", it.mask = &m, it.obb = b, it.obb_target = b, it.aux_mask = &m;
  write_overlay_png(dir + "/overlay.png", cam, "", {it});
  EXPECT_GT(std::filesystem::file_size(dir + "/overlay.png"), 100u);
}
