// voxelize_filled against independent math: a box fills exactly the voxels whose closed cells meet it,
// a polygonal sphere lies between the cells inside its inscribed ball and the cells touching its
// circumscribed ball (and near 4/3 pi r^3), a bowl's cavity stays empty, and the grid layout is
// (x, y, z) with x slowest.
#include "pipeline/world/voxelize.h"

#include "pipeline/physics/collision.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/world/parts.h"
#include "pipeline/world/shapes.h"

#include "test_files.h"

#include <gtest/gtest.h>

#include <cmath>

using namespace simu::world;
using simu::testing::error_of;

namespace {
constexpr int R = 32;
constexpr double kPi = 3.14159265358979323846;
size_t at(int x, int y, int z) { return (size_t(x) * R + y) * R + z; }
// Cells p (covering [p/R - 0.5, (p+1)/R - 0.5]) whose closed interval meets [a, b].
int cells_meeting(double a, double b) {
  int n = 0;
  for (int p = 0; p < R; ++p) n += double(p) / R - 0.5 <= b && double(p + 1) / R - 0.5 >= a;
  return n;
}
}  // namespace

// A box: the filled voxels are the product of the cells meeting each side's interval.
TEST(WorldVoxelize, BoxExact) {
  for (const Vec3 e : {Vec3(1.0, 0.6, 0.37), Vec3(0.43, 1.0, 0.81), Vec3(0.2, 0.3, 1.0)}) {
    const Mesh box = box_part(e);
    const auto g = voxelize_filled(box, R);
    ASSERT_EQ(g.size(), size_t(R) * R * R);
    const int64_t expect = int64_t(cells_meeting(-e.x() / 2, e.x() / 2)) * cells_meeting(-e.y() / 2, e.y() / 2) *
                           cells_meeting(-e.z() / 2, e.z() / 2);
    EXPECT_EQ(count_occupied(g), expect) << e.transpose();
    // And against the volume: between the box's volume and the box grown by one voxel per side.
    const double h = 1.0 / R;
    EXPECT_GE(double(count_occupied(g)) * h * h * h, e.prod());
    EXPECT_LE(double(count_occupied(g)) * h * h * h, (e.array() + 2 * h).prod());
    EXPECT_LT(count_occupied(voxelize_surface(box, R)), count_occupied(g));
  }
  // Axis order: a box long along x fills every x of one (y, z) line through the middle.
  const auto g = voxelize_filled(box_part(Vec3(1.0, 0.1, 0.1)), R);
  for (int x = 0; x < R; ++x) EXPECT_EQ(g[at(x, R / 2, R / 2)], 1);
  EXPECT_EQ(g[at(R / 2, 0, R / 2)], 0);
}

// A UV sphere of radius 0.5 (16 bands x 32 segments): between the cells inside its inscribed ball and
// the cells touching its circumscribed one.
TEST(WorldVoxelize, SphereBounds) {
  std::vector<std::pair<double, double>> prof;
  const int n = 16;
  for (int k = 0; k <= n; ++k) prof.emplace_back(-0.5 * std::cos(kPi * k / n), k == 0 || k == n ? 0.0 : 0.5 * std::sin(kPi * k / n));
  const Mesh sphere = revolve_part(prof, 32);
  const int64_t got = count_occupied(voxelize_filled(sphere, R));
  // Every face's vertices lie within an angle rho <= (pi/16 + 2 pi/32) / 2 of its centre direction on
  // the sphere, so its plane is at least 0.5 cos(rho) from the centre: the inscribed ball's radius.
  const double r_out = 0.5, r_in = 0.5 * std::cos(0.5 * (kPi / 16 + 2 * kPi / 32));
  const double h = 1.0 / R, half_diag = 0.5 * std::sqrt(3.0) * h;
  int64_t inside = 0, touching = 0;
  for (int x = 0; x < R; ++x)
    for (int y = 0; y < R; ++y)
      for (int z = 0; z < R; ++z) {
        const double d = Vec3((x + 0.5) * h - 0.5, (y + 0.5) * h - 0.5, (z + 0.5) * h - 0.5).norm();
        inside += d + half_diag <= r_in;
        touching += d - half_diag <= r_out;
      }
  EXPECT_GE(got, inside);
  EXPECT_LE(got, touching);
  // Near the analytic volume (4/3 pi 16^3 = 17157 voxels): the bounds' band is the surface shell.
  EXPECT_NEAR(double(got), 4.0 / 3.0 * kPi * std::pow(0.5 * R, 3), 0.25 * 4.0 / 3.0 * kPi * std::pow(0.5 * R, 3));
}

// A bowl is its walls: its cavity stays empty, far below its convex hull's filled count.
TEST(WorldVoxelize, BowlNotFilled) {
  for (uint64_t seed = 0; seed < 4; ++seed) {
    const ShapeInstance bowl = make_shape("bowl", seed);
    const auto g = voxelize_filled(bowl.mesh, R);
    const auto hull = voxelize_filled(simu::physics::convex_hull(bowl.mesh.V), R);
    EXPECT_EQ(g[at(R / 2, R / 2, R / 2)], 0) << bowl.name;  // mid-height on the axis: inside the cavity
    EXPECT_LT(double(count_occupied(g)), 0.6 * double(count_occupied(hull))) << bowl.name;
    // Filled contains the surface.
    const auto s = voxelize_surface(bowl.mesh, R);
    for (size_t i = 0; i < s.size(); ++i) ASSERT_TRUE(!s[i] || g[i]);
  }
}

TEST(WorldVoxelize, BadArguments) {
  EXPECT_NE(error_of([] { voxelize_filled(box_part(Vec3::Ones()), 1); }).find("resolution 1"), std::string::npos);
  EXPECT_NE(error_of([] { voxelize_filled(Mesh{}, 32); }).find("empty mesh"), std::string::npos);
}
