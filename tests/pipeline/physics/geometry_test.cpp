// Gravity diagnostics, stretch and auxiliary-mask tests against independently computed answers.
#include "pipeline/physics/camera.h"
#include "pipeline/physics/geometry.h"
#include "pipeline/physics/raster.h"
#include "tolerance.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>

using namespace simu::physics;

namespace {

// Vertices of an axis-aligned box [-e/2, e/2] with extra samples on its edges (canonical frame).
Points box_points(const Vec3& e, int per_edge = 4) {
  std::vector<Vec3> pts;
  for (int x = 0; x <= per_edge; ++x)
    for (int y = 0; y <= per_edge; ++y)
      for (int z = 0; z <= per_edge; ++z) {
        const int on = (x == 0 || x == per_edge) + (y == 0 || y == per_edge) + (z == 0 || z == per_edge);
        if (on < 2) continue;  // edges and corners only
        pts.emplace_back((double(x) / per_edge - 0.5) * e.x(), (double(y) / per_edge - 0.5) * e.y(),
                         (double(z) / per_edge - 0.5) * e.z());
      }
  Points P(pts.size(), 3);
  for (size_t i = 0; i < pts.size(); ++i) P.row(i) = pts[i].transpose();
  return P;
}

// A box as a mesh (canonical frame, axis-aligned, centred).
Mesh raw_box(const Vec3& e) {
  Obb b;
  b.extents = e;
  return b.to_mesh();
}

Mat3 rot(double angle, const Vec3& axis) { return Eigen::AngleAxisd(angle, axis.normalized()).toRotationMatrix(); }

// Ray (origin o, direction d) against a box: true when it hits (slab method, independent of raster).
bool ray_hits_box(const Vec3& o, const Vec3& d, const Obb& b) {
  const Vec3 lo = b.axes.transpose() * (o - b.center);
  const Vec3 dl = b.axes.transpose() * d;
  double t0 = 0, t1 = 1e30;
  for (int a = 0; a < 3; ++a) {
    const double h = 0.5 * b.extents(a);
    if (std::abs(dl(a)) < simu::testing::kFp64Short) {
      if (std::abs(lo(a)) > h) return false;
      continue;
    }
    double ta = (-h - lo(a)) / dl(a), tb = (h - lo(a)) / dl(a);
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta), t1 = std::min(t1, tb);
  }
  return t0 <= t1;
}

// Mask of the pixels whose centre ray hits the box (identity camera pose).
BinaryMask raycast_mask(const Camera& cam, const Obb& b) {
  BinaryMask m(cam.width, cam.height);
  for (int r = 0; r < cam.height; ++r)
    for (int c = 0; c < cam.width; ++c) m.at(r, c) = ray_hits_box(Vec3::Zero(), pixel_ray_camera(cam, c, r), b);
  return m;
}

Camera test_camera(int w = 320, int h = 240, double f = 300) {
  Camera cam;
  cam.fx = cam.fy = f;
  cam.cx = w / 2.0 - 0.37;  // keep box edges off the pixel centres
  cam.cy = h / 2.0 - 0.21;
  cam.width = w, cam.height = h;
  return cam;
}

}  // namespace

// A rotated box with distinct sides: the OBB recovers its centre, side lengths and axes.
TEST(Geometry, ObbRecoversRotatedBox) {
  const Vec3 e(0.4, 0.25, 0.1), c(0.3, -0.2, 1.7);
  const Mat3 Q = rot(0.7, Vec3(1, 2, 3)) * rot(-0.4, Vec3(0, 1, 0));
  const Points P = (box_points(e) * Q.transpose()).rowwise() + c.transpose();
  const Obb b = compute_obb(P);
  EXPECT_LT((b.center - c).norm(), simu::testing::kFp64Solve);
  EXPECT_NEAR(b.volume(), e.prod(), simu::testing::kFp64Solve);
  for (int k = 0; k < 3; ++k) {
    // Each found axis is +-one box axis with the matching side length.
    int match = -1;
    for (int j = 0; j < 3; ++j)
      if (std::abs(std::abs(b.axes.col(k).dot(Q.col(j))) - 1) < simu::testing::kFp64Solve) match = j;
    ASSERT_GE(match, 0) << "axis " << k << " is not a box axis";
    EXPECT_NEAR(b.extents(k), e(match), simu::testing::kFp64Solve);
  }
  EXPECT_NEAR(b.axes.determinant(), 1.0, simu::testing::kFp64Solve);
}

// A rotated cube (PCA is degenerate): the object's rotation as a hint gives the exact box, and the
// caliper refinement finds it without hints when one face is vertical (a yawed cube on a floor).
TEST(Geometry, ObbOfCube) {
  const Mat3 Q = rot(0.5, Vec3(0.3, -1, 0.2));
  const Points P = box_points(Vec3::Constant(0.3)) * Q.transpose();
  const Obb hinted = compute_obb(P, {Q});
  EXPECT_NEAR(hinted.volume(), 0.027, simu::testing::kFp64Chain);
  const Mat3 yaw = rot(0.6, Vec3(0, 1, 0));
  const Obb free = compute_obb(box_points(Vec3::Constant(0.3)) * yaw.transpose());
  EXPECT_NEAR(free.volume(), 0.027, simu::testing::kFp64Solve);
  EXPECT_THROW(compute_obb(Points(0, 3)), simu::Error);
}

// Gravity axis: the OBB axis most aligned with g, oriented along g, with its side length.
TEST(Geometry, GravityAxis) {
  Obb b;
  b.axes = rot(0.2, Vec3(0, 0, 1));  // x, y tilted by 0.2 rad about z
  b.extents = Vec3(0.5, 0.3, 0.2);
  const GravityAxis ga = gravity_axis(b, Vec3(0, 1, 0));
  EXPECT_EQ(ga.index, 1);
  EXPECT_NEAR(ga.length, 0.3, simu::testing::kFp64Short);
  EXPECT_NEAR(ga.alignment, std::cos(0.2), simu::testing::kFp64Chain);
  EXPECT_GT(ga.u.dot(Vec3(0, 1, 0)), 0);
  const GravityAxis down = gravity_axis(b, Vec3(0, -1, 0));
  EXPECT_LT(down.u.y(), 0);
}

// rho and eta follow eqs. (stretch_ratio)/(stretch_displacement); threshold 0.15 picks the branch.
TEST(Geometry, DiagnoseRhoEta) {
  Obb b;
  b.extents = Vec3(0.2, 0.25, 0.2);
  const Vec3 g(0, 1, 0);
  // Hovering 3 cm: falls 3 cm along g; pen push 0.
  Diagnosis d = diagnose(b, g, Vec3::Zero(), Vec3(0.01, 0.03, 0));
  EXPECT_NEAR(d.eta, 0.03 / 0.25, simu::testing::kFp64Chain);
  EXPECT_NEAR(d.rho, 0.12, simu::testing::kFp64Chain);
  EXPECT_EQ(d.branch, Branch::Stretch);
  // Sunk 5 cm: pushed up (against g) by 5 cm: eta < 0, rho = 0.2 -> resample.
  d = diagnose(b, g, Vec3(0, -0.05, 0), Vec3::Zero());
  EXPECT_NEAR(d.eta, -0.2, simu::testing::kFp64Chain);
  EXPECT_EQ(d.branch, Branch::Resample);
  CorrectionConfig cfg;
  cfg.resample_threshold = 0.25;
  EXPECT_EQ(diagnose(b, g, Vec3(0, -0.05, 0), Vec3::Zero(), cfg).branch, Branch::Stretch);
  // Exactly at the threshold resamples (rho >= 0.15).
  EXPECT_EQ(diagnose(b, g, Vec3::Zero(), Vec3(0, 0.0375, 0)).branch, Branch::Resample);
}

namespace {
// Checks a stretch result against the world-space answer: every world vertex x moves to
// x + eta (u.x - top) u, where top = min u.x (the anti-gravity face stays, the bottom moves by eta l).
void expect_world_stretch(const Mesh& canon, const Vec3& s, const Mat3& R, const Vec3& t, const Diagnosis& d,
                          const StretchResult& r) {
  const Vec3 u = d.axis.u;
  Points before = (canon.V * (R * s.asDiagonal()).transpose()).rowwise() + t.transpose();
  Points after = (r.canonical * (r.R * r.scale.asDiagonal()).transpose()).rowwise() + r.t.transpose();
  const double top = (before * u).minCoeff();
  double worst = 0;
  for (Eigen::Index i = 0; i < before.rows(); ++i) {
    const Vec3 x = before.row(i).transpose();
    const Vec3 want = x + d.eta * (u.dot(x) - top) * u;
    worst = std::max(worst, (Vec3(after.row(i).transpose()) - want).norm());
  }
  EXPECT_LT(worst, simu::testing::kFp64Chain);
  EXPECT_NEAR((after * u).minCoeff(), top, simu::testing::kFp64Chain);  // top face preserved
  EXPECT_NEAR((after * u).maxCoeff() - (before * u).maxCoeff(), d.g_displacement, simu::testing::kFp64Chain);  // bottom moved
  EXPECT_NEAR(r.top_face_shift, 0.0, simu::testing::kFp64Chain);
  // The canonical convention holds: AABB-centred, longest side 1.
  const Vec3 lo = r.canonical.colwise().minCoeff().transpose(), hi = r.canonical.colwise().maxCoeff().transpose();
  EXPECT_LT((0.5 * (lo + hi)).norm(), simu::testing::kFp64Chain);
  EXPECT_NEAR((hi - lo).maxCoeff(), 1.0, simu::testing::kFp64Chain);
}
}  // namespace

// The stretch equations keep the top (anti-gravity) face: box whose OBB axis is a canonical axis
// (folds into the per-axis scale), and a shape whose gravity axis is oblique in its canonical frame
// (new canonical mesh with an isotropic scale).
TEST(Geometry, StretchPreservesTopFace) {
  const Vec3 g(0, 1, 0);
  // Canonical box, longest side 1; tilted pose.
  const Mesh canon = raw_box(Vec3(1.0, 0.6, 0.4));
  const Vec3 s = Vec3::Constant(0.3);
  const Mat3 R = rot(0.3, Vec3(0, 1, 0)) * rot(0.25, Vec3(1, 0, 0));
  const Vec3 t(0.1, 0.7, 2.0);
  const Obb obb = object_obb(canon, s, R, t, g);
  Diagnosis d = diagnose(obb, g, Vec3::Zero(), Vec3(0, 0.02, 0));
  ASSERT_EQ(d.branch, Branch::Stretch);
  StretchResult r = gravity_axis_stretch(canon.V, s, R, t, R, d);
  EXPECT_FALSE(r.mesh_changed);
  EXPECT_NEAR(r.lambda, 1 + d.eta, simu::testing::kFp64Short);
  expect_world_stretch(canon, s, R, t, d, r);
  // Shrinking (pushed up out of a sinking pose).
  d = diagnose(obb, g, Vec3(0, -0.01, 0), Vec3::Zero());
  r = gravity_axis_stretch(canon.V, s, R, t, R, d);
  expect_world_stretch(canon, s, R, t, d, r);

  // A canonical mesh that is itself a box rotated inside its canonical frame (AABB-centred, longest
  // side 1): its OBB axes are oblique to the canonical axes.
  Mesh oblique = raw_box(Vec3(0.8, 0.5, 0.3));
  oblique.V = oblique.V * rot(0.5, Vec3(0, 0, 1)).transpose();
  const Vec3 lo = oblique.V.colwise().minCoeff().transpose(), hi = oblique.V.colwise().maxCoeff().transpose();
  oblique.V = (oblique.V.rowwise() - (0.5 * (lo + hi)).transpose()) / (hi - lo).maxCoeff();
  const Vec3 s2 = Vec3::Constant(0.4);
  const Mat3 R2 = rot(-0.2, Vec3(0, 1, 0));
  const Obb obb2 = object_obb(oblique, s2, R2, t, g);
  d = diagnose(obb2, g, Vec3::Zero(), Vec3(0, 0.015, 0));
  ASSERT_EQ(d.branch, Branch::Stretch);
  r = gravity_axis_stretch(oblique.V, s2, R2, t, R2, d);
  EXPECT_TRUE(r.mesh_changed);
  expect_world_stretch(oblique, s2, R2, t, d, r);
  // Paper: s_str = gamma s (isotropic input scale).
  EXPECT_NEAR(r.scale(0), r.gamma * s2(0), simu::testing::kFp64Chain);
}

// A hovering box (3 cm, height 25 cm) stretches: its bottom reaches the floor, top unchanged.
TEST(Geometry, HoveringBoxStretches) {
  const Vec3 g(0, 1, 0);
  const double floor_y = 1.0, h = 0.25, hover = 0.03;
  const Mesh canon = raw_box(Vec3(0.8, 1.0, 0.8));  // longest side 1 along canonical y
  const Vec3 s = Vec3::Constant(h);
  const Vec3 t(0.0, floor_y - hover - h / 2, 2.0);
  const Obb obb = object_obb(canon, s, Mat3::Identity(), t, g);
  EXPECT_NEAR(obb.extents(1), h, simu::testing::kFp64Chain);
  const Diagnosis d = diagnose(obb, g, Vec3::Zero(), Vec3(0, hover, 0));
  EXPECT_EQ(d.branch, Branch::Stretch);
  EXPECT_NEAR(d.rho, hover / h, simu::testing::kFp64Chain);
  const StretchResult r = gravity_axis_stretch(canon.V, s, Mat3::Identity(), t, Mat3::Identity(), d);
  const Points after = (r.canonical * r.scale.asDiagonal()).rowwise() + r.t.transpose();
  EXPECT_NEAR(after.col(1).maxCoeff(), floor_y, simu::testing::kFp64Chain);               // bottom on the floor
  EXPECT_NEAR(after.col(1).minCoeff(), floor_y - hover - h, simu::testing::kFp64Chain);   // top kept
  EXPECT_NEAR(after.col(0).maxCoeff() - after.col(0).minCoeff(), 0.8 * h, simu::testing::kFp64Chain);  // width kept
}

// Bottom cut off by 40%: the object hovers by the missing height, rho >= 0.15 -> resample; B_str is
// the full box and M' = modal mask united with exactly the projected missing part (pixels checked by
// ray casting the known missing box).
TEST(Geometry, CutBoxResamplesAndAuxMaskCoversMissingPart) {
  const Vec3 g(0, 1, 0);
  const double floor_y = 0.6, H = 0.3, cut = 0.4;
  const Vec3 full_extent(0.2, H, 0.15);
  Obb full;  // ground truth: standing on the floor, slightly yawed
  full.axes = rot(0.3, Vec3(0, 1, 0));
  full.extents = full_extent;
  full.center = Vec3(0.05, floor_y - H / 2, 1.6);
  // Reconstruction: only the top 60% (its top where the true top is).
  const double h_vis = (1 - cut) * H;
  Obb visible = full;
  visible.extents(1) = h_vis;
  visible.center = full.center - Vec3(0, (H - h_vis) / 2, 0);
  // Canonical mesh of the visible part + pose.
  const double longest = std::max({full_extent.x(), h_vis, full_extent.z()});
  const Mesh canon = raw_box(Vec3(full_extent.x(), h_vis, full_extent.z()) / longest);
  const Vec3 s = Vec3::Constant(longest);
  const Obb obb = object_obb(canon, s, full.axes, visible.center, g);
  EXPECT_NEAR(obb.extents(1), h_vis, simu::testing::kFp64Chain);
  // The simulation drops it by the missing height.
  const Diagnosis d = diagnose(obb, g, Vec3::Zero(), Vec3(0, cut * H, 0));
  EXPECT_NEAR(d.rho, cut / (1 - cut), simu::testing::kFp64Chain);
  EXPECT_EQ(d.branch, Branch::Resample);
  // B_str is the full box; its centre is the resampled translation.
  const Obb bstr = stretched_obb(d);
  EXPECT_LT((bstr.center - full.center).norm(), simu::testing::kFp64Chain);
  EXPECT_NEAR(bstr.extents(1), H, simu::testing::kFp64Chain);
  // M' = modal + the missing part, checked pixel by pixel with rays.
  const Camera cam = test_camera();
  const BinaryMask modal = raycast_mask(cam, visible);
  ASSERT_GT(modal.count(), 100);
  Obb missing = full;
  missing.extents(1) = cut * H;
  missing.center = full.center + Vec3(0, (H - cut * H) / 2, 0);
  const BinaryMask missing_px = raycast_mask(cam, missing);
  ASSERT_GT(missing_px.count(), 100);
  const BinaryMask aux = auxiliary_crop_mask(cam, modal, d);
  int64_t wrong = 0, added = 0;
  for (size_t i = 0; i < aux.data.size(); ++i) {
    const bool want = modal.data[i] || missing_px.data[i];
    wrong += (aux.data[i] != 0) != want;
    added += aux.data[i] && !modal.data[i];
  }
  EXPECT_LE(wrong, 2) << "pixels differing from modal + ray-cast missing part";
  EXPECT_GT(added, 100);
  // The crop box extends below the modal mask.
  EXPECT_GT(aux.bbox()[3], modal.bbox()[3] + 10);
  // A shrinking diagnosis adds nothing.
  const Diagnosis up = diagnose(obb, g, Vec3(0, -0.05, 0), Vec3::Zero());
  EXPECT_EQ(auxiliary_crop_mask(cam, modal, up).count(), modal.count());
}
