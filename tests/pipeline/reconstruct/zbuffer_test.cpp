// Tests the reconstruct z-buffer: depth of a fronto-parallel and a slanted quad against the analytic
// ray-plane intersection, vertex visibility of a box, the densifier.
#include <gtest/gtest.h>

#include <map>

#include "pipeline/reconstruct/zbuffer.h"
#include "reconstruct_test_util.h"
#include "tolerance.h"

using namespace simu::reconstruct;
using namespace simu::reconstruct::testing;

// A slanted quad's depth at every drawn pixel equals the ray-plane intersection.
TEST(ReconstructZbuffer, SlantedQuadDepthIsTheRayPlaneIntersection) {
  const Pinhole K = camera(64, 48, 60);
  Points V(4, 3);
  V << -1, -1, 2, 1, -1, 3, 1, 1, 3, -1, 1, 2;  // plane x/2 - z = -2.5 ... z = 2.5 + x/2
  Faces F(2, 3);
  F << 0, 1, 2, 0, 2, 3;
  const auto d = render_depth(V, F, K);
  int drawn = 0;
  for (int r = 0; r < K.height; ++r)
    for (int c = 0; c < K.width; ++c) {
      const float z = d[size_t(r) * K.width + c];
      if (!std::isfinite(z)) continue;
      ++drawn;
      // Ray (a, b, 1) z; plane z = 2.5 + x / 2 -> z = 2.5 / (1 - a / 2).
      const double a = (c - K.cx) / K.fx;
      // A float32 depth buffer: ~10 fp32 roundings of z <= 3 (the interpolation, the stored value).
      EXPECT_NEAR(z, 2.5 / (1 - a / 2), 3 * simu::testing::gamma(10));
    }
  EXPECT_GT(drawn, 500);
}

// Of a box seen face-on, the four front corners are visible and the four back corners hidden.
TEST(ReconstructZbuffer, BoxBackCornersAreHidden) {
  const Pinhole K = camera();
  Points V;
  Faces F;
  box_mesh(Vec3(0.4, 0.4, 0.4), V, F);
  for (Eigen::Index i = 0; i < V.rows(); ++i) V(i, 2) += 2.0;
  const auto vis = visible_vertices(V, F, K, 0.01);
  ASSERT_EQ(vis.size(), 4u);
  for (auto i : vis) EXPECT_LT(V(i, 2), 2.0);
}

// Densifying keeps the surface (every new vertex lies on an input face), bounds the edge length and
// keeps the mesh watertight (every edge shared by two triangles).
TEST(ReconstructZbuffer, DensifyBoundsEdgesAndKeepsTheSurface) {
  Points V;
  Faces F;
  box_mesh(Vec3(1, 0.5, 0.25), V, F);
  densify(V, F, 0.1);
  std::map<std::pair<int, int>, int> edges;
  for (Eigen::Index f = 0; f < F.rows(); ++f)
    for (int e = 0; e < 3; ++e) {
      int a = F(f, e), b = F(f, (e + 1) % 3);
      EXPECT_LE((V.row(a) - V.row(b)).norm(), 0.1 + simu::testing::kFp64Chain);
      ++edges[{std::min(a, b), std::max(a, b)}];
    }
  for (auto& [e, n] : edges) EXPECT_EQ(n, 2);
  for (Eigen::Index i = 0; i < V.rows(); ++i) {
    // On the box surface: some coordinate at its half extent.
    const bool on = std::abs(std::abs(V(i, 0)) - 0.5) < simu::testing::kFp64Chain || std::abs(std::abs(V(i, 1)) - 0.25) < simu::testing::kFp64Chain ||
                    std::abs(std::abs(V(i, 2)) - 0.125) < simu::testing::kFp64Chain;
    EXPECT_TRUE(on);
  }
}
