// Tests the plane step (planes.h): RANSAC against a known plane with outliers, DBSCAN orientation
// clusters, floor + two walls + a non-orthogonal wall under a pitched camera (normals within 1 degree,
// the odd wall dropped, up from the wall pair), the lowest-plane fallback and the floor snap.
#include <gtest/gtest.h>

#include "pipeline/reconstruct/planes.h"
#include "reconstruct_test_util.h"
#include "tolerance.h"

using namespace simu::reconstruct;
using namespace simu::reconstruct::testing;

namespace {
// n_points on the plane {x : n.x = d} within `half` of `centre`, with Gaussian noise sigma along n.
Points plane_points(const Vec3& n, const Vec3& centre, double half, int n_points, double sigma, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-half, half);
  std::normal_distribution<double> g(0, sigma);
  const Vec3 e1 = n.unitOrthogonal(), e2 = n.cross(e1);
  Points P(n_points, 3);
  for (int i = 0; i < n_points; ++i) P.row(i) = (centre + u(rng) * e1 + u(rng) * e2 + g(rng) * n).transpose();
  return P;
}
Points stack(const Points& a, const Points& b) {
  Points out(a.rows() + b.rows(), 3);
  out << a, b;
  return out;
}
}  // namespace

// RANSAC finds a tilted plane among 30% outliers to well under a degree.
TEST(ReconstructPlanes, RansacFindsThePlaneAmongOutliers) {
  const Vec3 n = Vec3(0.2, -1, 0.3).normalized();
  Points in = plane_points(n, Vec3(0, 1, 3), 1.0, 1000, 0.003, 1);
  std::mt19937_64 rng(2);
  std::uniform_real_distribution<double> u(-1, 1);
  Points out(300, 3);
  for (int i = 0; i < 300; ++i) out.row(i) << u(rng), 1 + u(rng), 3 + u(rng);
  RansacConfig rc;
  rc.threshold = 0.01;
  auto f = ransac_plane(stack(in, out), rc);
  ASSERT_TRUE(f);
  // The refit over 1,000 inliers with 3 mm noise on a 1 m patch: the normal's standard error is
  // ~0.003 / (0.29 sqrt(1000)) rad = 0.02 degrees, the offset's 0.003 / sqrt(1000) = 0.1 mm; the bounds
  // are 25 and 30 times those. Inliers: 3 mm Gaussian noise leaves every point but ~1 in 10^3 within the
  // 1 cm threshold (3.3 sigma); of 300 uniform outliers in a 2 m cube ~1% (3) fall within 1 cm.
  EXPECT_LT(line_angle_deg(f->normal, n), 0.5);
  EXPECT_NEAR(std::abs(f->distance(Vec3(0, 1, 3))), 0.0, 0.003);
  EXPECT_GE(f->inliers, 990);
  EXPECT_LT(f->inliers, 1000 + 60);
}

// DBSCAN groups directions by line angle: 0, 5 and 180 degrees together, 90 and 92 together.
TEST(ReconstructPlanes, DbscanGroupsLines) {
  auto d = [](double deg) { return Vec3(std::cos(deg * M_PI / 180), 0, std::sin(deg * M_PI / 180)); };
  const auto lab = dbscan_directions({d(0), d(5), d(90), d(92), d(180)}, 10, 1);
  EXPECT_EQ(lab[0], lab[1]);
  EXPECT_EQ(lab[0], lab[4]);
  EXPECT_EQ(lab[2], lab[3]);
  EXPECT_NE(lab[0], lab[2]);
}

// A pitched camera sees a floor and two orthogonal walls, plus a wall 45 degrees off: up and every
// kept normal within 1 degree of the truth, the odd wall dropped with a message.
TEST(ReconstructPlanes, FloorAndWallsUnderAPitchedCamera) {
  const Mat3 Rr = rot(Vec3(1, 0, 0), 25) * rot(Vec3(0, 1, 0), 30);  // room -> camera
  const Vec3 up = Rr * Vec3(0, -1, 0), w1 = Rr * Vec3(0, 0, -1), w2 = Rr * Vec3(1, 0, 0), w3 = Rr * Vec3(1, 0, -1).normalized();
  const Points floor = plane_points(up, Rr * Vec3(0, 1.5, 3), 1.5, 3000, 0.01, 3);
  std::vector<WallInput> walls = {{"back", plane_points(w1, Rr * Vec3(0, 0, 4), 1.5, 3000, 0.002, 4)},
                                  {"left", plane_points(w2, Rr * Vec3(-2, 0, 2.5), 1.0, 2000, 0.002, 5)},
                                  {"odd", plane_points(w3, Rr * Vec3(-1.5, 0, 3.5), 0.5, 500, 0.002, 6)}};
  const PlanesResult r = fit_planes(floor, walls, Points(), Vec3::Zero());
  ASSERT_TRUE(r.floor);
  EXPECT_EQ(r.up_source, "walls");
  // Plane fits over >= 2,000 points with <= 1 cm noise on metre patches: normals within ~0.1 degree
  // (noise / (extent sqrt(n))), offsets within 0.2 mm; 1 degree and 1 cm are the acceptance of a
  // room's planes, far above both.
  EXPECT_LT(angle_deg(r.up, up), 1.0);
  EXPECT_LT(angle_deg(r.floor->plane.normal, up), 1.0);
  EXPECT_NEAR(r.floor->plane.distance(Rr * Vec3(0, 1.5, 3)), 0.0, 0.01);
  ASSERT_EQ(r.walls.size(), 2u);
  EXPECT_EQ(r.walls[0].id, "back");  // by coverage
  EXPECT_LT(angle_deg(r.walls[0].plane.normal, w1), 1.0);
  EXPECT_LT(angle_deg(r.walls[1].plane.normal, w2), 1.0);
  for (auto& w : r.walls) EXPECT_NEAR(w.plane.normal.dot(r.up), 0.0, simu::testing::kFp64Solve);
  bool said = false;
  for (auto& m : r.messages) said |= m.find("wall odd") != std::string::npos && m.find("not orthogonal") != std::string::npos;
  EXPECT_TRUE(said);
}

// Only a floor: up is the floor's normal (pointing up, towards -y); a lone wall keeps its normal
// perpendicular to it.
TEST(ReconstructPlanes, FloorDecidesUpWithoutAWallPair) {
  const Vec3 up = rot(Vec3(1, 0, 0), 15) * Vec3(0, -1, 0);
  const PlanesResult r = fit_planes(plane_points(up, Vec3(0, 1.4, 3), 1.5, 2000, 0.01, 7), {}, Points(), Vec3::Zero());
  ASSERT_TRUE(r.floor);
  EXPECT_EQ(r.up_source, "floor");
  EXPECT_LT(angle_deg(r.up, up), 1.0);  // 2,000 points, 1 cm noise over 1.5 m: ~0.1 degree
}

// No floor mask: the lowest upward-facing plane of the point map is the floor, and the result says so;
// a wall-only mask that fails (too few points) is reported, not fatal.
TEST(ReconstructPlanes, FallbackToTheLowestSupportedPlane) {
  const Vec3 up(0, -1, 0);
  const Points all = stack(plane_points(up, Vec3(0, 1.5, 3), 1.5, 3000, 0.005, 8),      // floor
                           plane_points(up, Vec3(0.3, 0.7, 2.5), 0.4, 1500, 0.003, 9));  // table top
  std::vector<WallInput> walls = {{"tiny", plane_points(Vec3(0, 0, -1), Vec3(0, 0, 4), 0.1, 10, 0.001, 10)}};
  const PlanesResult r = fit_planes(Points(), walls, all, Vec3::Zero());
  ASSERT_TRUE(r.floor);
  EXPECT_TRUE(r.fallback);
  EXPECT_NEAR(r.floor->plane.distance(Vec3(0, 1.5, 3)), 0.0, 0.01);  // 3,000 points, 5 mm noise: ~0.1 mm
  bool said_floor = false, said_wall = false;
  for (auto& m : r.messages) {
    said_floor |= m.find("lowest supported plane") != std::string::npos;
    said_wall |= m.find("wall tiny") != std::string::npos;
  }
  EXPECT_TRUE(said_floor);
  EXPECT_TRUE(said_wall);
}

// The floor snap moves the floor along up to the lowest mesh vertex.
TEST(ReconstructPlanes, FloorSnapsToTheLowestMeshVertex) {
  PlanesResult r;
  r.up = Vec3(0, -1, 0);
  r.floor = NamedPlane{"floor", PlaneFit{Vec3(0, 1.5, 3), r.up, 0, 0}};
  Points a(2, 3), b(1, 3);
  a << 0, 1.2, 3, 0, 1.47, 3;  // lowest: y = 1.47 (height -1.47)
  b << 1, 1.3, 2;
  EXPECT_NEAR(snap_floor_to_meshes(r, {a, b}), 0.03, simu::testing::kFp64Chain);
  EXPECT_NEAR(r.floor->plane.distance(Vec3(0, 1.47, 0)), 0.0, simu::testing::kFp64Chain);
  // A mesh far below the floor (a wrong lift) does not drag the floor: refused with a message.
  Points deep(1, 3);
  deep << 0, 2.5, 3;
  EXPECT_EQ(snap_floor_to_meshes(r, {a, deep}), 0.0);
  EXPECT_NEAR(r.floor->plane.distance(Vec3(0, 1.47, 0)), 0.0, simu::testing::kFp64Chain);
  EXPECT_NE(r.messages.back().find("floor snap refused"), std::string::npos);
}
