// Surface samples and point-to-surface distances (surface_distance.h) against closed-form answers:
// the closest point in each Voronoi region of a triangle, the distance to a box from outside and
// inside, the hierarchy against a brute-force minimum, samples on the surface and spread by area.
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/surface_distance.h"
#include "pipeline/physics/synthetic.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>

using namespace simu::physics;

// Each region of triangle (0,0,0), (1,0,0), (0,1,0) with the closest point worked out by hand.
TEST(SurfaceDistance, ClosestPointRegions) {
  const Vec3 a(0, 0, 0), b(1, 0, 0), c(0, 1, 0);
  auto cp = [&](const Vec3& p) { return closest_point_on_triangle(p, a, b, c); };
  // Exact in binary floating point: every operand and result is a small dyadic rational.
  const double tol = 1e-15;
  EXPECT_LT((cp(Vec3(-1, -1, 2)) - a).norm(), tol);                     // vertex a
  EXPECT_LT((cp(Vec3(2, -0.5, 0)) - b).norm(), tol);                    // vertex b
  EXPECT_LT((cp(Vec3(-0.5, 2, 1)) - c).norm(), tol);                    // vertex c
  EXPECT_LT((cp(Vec3(0.5, -1, 3)) - Vec3(0.5, 0, 0)).norm(), tol);      // edge ab
  EXPECT_LT((cp(Vec3(-2, 0.25, 0)) - Vec3(0, 0.25, 0)).norm(), tol);    // edge ac
  EXPECT_LT((cp(Vec3(1, 1, -1)) - Vec3(0.5, 0.5, 0)).norm(), tol);      // edge bc
  EXPECT_LT((cp(Vec3(0.25, 0.25, 5)) - Vec3(0.25, 0.25, 0)).norm(), tol);  // face
}

// Distance to a box [-e/2, e/2]: outside, the norm of (|p| - e/2)_+; inside, the nearest face.
TEST(SurfaceDistance, BoxDistancesInsideAndOutside) {
  const Vec3 e(0.4, 0.2, 0.1);
  const SurfaceDistance box(box_mesh(0.5 * e));
  const Vec3 pts[] = {{0.5, 0.0, 0.0}, {0.3, 0.25, 0.0}, {-0.3, 0.2, -0.1}, {0.05, 0.02, 0.01}, {0.0, -0.09, 0.0}};
  for (const Vec3& p : pts) {
    const Vec3 out = (p.cwiseAbs() - 0.5 * e).cwiseMax(Vec3::Zero());
    const double expected = out.norm() > 0 ? out.norm() : (0.5 * e - p.cwiseAbs()).minCoeff();
    // Sums and differences of a few values below 1: a few ulps of 1 (2^-52 each).
    EXPECT_NEAR(box.distance(p), expected, 1e-15) << p.transpose();
  }
}

// The hierarchy's pruning never changes the answer: equal to the minimum over every triangle.
TEST(SurfaceDistance, HierarchyEqualsBruteForce) {
  const Mesh m = lathe_mesh({{-0.5, 0.1}, {-0.2, 0.3}, {0.1, 0.35}, {0.5, 0.2}}, 20);
  const SurfaceDistance fast(m);
  const Points probes = sample_surface(box_mesh(Vec3(0.6, 0.7, 0.5)), 300, 5);
  for (Eigen::Index i = 0; i < probes.rows(); ++i) {
    const Vec3 p = probes.row(i).transpose();
    double best = std::numeric_limits<double>::infinity();
    for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
      const Vec3 q = closest_point_on_triangle(p, m.V.row(m.F(f, 0)).transpose(), m.V.row(m.F(f, 1)).transpose(),
                                               m.V.row(m.F(f, 2)).transpose());
      best = std::min(best, (q - p).norm());
    }
    // The same triangles and arithmetic: identical results.
    EXPECT_EQ(fast.distance(p), best);
  }
}

// Samples lie on the surface, spread over a box's faces in proportion to their areas, and repeat
// for a seed.
TEST(SurfaceDistance, SamplesOnSurfaceByArea) {
  const Vec3 e(0.5, 0.3, 0.1);
  const Mesh box = box_mesh(0.5 * e);
  const int64_t n = 20000;
  const Points p = sample_surface(box, n, 11);
  const SurfaceDistance d(box);
  int64_t on_x = 0;
  for (Eigen::Index i = 0; i < n; ++i) {
    // A convex combination of three vertices: within a few ulps of 0.5 (2^-53 each) of the face.
    EXPECT_LT(d.distance(p.row(i).transpose()), 1e-15);
    on_x += std::abs(std::abs(p(i, 0)) - 0.5 * e.x()) < 1e-12;
  }
  // The two x faces hold 2 * 0.3 * 0.1 of the area 2 (0.15 + 0.05 + 0.03): share q = 0.1304. The count
  // is binomial: 6 standard deviations sqrt(q (1 - q) / n) = 0.0143 bound a false failure below 1e-8.
  const double q = 0.03 / 0.23;
  EXPECT_NEAR(static_cast<double>(on_x) / n, q, 6 * std::sqrt(q * (1 - q) / n));
  EXPECT_EQ(sample_surface(box, 50, 11), p.topRows(50));
  EXPECT_NE(sample_surface(box, 50, 12), p.topRows(50));
  EXPECT_NEAR(surface_area(box), 2 * 0.23, 1e-15);
}
