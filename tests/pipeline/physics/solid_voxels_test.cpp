// Filled voxel occupancy and voxel IoU (solid_voxels.h) against counts and box volumes worked out by
// hand: boxes whose faces lie on voxel centres (exact counts), open and closed shells, arbitrary boxes
// within the volume bounds of a one-voxel dilation, and the separating-axis triangle-box test.
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/solid_voxels.h"
#include "test_files.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>

using namespace simu::physics;

namespace {

// An axis-aligned box mesh [lo, hi].
Mesh box_between(const Vec3& lo, const Vec3& hi) {
  Mesh m = box_mesh(0.5 * (hi - lo));
  for (Eigen::Index i = 0; i < m.V.rows(); ++i) m.V.row(i) += 0.5 * (lo + hi).transpose();
  return m;
}

// Volume of the intersection of two boxes.
double overlap_volume(const Vec3& alo, const Vec3& ahi, const Vec3& blo, const Vec3& bhi) {
  return (ahi.cwiseMin(bhi) - alo.cwiseMax(blo)).cwiseMax(Vec3::Zero()).prod();
}

}  // namespace

// Faces on voxel centre planes: a box from (a + 0.5) h to (b + 0.5) h fills voxels a..b exactly (each
// face plane lies inside one layer, h / 2 from both of its boundaries), so the voxel IoU of two such
// boxes is the IoU of the boxes grown by h / 2, by counting.
TEST(SolidVoxels, OffsetBoxesOnVoxelCentresCountExactly) {
  const double h = 0.01;
  auto face = [&](int k) { return (k + 0.5) * h; };
  const Mesh a = box_between(Vec3(face(0), face(0), face(0)), Vec3(face(10), face(10), face(10)));
  const Mesh b = box_between(Vec3(face(3), face(2), face(0)), Vec3(face(13), face(12), face(10)));
  const SolidIou r = solid_iou(a, b, h);
  EXPECT_EQ(r.h, h);
  EXPECT_EQ(r.a, 11 * 11 * 11);
  EXPECT_EQ(r.b, 11 * 11 * 11);
  EXPECT_EQ(r.both, 8 * 9 * 11);  // x: voxels 3..10, y: 2..10, z: 0..10
  const double expected = 8.0 * 9 * 11 / (2.0 * 11 * 11 * 11 - 8 * 9 * 11);
  // Two integer counts divided: one rounding of the quotient (2^-53 relative).
  EXPECT_NEAR(r.iou, expected, 1e-15);
  // The analytic IoU of the boxes themselves (sides 10 h, offsets 3 h, 2 h, 0) differs by the h / 2 growth:
  // 560 / 1440 = 0.3889 against 792 / 1870 = 0.4235.
  EXPECT_NEAR(7.0 * 8 * 10 / (2000.0 - 560), 0.3889, 1e-4);
  EXPECT_GT(r.iou, 0.42);
}

// Arbitrary boxes: the filled voxels contain the box and lie inside it grown by h on every side, so
// the voxel IoU is within [|A n B| / |A_h u B_h|, |A_h n B_h| / |A u B|] of the true and grown boxes.
TEST(SolidVoxels, ArbitraryBoxesWithinDilationBounds) {
  const double h = 0.004;
  const Vec3 alo(0.0123, -0.0311, 0.2047), ahi(0.1377, 0.0522, 0.3101);
  const Vec3 d(0.0418, -0.0173, 0.0252);
  const Vec3 blo = alo + d, bhi = ahi + d;
  const SolidIou r = solid_iou(box_between(alo, ahi), box_between(blo, bhi), h);
  const Vec3 g = Vec3::Constant(h);
  const double inter = overlap_volume(alo, ahi, blo, bhi), inter_h = overlap_volume(alo - g, ahi + g, blo - g, bhi + g);
  const double vol = (ahi - alo).prod(), vol_h = (ahi - alo + 2 * g).prod();
  const double lo = inter / (2 * vol_h - inter_h), hi = inter_h / (2 * vol - inter);
  EXPECT_GE(r.iou, lo);
  EXPECT_LE(r.iou, hi);
  // The voxel volumes obey the same inclusions.
  EXPECT_GE(r.a * h * h * h, vol * (1 - 1e-12));
  EXPECT_LE(r.a * h * h * h, vol_h * (1 + 1e-12));
}

// Closed shells are solid; a box without its top is its walls (the inside is reachable through the
// opening); identical meshes have IoU 1; disjoint ones 0 without voxelising.
TEST(SolidVoxels, FilledMeansEnclosed) {
  const double h = 0.01;
  auto face = [&](int k) { return (k + 0.5) * h; };
  const Mesh closed = box_between(Vec3::Constant(face(0)), Vec3::Constant(face(10)));
  EXPECT_EQ(voxelize_solid(closed, h).count, 11 * 11 * 11);
  // Drop the two triangles of the +y face.
  Mesh open = closed;
  std::vector<Eigen::Vector3i> kept;
  for (Eigen::Index f = 0; f < closed.F.rows(); ++f) {
    bool top = true;
    for (int k = 0; k < 3; ++k) top &= closed.V(closed.F(f, k), 1) > face(9);
    if (!top) kept.push_back(closed.F.row(f).transpose());
  }
  ASSERT_EQ(kept.size(), 10u);
  open.F.resize(kept.size(), 3);
  for (size_t f = 0; f < kept.size(); ++f) open.F.row(f) = kept[f].transpose();
  // The 11^3 block less its 9^3 interior and less the 9 x 9 top layer's interior (no face there).
  EXPECT_EQ(voxelize_solid(open, h).count, 11 * 11 * 11 - 9 * 9 * 9 - 9 * 9);

  const SolidIou same = solid_iou(closed, closed, h);
  EXPECT_EQ(same.iou, 1.0);
  Mesh far = closed;
  far.V.col(0).array() += 1.0;
  const SolidIou apart = solid_iou(closed, far, h);
  EXPECT_EQ(apart.iou, 0.0);
  EXPECT_EQ(apart.a, -1);
}

// A grid over max_voxels grows the spacing for both meshes until it fits, and says so.
TEST(SolidVoxels, SpacingGrowsToFitTheLimit) {
  const Mesh a = box_between(Vec3::Zero(), Vec3(0.5, 0.5, 0.5));
  const SolidIou r = solid_iou(a, a, 0.001, 40 * 40 * 40);
  EXPECT_GT(r.h, 0.001);
  // A side of 0.5 spans at least 0.5 / h - 1 cell boundaries, so at least 0.5 / h cells, plus two of
  // padding: (0.5 / h + 2)^3 <= 40^3 needs h >= 0.5 / 38.
  EXPECT_GE(r.h, 0.5 / 38);
  EXPECT_EQ(r.iou, 1.0);
  // voxelize_solid itself refuses, naming the grid.
  EXPECT_NE(simu::testing::error_of([&] { voxelize_solid(a, 0.001, 1000); }).find("exceeds 1000 voxels"),
            std::string::npos);
}

// The separating-axis test on cases whose answer is plain geometry: a triangle through the box, one
// beside it, one whose bounds overlap the box but whose plane passes the corner by (plane axis), and
// one separated only by an edge cross-product axis.
TEST(SolidVoxels, TriangleBoxOverlapCases) {
  const Vec3 c = Vec3::Zero(), half = Vec3::Constant(0.5);
  EXPECT_TRUE(triangle_box_overlap(c, half, Vec3(-2, 0, -2), Vec3(2, 0, -2), Vec3(0, 0, 2)));
  EXPECT_FALSE(triangle_box_overlap(c, half, Vec3(0.6, 0, 0), Vec3(2, 0, 0), Vec3(1, 1, 0)));
  // Plane x + y + z = 1.6 (> 1.5, the corner's value): bounds overlap, the plane misses.
  EXPECT_FALSE(triangle_box_overlap(c, half, Vec3(1.6, 0, 0), Vec3(0, 1.6, 0), Vec3(0, 0, 1.6)));
  EXPECT_TRUE(triangle_box_overlap(c, half, Vec3(1.4, 0, 0), Vec3(0, 1.4, 0), Vec3(0, 0, 1.4)));
  // A sliver in the plane z = 0 along the line x + y = 1.2 (the box's corner region ends at x + y = 1):
  // its bounds and plane overlap the box, the edge-axis (z x edge) separates it.
  EXPECT_FALSE(triangle_box_overlap(c, half, Vec3(1.2, 0, 0), Vec3(0, 1.2, 0), Vec3(0.6, 0.61, 0)));
  // Touching counts: a triangle in the box's face plane x = 0.5.
  EXPECT_TRUE(triangle_box_overlap(c, half, Vec3(0.5, -1, -1), Vec3(0.5, 1, -1), Vec3(0.5, 0, 1)));
}
