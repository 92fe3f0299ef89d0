// Filled voxel occupancy on a world lattice (surface voxels by separating axes, interior by flood
// fill from the padding) and the voxel IoU.
#include "pipeline/physics/solid_voxels.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "common/error.h"

namespace simu::physics {

namespace {

int cell(double x, double h) { return static_cast<int>(std::floor(x / h)); }

// Projections of the triangle (v0, v1, v2) and of the box (half extents) onto axis: false when the
// axis separates them (touching does not separate).
bool overlap_on(const Vec3& axis, const Vec3& v0, const Vec3& v1, const Vec3& v2, const Vec3& half) {
  const double p0 = axis.dot(v0), p1 = axis.dot(v1), p2 = axis.dot(v2);
  const double r = half.dot(axis.cwiseAbs());
  return !(std::min({p0, p1, p2}) > r || std::max({p0, p1, p2}) < -r);
}

}  // namespace

int64_t LatticeBox::voxels() const {
  if (empty()) return 0;
  return int64_t(hi.x() - lo.x() + 1) * int64_t(hi.y() - lo.y() + 1) * int64_t(hi.z() - lo.z() + 1);
}

LatticeBox lattice_bounds(const Mesh& world_mesh, double h) {
  LatticeBox b;
  if (world_mesh.V.rows() == 0) return b;
  const Vec3 lo = world_mesh.V.colwise().minCoeff().transpose(), hi = world_mesh.V.colwise().maxCoeff().transpose();
  SIMU_CHECK(lo.allFinite() && hi.allFinite(), "voxel lattice: the mesh has a non-finite vertex");
  SIMU_CHECK(std::max(lo.cwiseAbs().maxCoeff(), hi.cwiseAbs().maxCoeff()) / h < 1e9,
             "voxel lattice: a vertex {} m from the origin is beyond the lattice's integer range at {} m",
             std::max(lo.cwiseAbs().maxCoeff(), hi.cwiseAbs().maxCoeff()), h);
  for (int a = 0; a < 3; ++a) {
    b.lo(a) = cell(lo(a), h);
    b.hi(a) = cell(hi(a), h);
  }
  return b;
}

LatticeBox intersect(const LatticeBox& a, const LatticeBox& b) {
  LatticeBox r;
  r.lo = a.lo.cwiseMax(b.lo);
  r.hi = a.hi.cwiseMin(b.hi);
  return r;
}

uint8_t SolidGrid::at(int i, int j, int k) const {
  const int x = i - box.lo.x(), y = j - box.lo.y(), z = k - box.lo.z();
  if (x < 0 || y < 0 || z < 0 || x >= dims.x() || y >= dims.y() || z >= dims.z()) return 0;
  return occ[(int64_t(x) * dims.y() + y) * dims.z() + z];
}

bool triangle_box_overlap(const Vec3& centre, const Vec3& half, const Vec3& a, const Vec3& b, const Vec3& c) {
  const Vec3 v0 = a - centre, v1 = b - centre, v2 = c - centre;
  // The box's face normals: the triangle's bounds against the box.
  for (int k = 0; k < 3; ++k)
    if (std::min({v0(k), v1(k), v2(k)}) > half(k) || std::max({v0(k), v1(k), v2(k)}) < -half(k)) return false;
  // The triangle's plane.
  const Vec3 e0 = v1 - v0, e1 = v2 - v1, e2 = v0 - v2;
  const Vec3 n = e0.cross(e1);
  if (!overlap_on(n, v0, v1, v2, half)) return false;
  // The nine cross products of the box axes with the triangle's edges (a zero axis never separates).
  for (const Vec3& e : {e0, e1, e2})
    for (int k = 0; k < 3; ++k)
      if (!overlap_on(Vec3::Unit(k).cross(e), v0, v1, v2, half)) return false;
  return true;
}

SolidGrid voxelize_solid(const Mesh& world_mesh, double h, int64_t max_voxels) {
  SIMU_CHECK(h > 0 && std::isfinite(h), "voxelize: spacing {} must be positive", h);
  SIMU_CHECK(world_mesh.F.rows() > 0, "voxelize: the mesh has no triangles");
  SIMU_CHECK(world_mesh.V.allFinite(), "voxelize: the mesh has a non-finite vertex");
  for (Eigen::Index f = 0; f < world_mesh.F.rows(); ++f)
    for (int k = 0; k < 3; ++k)
      SIMU_CHECK(world_mesh.F(f, k) >= 0 && world_mesh.F(f, k) < world_mesh.V.rows(),
                 "voxelize: face {} index {} is outside the {} vertices", f, world_mesh.F(f, k), world_mesh.V.rows());
  SolidGrid g;
  g.h = h;
  g.box = lattice_bounds(world_mesh, h);
  g.box.lo.array() -= 1;  // one empty layer all round: the flood fill starts there
  g.box.hi.array() += 1;
  g.dims = g.box.hi - g.box.lo + Eigen::Vector3i::Ones();
  SIMU_CHECK(g.box.voxels() <= max_voxels, "voxelize: a {} x {} x {} grid at {} m exceeds {} voxels", g.dims.x(),
             g.dims.y(), g.dims.z(), h, max_voxels);
  const int64_t ny = g.dims.y(), nz = g.dims.z();
  auto index = [&](int x, int y, int z) { return (int64_t(x) * ny + y) * nz + z; };
  // 1: surface voxel, 2: reached from outside, 0 (after the fill): enclosed.
  std::vector<uint8_t> state(static_cast<size_t>(g.box.voxels()), 0);
  const Vec3 half = Vec3::Constant(0.5 * h);
  for (Eigen::Index f = 0; f < world_mesh.F.rows(); ++f) {
    const Vec3 a = world_mesh.V.row(world_mesh.F(f, 0)).transpose(), b = world_mesh.V.row(world_mesh.F(f, 1)).transpose(),
               c = world_mesh.V.row(world_mesh.F(f, 2)).transpose();
    const Vec3 lo = a.cwiseMin(b).cwiseMin(c), hi = a.cwiseMax(b).cwiseMax(c);
    for (int i = cell(lo.x(), h); i <= cell(hi.x(), h); ++i)
      for (int j = cell(lo.y(), h); j <= cell(hi.y(), h); ++j)
        for (int k = cell(lo.z(), h); k <= cell(hi.z(), h); ++k) {
          const int64_t at = index(i - g.box.lo.x(), j - g.box.lo.y(), k - g.box.lo.z());
          if (state[at]) continue;
          const Vec3 centre = (Vec3(i, j, k) + Vec3::Constant(0.5)) * h;
          if (triangle_box_overlap(centre, half, a, b, c)) state[at] = 1;
        }
  }
  // Flood fill through non-surface voxels from the padding layer (all of it is outside the mesh).
  std::vector<int64_t> queue;
  auto push = [&](int x, int y, int z) {
    const int64_t at = index(x, y, z);
    if (state[at] == 0) {
      state[at] = 2;
      queue.push_back(at);
    }
  };
  for (int x = 0; x < g.dims.x(); ++x)
    for (int y = 0; y < g.dims.y(); ++y)
      for (int z = 0; z < g.dims.z(); ++z)
        if (x == 0 || y == 0 || z == 0 || x == g.dims.x() - 1 || y == g.dims.y() - 1 || z == g.dims.z() - 1) push(x, y, z);
  for (size_t q = 0; q < queue.size(); ++q) {
    const int64_t at = queue[q];
    const int z = static_cast<int>(at % nz), y = static_cast<int>((at / nz) % ny), x = static_cast<int>(at / (nz * ny));
    if (x > 0) push(x - 1, y, z);
    if (x + 1 < g.dims.x()) push(x + 1, y, z);
    if (y > 0) push(x, y - 1, z);
    if (y + 1 < g.dims.y()) push(x, y + 1, z);
    if (z > 0) push(x, y, z - 1);
    if (z + 1 < g.dims.z()) push(x, y, z + 1);
  }
  g.occ.resize(state.size());
  for (size_t i = 0; i < state.size(); ++i) {
    g.occ[i] = state[i] != 2;
    g.count += g.occ[i];
  }
  return g;
}

int64_t overlap_count(const SolidGrid& a, const SolidGrid& b) {
  SIMU_CHECK(a.h == b.h, "voxel overlap: the grids have different spacings ({} and {} m)", a.h, b.h);
  const LatticeBox r = intersect(a.box, b.box);
  if (r.empty()) return 0;
  int64_t n = 0;
  for (int i = r.lo.x(); i <= r.hi.x(); ++i)
    for (int j = r.lo.y(); j <= r.hi.y(); ++j)
      for (int k = r.lo.z(); k <= r.hi.z(); ++k) n += a.at(i, j, k) & b.at(i, j, k);
  return n;
}

SolidIou solid_iou(const Mesh& a, const Mesh& b, double h, int64_t max_voxels) {
  SIMU_CHECK(h > 0 && std::isfinite(h), "voxel IoU: spacing {} must be positive", h);
  SIMU_CHECK(max_voxels >= 27, "voxel IoU: max_voxels {} is below one padded voxel (27)", max_voxels);
  SolidIou r;
  // Grow the spacing (both grids alike) until the larger padded grid fits.
  for (;;) {
    LatticeBox ba = lattice_bounds(a, h), bb = lattice_bounds(b, h);
    ba.lo.array() -= 1, ba.hi.array() += 1, bb.lo.array() -= 1, bb.hi.array() += 1;
    const int64_t n = std::max(ba.voxels(), bb.voxels());
    if (n <= max_voxels) break;
    h *= std::max(1.01, std::cbrt(static_cast<double>(n) / static_cast<double>(max_voxels)));
  }
  r.h = h;
  if (intersect(lattice_bounds(a, h), lattice_bounds(b, h)).empty()) return r;  // disjoint cells: IoU 0
  const SolidGrid ga = voxelize_solid(a, h, max_voxels), gb = voxelize_solid(b, h, max_voxels);
  r.a = ga.count;
  r.b = gb.count;
  r.both = overlap_count(ga, gb);
  const int64_t uni = r.a + r.b - r.both;
  r.iou = uni > 0 ? static_cast<double>(r.both) / static_cast<double>(uni) : 0.0;
  return r;
}

}  // namespace simu::physics
