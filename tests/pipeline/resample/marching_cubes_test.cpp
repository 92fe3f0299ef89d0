// Marching cubes: closed, consistently oriented meshes of the right volume; canonical frame; PLY output.
#include <cmath>
#include <fstream>
#include <sstream>

#include "common/fs.h"
#include "pipeline/resample/marching_cubes.h"
#include "pipeline/resample/voxel_ply.h"
#include "test_util.h"

using namespace simu::physics;
using namespace simu::resample;

namespace {
constexpr double kPi = 3.14159265358979323846;
// Occupancy logits (+1 inside, -1 outside) of a ball of radius r (voxel units) centred at c, on an R^3 grid.
torch::Tensor ball_occupancy(int64_t R, double r, double c) {
  auto i = torch::arange(R, torch::kFloat64);
  auto gx = i.view({R, 1, 1}) - c, gy = i.view({1, R, 1}) - c, gz = i.view({1, 1, R}) - c;
  auto d2 = gx * gx + gy * gy + gz * gz;
  return torch::where(d2 <= r * r, torch::ones_like(d2), -torch::ones_like(d2)).to(torch::kFloat32);
}
}  // namespace

// A ball's occupancy at 64^3: closed, outward-oriented, volume within 3% of 4/3 pi r^3.
TEST(MarchingCubes, BallOccupancyClosedRightVolume) {
  const double r = 24.0;
  auto grid = ball_occupancy(64, r, 31.5);
  auto mesh = marching_cubes(grid);
  ASSERT_FALSE(mesh.empty());
  EXPECT_EQ(mesh_closedness_problem(mesh), "");
  const double want = 4.0 / 3.0 * kPi * r * r * r;
  const double got = mesh_signed_volume(mesh);
  std::printf("ball r=%.0f: %ld vertices, %ld faces, volume %.1f vs %.1f (%.2f%%)\n", r, (long)mesh.V.rows(),
              (long)mesh.F.rows(), got, want, 100.0 * (got - want) / want);
  // Discretisation, not rounding: binary occupancy puts every crossing at an edge's mid-point, within
  // a quarter voxel of the sphere on average; the volume moves by at most the area times that,
  // 3 (1/4) / r = 3.1% of it at r = 24.
  EXPECT_NEAR(got / want, 1.0, 0.03);
}

// A signed-distance grid gives a far more accurate sphere (interpolated crossings).
TEST(MarchingCubes, BallSignedDistanceAccurate) {
  const int64_t R = 64;
  const double r = 20.0, c = 30.2;
  auto i = torch::arange(R, torch::kFloat64);
  auto d = torch::sqrt((i.view({R, 1, 1}) - c).pow(2) + (i.view({1, R, 1}) - c).pow(2) + (i.view({1, 1, R}) - c).pow(2));
  auto mesh = marching_cubes(r - d);  // positive inside
  EXPECT_EQ(mesh_closedness_problem(mesh), "");
  const double want = 4.0 / 3.0 * kPi * r * r * r;
  // Linear interpolation of r - d along a unit edge misses the sphere by at most the distance
  // function's curvature, 1 / (2 r) = 0.025 voxel: the volume by 3 x 0.025 / r = 0.4%.
  EXPECT_NEAR(mesh_signed_volume(mesh) / want, 1.0, 0.01);
  // Every vertex lies on the sphere up to that interpolation error (0.025), with room.
  const Eigen::RowVector3d centre(c, c, c);
  const Eigen::VectorXd dist = (mesh.V.rowwise() - centre).rowwise().norm();
  EXPECT_LT((dist.array() - r).abs().maxCoeff(), 0.1);
}

// A box's occupancy, touching the grid boundary (padding must close it): closed, volume within 3%.
TEST(MarchingCubes, BoxOccupancyTouchingBorder) {
  auto grid = -torch::ones({64, 64, 64});
  grid.slice(0, 0, 40).slice(1, 10, 50).slice(2, 20, 64).fill_(1.0);  // 40 x 40 x 44 voxels
  auto mesh = marching_cubes(grid.view({1, 1, 64, 64, 64}));
  EXPECT_EQ(mesh_closedness_problem(mesh), "");
  const double want = 40.0 * 40.0 * 44.0;
  const double got = mesh_signed_volume(mesh);
  std::printf("box: volume %.1f vs %.1f (%.2f%%)\n", got, want, 100.0 * (got - want) / want);
  // The mid-point crossings bevel the 12 edges (a quarter voxel^2 / 2 of section each): 0.09% here.
  EXPECT_NEAR(got / want, 1.0, 0.03);
  // Crossings at the cell mid-points: the AABB spans [-0.5, 39.5] x [9.5, 49.5] x [19.5, 63.5]
  // (t = v0 / (v0 - v1) = 1/2 for +-1 values, added to an integer: float64, 2 roundings of <= 64).
  const double mid = 64 * simu::testing::gamma(2, simu::testing::kFp64Unit);
  EXPECT_NEAR(mesh.V.col(0).minCoeff(), -0.5, mid);
  EXPECT_NEAR(mesh.V.col(0).maxCoeff(), 39.5, mid);
  EXPECT_NEAR(mesh.V.col(2).maxCoeff(), 63.5, mid);
}

// Every one of the 256 single-cube configurations (corner values +-1 on a 2x2x2 grid), and random
// noise full of ambiguous faces, yields closed, consistently oriented meshes with positive volume.
TEST(MarchingCubes, AllCasesAndNoiseAreClosed) {
  for (int mask = 1; mask < 256; ++mask) {
    auto g = torch::empty({2, 2, 2});
    for (int c = 0; c < 8; ++c) g[c & 1][(c >> 1) & 1][(c >> 2) & 1] = ((mask >> c) & 1) ? 1.0 : -1.0;
    auto mesh = marching_cubes(g);
    ASSERT_EQ(mesh_closedness_problem(mesh), "") << "case " << mask;
    ASSERT_GT(mesh_signed_volume(mesh), 0.0) << "case " << mask;
  }
  torch::manual_seed(3);
  auto noise = torch::randn({12, 13, 11});
  auto mesh = marching_cubes(noise, {0.2});
  EXPECT_EQ(mesh_closedness_problem(mesh), "");
  EXPECT_GT(mesh_signed_volume(mesh), 0.0);
}

// Canonical frame: AABB centred at 0 with longest side 1; the returned transform maps back.
TEST(MarchingCubes, CanonicalFrame) {
  auto grid = -torch::ones({16, 16, 16});
  grid.slice(0, 2, 10).slice(1, 3, 7).slice(2, 5, 9).fill_(1.0);
  auto mesh = marching_cubes(grid);
  const auto before = mesh.V;
  auto tf = canonicalize_mesh(mesh);
  const Eigen::Vector3d lo = mesh.V.colwise().minCoeff(), hi = mesh.V.colwise().maxCoeff();
  // float64: a few roundings of coordinates <= 16 before, <= 1 after the scaling.
  const double canon = 16 * simu::testing::gamma(4, simu::testing::kFp64Unit);
  EXPECT_NEAR((hi - lo).maxCoeff(), 1.0, canon);
  EXPECT_NEAR((hi + lo).norm(), 0.0, canon);
  EXPECT_NEAR(tf.factor, 1.0 / 8.0, canon);  // x extent 1.5..9.5
  EXPECT_NEAR(((before.rowwise() - tf.centre.transpose()) * tf.factor - mesh.V).cwiseAbs().maxCoeff(), 0.0, canon);
  EXPECT_EQ(mesh_closedness_problem(mesh), "");
}

// PLY writers: headers, counts, and cube PLYs that enclose exactly N voxels of volume.
TEST(VoxelPly, PointsAndCubes) {
  const auto dir = simu::testing::temp_dir("voxel_ply");
  auto coords = torch::tensor({0, 1, 2, 3, 0, 1, 2, 4, 1, 5, 5, 5}, torch::kInt32).view({3, 4});
  EXPECT_EQ(write_voxel_ply(coords, dir + "/all.ply"), 3);
  VoxelPlyOptions b0;
  b0.batch = 0;
  EXPECT_EQ(write_voxel_ply(coords, dir + "/b0.ply", b0), 2);
  const auto text = simu::fs::read_file(dir + "/b0.ply");
  EXPECT_NE(text.find("element vertex 2\n"), std::string::npos);
  EXPECT_NE(text.find("\n-0.484375 -0.46875 -0.453125\n"), std::string::npos);  // (1,2,3)/64 - 0.5

  VoxelPlyOptions cubes;
  cubes.style = VoxelPlyStyle::Cubes;
  cubes.resolution = 4;
  EXPECT_EQ(write_voxel_ply(coords, dir + "/cubes.ply", cubes), 3);
  // Parse back and compute the enclosed volume from the quads (split into triangles).
  std::istringstream in(simu::fs::read_file(dir + "/cubes.ply"));
  std::string line;
  int nv = 0, nf = 0;
  while (std::getline(in, line) && line != "end_header") {
    if (line.rfind("element vertex", 0) == 0) nv = std::stoi(line.substr(15));
    if (line.rfind("element face", 0) == 0) nf = std::stoi(line.substr(13));
  }
  ASSERT_EQ(nv, 24);
  ASSERT_EQ(nf, 18);
  std::vector<Eigen::Vector3d> v(nv);
  for (auto& p : v) in >> p.x() >> p.y() >> p.z();
  double six_v = 0;
  for (int f = 0; f < nf; ++f) {
    int k, q[4];
    in >> k >> q[0] >> q[1] >> q[2] >> q[3];
    ASSERT_EQ(k, 4);
    six_v += v[q[0]].dot(v[q[1]].cross(v[q[2]])) + v[q[0]].dot(v[q[2]].cross(v[q[3]]));
  }
  // Three voxels of side 1/4: vertices at multiples of 1/8, printed and parsed exactly; 36 float64
  // triple products (5 roundings each) of values <= 1 summed.
  EXPECT_NEAR(six_v / 6.0, 3.0 / 64.0, simu::testing::gamma(36 * 5 + 36, simu::testing::kFp64Unit));
}

// Mesh PLY: counts in the header and the face lines.
TEST(MarchingCubes, WritesMeshPly) {
  auto mesh = marching_cubes(ball_occupancy(8, 2.5, 3.5));
  const auto dir = simu::testing::temp_dir("mesh_ply");
  write_mesh_ply(mesh, dir + "/m.ply");
  const auto text = simu::fs::read_file(dir + "/m.ply");
  EXPECT_NE(text.find(fmt::format("element vertex {}\n", mesh.V.rows())), std::string::npos);
  EXPECT_NE(text.find(fmt::format("element face {}\n", mesh.F.rows())), std::string::npos);
  EXPECT_NE(text.find(fmt::format("3 {} {} {}\n", mesh.F(0, 0), mesh.F(0, 1), mesh.F(0, 2))), std::string::npos);
}

// offset_surface moves a signed-distance sphere's vertices inward along their normals by the distance
// asked: every vertex lands on the smaller sphere (interpolation error 0.025 plus the normals' deviation
// from radial, well under 0.1 voxel at r = 20), the mesh stays closed, 0 changes nothing and a negative
// distance moves outward.
TEST(MarchingCubes, OffsetSurfaceMovesAlongNormals) {
  const int64_t R = 64;
  const double r = 20.0, c = 30.2;
  auto i = torch::arange(R, torch::kFloat64);
  auto d = torch::sqrt((i.view({R, 1, 1}) - c).pow(2) + (i.view({1, R, 1}) - c).pow(2) + (i.view({1, 1, R}) - c).pow(2));
  const Mesh base = marching_cubes(r - d);
  const Eigen::RowVector3d centre(c, c, c);
  for (double off : {0.5, 1.0, -0.5}) {
    Mesh m = base;
    offset_surface(m, off);
    EXPECT_EQ(mesh_closedness_problem(m), "") << off;
    const Eigen::VectorXd dist = (m.V.rowwise() - centre).rowwise().norm();
    EXPECT_LT((dist.array() - (r - off)).abs().maxCoeff(), 0.1) << "offset " << off;
  }
  Mesh same = base;
  offset_surface(same, 0.0);
  EXPECT_TRUE(same.V == base.V);
}

// Why the resampler offsets its meshes: a conservative voxelisation (every voxel the ball touches is
// occupied, as world::voxelize_filled marks the VAE's targets) meshed at iso 0 sits outside the ball:
// half a voxel where the surface runs along the grid axes (the iso-0 crossing is half-way to the empty
// neighbour) and more where a voxel's corner touches it (measured: 0.77 voxel for this ball). Moved
// inward by half a voxel, the mean radius moves by that half voxel (the normals are radial) and is closer
// to the truth. The occupancy is computed here from the voxel cubes' distance to the centre
// (independent of the project's voxeliser).
TEST(MarchingCubes, OffsetCorrectsConservativeVoxelisation) {
  const int64_t R = 16;
  const double r = 5.3, c = 7.3;
  // Voxel (x, y, z) is the cube [x - 0.5, x + 0.5]^3; it touches the ball iff its closest point is within r.
  auto i = torch::arange(R, torch::kFloat64);
  auto gap = [&](const torch::Tensor& v) { return torch::clamp(torch::abs(v - c) - 0.5, 0.0); };
  auto gx = gap(i.view({R, 1, 1})), gy = gap(i.view({1, R, 1})), gz = gap(i.view({1, 1, R}));
  auto touch = (gx * gx + gy * gy + gz * gz) <= r * r;
  auto grid = torch::where(touch, torch::ones({R, R, R}, torch::kFloat64), -torch::ones({R, R, R}, torch::kFloat64));
  const Eigen::RowVector3d centre(c, c, c);
  auto mean_radius_error = [&](double off) {
    Mesh m = marching_cubes(grid);
    offset_surface(m, off);
    return ((m.V.rowwise() - centre).rowwise().norm().array() - r).mean();
  };
  const double e0 = mean_radius_error(0.0), e5 = mean_radius_error(0.5);
  std::printf("conservative ball r=%.1f at 16^3: mean radius error %.3f voxel at offset 0, %.3f at 0.5\n", r, e0, e5);
  EXPECT_GT(e0, 0.5);
  EXPECT_NEAR(e0 - e5, 0.5, 0.05);
  EXPECT_LT(std::abs(e5), std::abs(e0));
}
