// Mesh files, convex hulls, convex decomposition and mass properties against closed-form answers.
#include <gtest/gtest.h>

#include <filesystem>

#include "common/error.h"
#include "pipeline/physics/collision.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/physics_test_util.h"
#include "tolerance.h"

using namespace simu::physics;

namespace {
// An L-shaped prism: unit square minus its upper-right 0.6 x 0.6 corner, 0.4 thick.
// Area 1 - 0.36 = 0.64, volume 0.256. Vertex 0 is the reflex corner (fan-triangulable from it).
Mesh l_prism() {
  return prism_mesh({{0.4, 0.4}, {0.4, 1}, {0, 1}, {0, 0}, {1, 0}, {1, 0.4}}, 0.2);
}
}  // namespace

TEST(Mesh, FileRoundTripObjPlyGlb) {
  const auto dir = simu::testing::physics_temp_dir("mesh_io");
  const Mesh box = box_mesh(Vec3(0.5, 0.25, 0.1));
  for (const char* ext : {".obj", ".ply", ".glb"}) {
    const std::string path = dir + "/box" + ext;
    write_mesh(box, path);
    const Mesh back = read_mesh(path);
    EXPECT_EQ(back.F.rows(), 12) << ext;
    // The files hold fp32 coordinates (|v| <= 0.5 exact here, but a format may round): one fp32 rounding
    // per coordinate moves the volume by 3 u of it and a corner by u |v|.
    EXPECT_NEAR(signed_volume(back), 1.0 * 0.5 * 0.2, 0.1 * simu::testing::gamma(3)) << ext;  // winding kept
    const auto b = mesh_aabb(back);
    EXPECT_NEAR((b.max - Vec3(0.5, 0.25, 0.1)).norm(), 0.0, 0.6 * simu::testing::kFp32Unit) << ext;
  }
  EXPECT_THROW(read_mesh(dir + "/missing.obj"), simu::Error);
  EXPECT_THROW(write_mesh(box, dir + "/box.xyz"), simu::Error);
}

TEST(Mesh, PrismVolumeAndCanonicalize) {
  Mesh l = l_prism();
  EXPECT_NEAR(signed_volume(l), 0.64 * 0.4, simu::testing::kFp64Chain);
  const double f = canonicalize(l);
  EXPECT_NEAR(f, 1.0, simu::testing::kFp64Chain);
  EXPECT_NEAR(mesh_aabb(l).center().norm(), 0.0, simu::testing::kFp64Chain);
  EXPECT_NE(mesh_problem(Mesh{}), "");
}

// Box a x b x c, density rho: m = rho abc, I_xx = m (b^2 + c^2) / 12, centre of mass at the shift.
TEST(Collision, MassPropertiesOfABoxMatchClosedForm) {
  Mesh box = box_mesh(Vec3(0.1, 0.2, 0.3));
  const Vec3 shift(0.3, -0.2, 1.0);
  for (Eigen::Index i = 0; i < box.V.rows(); ++i) box.V.row(i) += shift.transpose();
  const auto p = mass_properties({box}, 1000.0);
  const double m = 1000.0 * 0.2 * 0.4 * 0.6;
  EXPECT_NEAR(p.mass, m, simu::testing::kFp64Solve);
  EXPECT_NEAR((p.com - shift).norm(), 0.0, simu::testing::kFp64Chain);
  EXPECT_NEAR(p.inertia(0, 0), m * (0.16 + 0.36) / 12, simu::testing::kFp64Solve);
  EXPECT_NEAR(p.inertia(1, 1), m * (0.04 + 0.36) / 12, simu::testing::kFp64Solve);
  EXPECT_NEAR(p.inertia(2, 2), m * (0.04 + 0.16) / 12, simu::testing::kFp64Solve);
  EXPECT_NEAR(p.inertia(0, 1), 0.0, simu::testing::kFp64Solve);
  // Two halves give the same answer as the whole.
  const auto a = mass_properties({box_mesh(Vec3(0.5, 0.5, 0.25))}, 1.0);
  EXPECT_NEAR(a.volume, 0.5, simu::testing::kFp64Chain);
}

TEST(Collision, ConvexHullIsClosedAndOutward) {
  Eigen::Matrix<double, -1, 3, Eigen::RowMajor> pts(58, 3);
  pts.topRows(8) = box_mesh(Vec3::Constant(0.5)).V;
  pts.bottomRows(50).setRandom();
  pts.bottomRows(50) *= 0.45;
  const Mesh h = convex_hull(pts);
  EXPECT_EQ(h.V.rows(), 8);
  EXPECT_NEAR(signed_volume(h), 1.0, simu::testing::kFp64Solve);
  // Every face normal points away from the centre.
  for (Eigen::Index i = 0; i < h.F.rows(); ++i) {
    const Vec3 a = h.V.row(h.F(i, 0)), b = h.V.row(h.F(i, 1)), c = h.V.row(h.F(i, 2));
    EXPECT_GT((b - a).cross(c - a).dot((a + b + c) / 3), 0);
  }
  Eigen::Matrix<double, -1, 3, Eigen::RowMajor> flat(4, 3);
  flat << 0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0;
  EXPECT_THROW(convex_hull(flat), simu::Error);
}

// CoACD splits the L into convex parts whose volumes add up to the L's (a single hull would be 0.4
// for the convex hull, 28% too much).
TEST(Collision, DecompositionOfAnLShape) {
  Mesh l = l_prism();
  canonicalize(l);
  CollisionConfig cfg;
  cfg.cache_dir = simu::testing::physics_temp_dir("hull_cache");
  const auto shape = decompose(l, cfg);
  double vol = 0;
  for (const auto& h : shape.hulls) {
    const double v = signed_volume(h);
    EXPECT_GT(v, 0);
    vol += v;
  }
#ifdef SIMU_HAVE_COACD
  EXPECT_EQ(shape.method, "coacd");
  EXPECT_GE(shape.hulls.size(), 2u);
  // CoACD's decomposition is approximate by design: its concavity threshold (0.05 of the size here)
  // lets each hull bulge over the concave corner; 15% of the volume covers the hulls it makes.
  EXPECT_NEAR(vol, 0.256, 0.256 * 0.15);
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(cfg.cache_dir), std::filesystem::directory_iterator{}), 1);
#else
  EXPECT_NEAR(vol, 0.328, simu::testing::kFp64Solve);
#endif
  // Without CoACD: the whole convex hull, the unit square minus the corner triangle beyond the
  // segment (1, 0.4)-(0.4, 1): area 1 - 0.18 = 0.82, volume 0.328.
  cfg.use_coacd = false;
  const auto one = decompose(l, cfg);
  ASSERT_EQ(one.hulls.size(), 1u);
  EXPECT_NEAR(signed_volume(one.hulls[0]), 0.328, simu::testing::kFp64Solve);
}

// A flat mesh (one quad) cannot be a MuJoCo mesh; it is thickened to min_thickness.
TEST(Collision, FlatMeshIsThickened) {
  Mesh quad;
  quad.V.resize(4, 3);
  quad.V << -0.5, -0.5, 0, 0.5, -0.5, 0, 0.5, 0.5, 0, -0.5, 0.5, 0;
  quad.F.resize(2, 3);
  quad.F << 0, 1, 2, 0, 2, 3;
  CollisionConfig cfg;
  cfg.use_coacd = false;
  const auto s = decompose(quad, cfg);
  ASSERT_EQ(s.hulls.size(), 1u);
  EXPECT_EQ(s.method, "hull+thickened");
  EXPECT_NEAR(signed_volume(s.hulls[0]), cfg.min_thickness, simu::testing::kFp64Solve);
#ifdef SIMU_HAVE_COACD
  // CoACD remeshes the open quad into a thin solid of its own; still a usable positive volume.
  cfg.use_coacd = true;
  const auto c = decompose(quad, cfg);
  ASSERT_FALSE(c.hulls.empty());
  for (const auto& h : c.hulls) EXPECT_GT(signed_volume(h), 0);
#endif
}

// A convex mesh (a box) is its own single hull without decomposition; an L prism is not convex.
// An affine image of a decomposed mesh gets the mapped hulls: volume scales by |det A|.
TEST(Collision, ConvexShortcutAndAffineMapping) {
  using namespace simu::physics;
  const Mesh box = box_mesh(Vec3(0.5, 0.3, 0.2));
  EXPECT_TRUE(is_closed_oriented(box));
  const CollisionShape s = decompose(box);
  EXPECT_EQ(s.method, "convex");
  ASSERT_EQ(s.hulls.size(), 1u);
  EXPECT_NEAR(mass_properties(s.hulls, 1.0).volume, 1.0 * 0.6 * 0.4, simu::testing::kFp64Chain);
  Mesh open = box;
  open.F.conservativeResize(11, 3);  // one triangle missing
  EXPECT_FALSE(is_closed_oriented(open));
  const Mesh ell = prism_mesh({{0.5, 0.5}, {0.5, 1}, {0, 1}, {0, 0}, {1, 0}, {1, 0.5}}, 0.25);
  const CollisionShape se = decompose(ell);
  EXPECT_NE(se.method, "convex");
  // Affine image: x -> diag(1, 2, 0.5) x + (0.1, 0, 0), det = 1.
  Mesh stretched = ell;
  stretched.V = (ell.V * Vec3(1, 2, 0.5).asDiagonal()).rowwise() + Eigen::RowVector3d(0.1, 0, 0);
  const auto mapped = map_shape(ell, stretched, se);
  ASSERT_TRUE(mapped.has_value());
  EXPECT_EQ(mapped->hulls.size(), se.hulls.size());
  EXPECT_NEAR(mass_properties(mapped->hulls, 1.0).volume, mass_properties(se.hulls, 1.0).volume, simu::testing::kFp64Solve);
  // Not an affine image (one vertex moved): no mapping.
  Mesh bent = stretched;
  bent.V(0, 0) += 0.05;
  EXPECT_FALSE(map_shape(ell, bent, se).has_value());
}
