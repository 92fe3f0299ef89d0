// The world-frame 3D metrics (shape_metrics.h) and the symmetry-aware rotation error (symmetry.h)
// against independent math: the ground truth as its own prediction (IoU 1, F 1, errors 0), a sphere
// against a scaled sphere (Chamfer |k - 1| r within the tessellation's bounds), a translated and a
// scaled copy, and the rotation error of shapes whose symmetry groups are known (cylinder, box,
// cube, cone, sphere, an L-shaped prism with none).
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/shape_metrics.h"
#include "pipeline/physics/surface_distance.h"
#include "pipeline/physics/synthetic.h"

#include <gtest/gtest.h>

#include <cmath>
#include <map>

using namespace simu::physics;

namespace {

constexpr double kPi = 3.14159265358979323846;

// An icosahedron subdivided `levels` times, vertices on the sphere of radius r about the origin.
Mesh icosphere(double r, int levels) {
  const double t = (1 + std::sqrt(5.0)) / 2;
  std::vector<Vec3> v{{-1, t, 0}, {1, t, 0}, {-1, -t, 0}, {1, -t, 0}, {0, -1, t}, {0, 1, t},
                      {0, -1, -t}, {0, 1, -t}, {t, 0, -1}, {t, 0, 1}, {-t, 0, -1}, {-t, 0, 1}};
  std::vector<Eigen::Vector3i> f{{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11}, {1, 5, 9}, {5, 11, 4},
                                 {11, 10, 2}, {10, 7, 6}, {7, 1, 8},  {3, 9, 4},  {3, 4, 2},   {3, 2, 6}, {3, 6, 8},
                                 {3, 8, 9},  {4, 9, 5},  {2, 4, 11}, {6, 2, 10}, {8, 6, 7},   {9, 8, 1}};
  for (int l = 0; l < levels; ++l) {
    std::map<std::pair<int, int>, int> mid;
    auto midpoint = [&](int a, int b) {
      const auto key = std::minmax(a, b);
      auto it = mid.find(key);
      if (it != mid.end()) return it->second;
      v.push_back(0.5 * (v[a] + v[b]));
      return mid[key] = static_cast<int>(v.size()) - 1;
    };
    std::vector<Eigen::Vector3i> g;
    for (const auto& tri : f) {
      const int ab = midpoint(tri[0], tri[1]), bc = midpoint(tri[1], tri[2]), ca = midpoint(tri[2], tri[0]);
      g.insert(g.end(), {{tri[0], ab, ca}, {tri[1], bc, ab}, {tri[2], ca, bc}, {ab, bc, ca}});
    }
    f = g;
  }
  Mesh m;
  m.V.resize(v.size(), 3);
  for (size_t i = 0; i < v.size(); ++i) m.V.row(i) = (r * v[i].normalized()).transpose();
  m.F.resize(f.size(), 3);
  for (size_t i = 0; i < f.size(); ++i) m.F.row(i) = f[i].transpose();
  return m;
}

// The smallest distance of a face plane from the origin (the inscribed radius of a convex mesh about it).
double inscribed_radius(const Mesh& m) {
  double r = std::numeric_limits<double>::infinity();
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    const Vec3 a = m.V.row(m.F(f, 0)), b = m.V.row(m.F(f, 1)), c = m.V.row(m.F(f, 2));
    r = std::min(r, std::abs((b - a).cross(c - a).normalized().dot(a)));
  }
  return r;
}

Mat3 rot(const Vec3& axis, double deg) { return axis_rotation(axis, deg * kPi / 180.0); }

PlacedShape placed(const Mesh& canonical, const Vec3& scale, const Mat3& R, const Vec3& t) {
  PlacedShape s;
  s.canonical = canonical;
  s.scale = scale, s.R = R, s.t = t;
  return s;
}

// A small fast configuration (fewer samples than eval_lift's default).
ShapeMetricsConfig quick() {
  ShapeMetricsConfig c;
  c.samples = 3000;
  c.symmetry.samples = 600;
  return c;
}

}  // namespace

// The ground truth fed back as the prediction: every metric at its ideal value.
TEST(ShapeMetrics, GroundTruthAsPredictionIsPerfect) {
  Mesh bottle = lathe_mesh({{-0.5, 0.12}, {-0.3, 0.12}, {-0.1, 0.3}, {0.5, 0.3}}, 24);
  const PlacedShape gt = placed(bottle, Vec3::Constant(0.23), rot(Vec3(0.3, 1, 0.2), 37), Vec3(0.1, 0.4, 1.2));
  const ShapeMetrics m = shape_metrics(gt, gt, quick());
  EXPECT_EQ(m.iou, 1.0);
  ASSERT_EQ(m.fscore.size(), 2u);
  EXPECT_EQ(m.fscore[0].f, 1.0);
  EXPECT_EQ(m.fscore[1].f, 1.0);
  // Samples are convex combinations of world vertices (|x| < 2): a few ulps of 2 (2^-51 each).
  EXPECT_LT(m.chamfer, 1e-14);
  // acos near 1 turns rounding of the trace (~1e-16) into sqrt(2e-16) = 1.5e-8 rad = 8.5e-7 degrees.
  EXPECT_LT(m.rot_err_deg, 1e-5);
  EXPECT_EQ(m.trans_err, 0.0);
  EXPECT_EQ(m.scale_err_pct, 0.0);
  EXPECT_EQ(m.symmetry, "axial");  // a bottle: round, not flippable
  // The IoU lattice resolves the 23 cm object with 50 voxels across: 4.6 mm.
  EXPECT_NEAR(m.iou_voxel, 0.23 / 50, 1e-15);
}

// Concentric spheres r and k r: every point of one is |k - 1| r from the other. The meshes are
// inscribed polyhedra with vertices at radius R_i and faces no nearer than rho_i R_i (rho = the
// inscribed radius / R), so each distance lies in [k r rho - r, k r - r rho] (a point of the inner mesh
// sits at radius [r rho, r] inside the convex outer one, whose boundary along any ray lies at
// [k r rho, k r]; likewise outward), and so do both means and the Chamfer distance.
TEST(ShapeMetrics, SphereAgainstScaledSphere) {
  const double r = 0.1, k = 1.05;
  const Mesh unit = icosphere(0.5, 3);  // canonical: longest side 1
  const double rho = inscribed_radius(unit) / 0.5;
  const PlacedShape gt = placed(unit, Vec3::Constant(2 * r), Mat3::Identity(), Vec3(0.3, 0.1, 1.0));
  const PlacedShape pred = placed(unit, Vec3::Constant(2 * r * k), rot(Vec3(1, 2, 3), 50), Vec3(0.3, 0.1, 1.0));
  const ShapeMetrics m = shape_metrics(pred, gt, quick());
  const double lo = k * r * rho - r, hi = k * r - r * rho;
  ASSERT_LT(hi, 0.01);  // rho = 0.9935 at three subdivisions: [4.3, 5.7] mm
  EXPECT_GE(m.chamfer, lo);
  EXPECT_LE(m.chamfer, hi);
  // Every distance is below 1 cm: F@1cm and F@2cm are exactly 1.
  EXPECT_EQ(m.fscore[0].f, 1.0);
  EXPECT_EQ(m.fscore[1].f, 1.0);
  // A sphere has every rotation as a symmetry.
  EXPECT_EQ(m.symmetry, "spherical");
  EXPECT_EQ(m.rot_err_deg, 0.0);
  // Sizes 2 r k against 2 r: 5 % (rounding of two products and a quotient: ~1e-13 %).
  EXPECT_NEAR(m.scale_err_pct, 5.0, 1e-12);
  // The GT polyhedron A (between the balls of radius r rho and r) lies inside the prediction B (between
  // k r rho and k r). The filled voxels of each contain it and lie within d = h sqrt(3) of it, so
  // |A| <= |VA n VB| and |VA u VB| <= |B + d|: IoU >= (r rho)^3 / (k r + d)^3; and IoU <= |VA| / |VB|
  // <= (r + d)^3 / (k r rho)^3. (The polyhedra's own IoU is 1 / k^3 = 0.864.)
  const double d = m.iou_voxel * std::sqrt(3.0);
  EXPECT_GE(m.iou, std::pow(r * rho / (k * r + d), 3));
  EXPECT_LE(m.iou, std::pow((r + d) / (k * r * rho), 3));
  // A 3 cm gap: every distance is above 2 cm, so both F-scores are 0.
  const ShapeMetrics far = shape_metrics(placed(unit, Vec3::Constant(2 * (r + 0.03) / rho), Mat3::Identity(),
                                                gt.t), gt, quick());
  EXPECT_EQ(far.fscore[1].f, 0.0);
}

// A translated copy: the translation error is the offset, rotation and scale errors 0; a shift by
// 3 cm along x of a 10 cm cube leaves the IoU near 7/13 (boxes [0, 10] and [3, 13] cm: 700 / 1300).
TEST(ShapeMetrics, TranslatedCube) {
  const Mesh cube = box_mesh(Vec3::Constant(0.5));
  const PlacedShape gt = placed(cube, Vec3::Constant(0.1), Mat3::Identity(), Vec3(0.0051, 0.0052, 0.5053));
  PlacedShape pred = gt;
  pred.t.x() += 0.03;
  const ShapeMetrics m = shape_metrics(pred, gt, quick());
  EXPECT_NEAR(m.trans_err, 0.03, 1e-15);
  EXPECT_EQ(m.scale_err_pct, 0.0);
  EXPECT_LT(m.rot_err_deg, 1e-5);  // see GroundTruthAsPredictionIsPerfect
  EXPECT_EQ(m.symmetry, "discrete-24");
  // The voxel solid lies between the box and the box grown by h (SolidVoxels.ArbitraryBoxesWithinDilationBounds).
  const double h = m.iou_voxel;
  EXPECT_GE(m.iou, (0.07 * 0.01) / ((0.1 + 2 * h) * (0.1 + 2 * h) * (0.13 + 2 * h)));
  EXPECT_LE(m.iou, ((0.07 + 2 * h) * (0.1 + 2 * h) * (0.1 + 2 * h)) / (0.13 * 0.01));
  // The x faces are 3 cm apart: not within 2 cm, so neither score is 1; the other faces overlap.
  EXPECT_LT(m.fscore[1].f, 1.0);
  EXPECT_GT(m.fscore[1].f, 0.5);
}

// A cylinder turned about its own axis has no rotation error; tilted by 30 degrees, 30; flipped end
// over end, 0 (a cylinder's flip is a symmetry).
TEST(Symmetry, CylinderAboutItsAxis) {
  const Mesh cyl = lathe_mesh({{-0.5, 0.3}, {0.5, 0.3}}, 48);
  const Vec3 s = Vec3::Constant(0.2);
  const PlacedShape gt = placed(cyl, s, rot(Vec3(1, 0, 1), 20), Vec3::Zero());
  const Symmetry sym = find_symmetry(gt.scaled(), quick().symmetry);
  EXPECT_EQ(sym.describe(), "axial+flip");
  ASSERT_EQ(sym.axes.size(), 1u);
  EXPECT_NEAR(std::abs(sym.axes[0].y()), 1.0, 1e-12);
  // The axis images agree to rounding: acos of 1 - 1e-16 (see above), below 1e-5 degrees.
  EXPECT_LT(rotation_error_deg(gt.R * rot(Vec3::UnitY(), 40), gt.R, sym), 1e-5);
  EXPECT_LT(rotation_error_deg(gt.R * rot(Vec3::UnitX(), 180), gt.R, sym), 1e-5);
  // A tilt of the axis by 30 degrees: the angle between the axis images, 30 (acos rounding 1e-6 deg).
  EXPECT_NEAR(rotation_error_deg(gt.R * rot(Vec3::UnitX(), 30), gt.R, sym), 30.0, 1e-6);
}

// A truncated cone is round but not flippable: end over end is 180 degrees off.
TEST(Symmetry, ConeIsNotFlippable) {
  const Mesh cone = lathe_mesh({{-0.5, 0.05}, {0.5, 0.5}}, 48);
  const Symmetry sym = find_symmetry(cone, quick().symmetry);
  EXPECT_EQ(sym.describe(), "axial");
  EXPECT_NEAR(rotation_error_deg(rot(Vec3::UnitZ(), 180), Mat3::Identity(), sym), 180.0, 1e-6);
  EXPECT_LT(rotation_error_deg(rot(Vec3::UnitY(), 71), Mat3::Identity(), sym), 1e-5);
}

// A box with three different sides has the four rotations of D2 (identity and three half turns):
// half turns are free, a quarter turn costs 90. The same unit cube scaled to unequal sides is such a
// box (symmetry in the metric frame), and unscaled it is a cube with all 24.
TEST(Symmetry, BoxesAndCubes) {
  const Mesh cube = box_mesh(Vec3::Constant(0.5));
  const Symmetry box = find_symmetry(transform_mesh(cube, Vec3(0.3, 0.2, 0.1).asDiagonal(), Vec3::Zero()),
                                     quick().symmetry);
  EXPECT_EQ(box.describe(), "discrete-4");
  EXPECT_LT(rotation_error_deg(rot(Vec3::UnitY(), 180), Mat3::Identity(), box), 1e-5);
  EXPECT_NEAR(rotation_error_deg(rot(Vec3::UnitY(), 90), Mat3::Identity(), box), 90.0, 1e-6);
  // 10 degrees off a half turn: 10 from the nearest symmetry.
  EXPECT_NEAR(rotation_error_deg(rot(Vec3::UnitZ(), 190), Mat3::Identity(), box), 10.0, 1e-6);
  const Symmetry cubic = find_symmetry(cube, quick().symmetry);
  EXPECT_EQ(cubic.describe(), "discrete-24");
  EXPECT_LT(rotation_error_deg(rot(Vec3::UnitX(), 90) * rot(Vec3::UnitZ(), 90), Mat3::Identity(), cubic), 1e-5);
  // The largest error modulo the cube group is 62.8 degrees (about a face axis by 45 and beyond);
  // a turn of 45 degrees about a face axis is 45 away from the nearest symmetry.
  EXPECT_NEAR(rotation_error_deg(rot(Vec3::UnitY(), 45), Mat3::Identity(), cubic), 45.0, 1e-6);
}

// An L-shaped prism with unequal legs has no rotational symmetry (its only mirror, z -> -z, is not a
// rotation; equal legs would add a half turn about the diagonal): the error is the plain geodesic angle.
TEST(Symmetry, LShapeHasNone) {
  Mesh l = prism_mesh({{0, 0}, {1, 0}, {1, 0.3}, {0.3, 0.3}, {0.3, 0.6}, {0, 0.6}}, 0.15);
  canonicalize(l);
  const Symmetry sym = find_symmetry(l, quick().symmetry);
  EXPECT_EQ(sym.describe(), "none");
  EXPECT_NEAR(rotation_error_deg(rot(Vec3(1, 2, -1), 30), Mat3::Identity(), sym), 30.0, 1e-6);
}

// A cylinder whose axis is none of the mesh's axes: the principal-axis frame finds it.
TEST(Symmetry, LatheOnAnObliqueAxis) {
  const Mat3 tilt = rot(Vec3::UnitZ(), 35);
  Mesh cyl = transform_mesh(lathe_mesh({{-0.5, 0.2}, {0.5, 0.2}}, 48), tilt, Vec3::Zero());
  canonicalize(cyl);
  const Symmetry sym = find_symmetry(cyl, quick().symmetry);
  EXPECT_EQ(sym.describe(), "axial+flip");
  ASSERT_EQ(sym.axes.size(), 1u);
  // The exact second moments of a 48-gon prism are those of a round one (a regular polygon's in-plane
  // moments are isotropic), so the principal axis is the tilted y axis up to rounding (1e-12).
  EXPECT_NEAR(std::abs(sym.axes[0].dot(tilt * Vec3::UnitY())), 1.0, 1e-12);
  EXPECT_LT(rotation_error_deg(axis_rotation(tilt * Vec3::UnitY(), 1.1), Mat3::Identity(), sym), 1e-5);
}
