// Filled occupancy: surface voxels by exact triangle / closed-cell overlap, then a flood fill of the
// outside from the grid border through non-surface voxels; everything not reached is filled.
#include "pipeline/world/voxelize.h"

#include "common/error.h"

#include <algorithm>
#include <array>
#include <cmath>

namespace simu::world {

namespace {

using V3 = std::array<double, 3>;

V3 sub(const V3& a, const V3& b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
V3 cross(const V3& a, const V3& b) {
  return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
double dot(const V3& a, const V3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

// Whether the triangle (vertices relative to the box centre) meets the closed axis-aligned box of half
// size h: the separating-axis test over the 3 box normals, the triangle normal and the 9 edge cross
// products (Akenine-Moller, "Fast 3D triangle-box overlap testing", 2001). Touching counts as overlap.
bool triangle_meets_box(const V3& a, const V3& b, const V3& c, double h) {
  // Box normals: the triangle's extent per axis against [-h, h].
  for (int k = 0; k < 3; ++k) {
    if (std::min({a[k], b[k], c[k]}) > h || std::max({a[k], b[k], c[k]}) < -h) return false;
  }
  const V3 e[3] = {sub(b, a), sub(c, b), sub(a, c)};
  // Edge x axis cross products.
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) {
      V3 axis{0, 0, 0};
      V3 unit{0, 0, 0};
      unit[k] = 1;
      axis = cross(unit, e[i]);
      const double pa = dot(axis, a), pb = dot(axis, b), pc = dot(axis, c);
      const double r = h * (std::abs(axis[0]) + std::abs(axis[1]) + std::abs(axis[2]));
      if (std::min({pa, pb, pc}) > r || std::max({pa, pb, pc}) < -r) return false;
    }
  // Triangle plane.
  const V3 n = cross(e[0], e[1]);
  const double d = dot(n, a), r = h * (std::abs(n[0]) + std::abs(n[1]) + std::abs(n[2]));
  return std::abs(d) <= r;
}

void check_args(const physics::Mesh& m, int R) {
  SIMU_CHECK(R >= 2 && R <= 512, "voxelize: resolution {} outside [2, 512]", R);
  SIMU_CHECK(!m.empty(), "voxelize: empty mesh ({} vertices, {} faces)", m.V.rows(), m.F.rows());
  SIMU_CHECK(m.F.minCoeff() >= 0 && m.F.maxCoeff() < m.V.rows(), "voxelize: a face index is outside [0, {})",
             m.V.rows());
  SIMU_CHECK(m.V.allFinite(), "voxelize: non-finite vertex");
}

}  // namespace

std::vector<uint8_t> voxelize_surface(const physics::Mesh& m, int R) {
  check_args(m, R);
  std::vector<uint8_t> grid(size_t(R) * R * R, 0);
  // Voxel units: u = (c + 0.5) R, voxel p is the closed cell [p, p + 1] per axis.
  auto vox = [&](Eigen::Index i) -> V3 { return {(m.V(i, 0) + 0.5) * R, (m.V(i, 1) + 0.5) * R, (m.V(i, 2) + 0.5) * R}; };
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    const V3 a = vox(m.F(f, 0)), b = vox(m.F(f, 1)), c = vox(m.F(f, 2));
    int lo[3], hi[3];
    bool outside = false;
    for (int k = 0; k < 3; ++k) {
      // Cells [p, p + 1] touching [min, max]: p in [ceil(min) - 1, floor(max)].
      lo[k] = std::max(0, int(std::ceil(std::min({a[k], b[k], c[k]}))) - 1);
      hi[k] = std::min(R - 1, int(std::floor(std::max({a[k], b[k], c[k]}))));
      outside |= lo[k] > hi[k];
    }
    if (outside) continue;
    for (int x = lo[0]; x <= hi[0]; ++x)
      for (int y = lo[1]; y <= hi[1]; ++y)
        for (int z = lo[2]; z <= hi[2]; ++z) {
          uint8_t& g = grid[(size_t(x) * R + y) * R + z];
          if (g) continue;
          const V3 o{x + 0.5, y + 0.5, z + 0.5};
          if (triangle_meets_box(sub(a, o), sub(b, o), sub(c, o), 0.5)) g = 1;
        }
  }
  return grid;
}

std::vector<uint8_t> voxelize_filled(const physics::Mesh& m, int R) {
  std::vector<uint8_t> grid = voxelize_surface(m, R);
  // Flood the outside (value 2) from every non-surface border voxel, 6-connected.
  std::vector<int32_t> stack;
  stack.reserve(size_t(R) * R * 6);
  auto push = [&](int x, int y, int z) {
    const size_t i = (size_t(x) * R + y) * R + z;
    if (grid[i] == 0) grid[i] = 2, stack.push_back(int32_t(i));
  };
  for (int a = 0; a < R; ++a)
    for (int b = 0; b < R; ++b) {
      push(0, a, b), push(R - 1, a, b), push(a, 0, b), push(a, R - 1, b), push(a, b, 0), push(a, b, R - 1);
    }
  while (!stack.empty()) {
    const int32_t i = stack.back();
    stack.pop_back();
    const int z = i % R, y = (i / R) % R, x = i / (R * R);
    if (x > 0) push(x - 1, y, z);
    if (x + 1 < R) push(x + 1, y, z);
    if (y > 0) push(x, y - 1, z);
    if (y + 1 < R) push(x, y + 1, z);
    if (z > 0) push(x, y, z - 1);
    if (z + 1 < R) push(x, y, z + 1);
  }
  for (auto& g : grid) g = g == 2 ? 0 : 1;
  return grid;
}

int64_t count_occupied(const std::vector<uint8_t>& grid) {
  int64_t n = 0;
  for (uint8_t g : grid) n += g != 0;
  return n;
}

}  // namespace simu::world
