// Solid occupancy of world-frame meshes on one metric lattice, and the voxel IoU of two of them (the
// 3D IoU of shape_metrics.h: shape and pose together).
//
// Lattice: spacing h anchored at the world origin; voxel (i, j, k) covers [i h, (i+1) h) x [j h,
// (j+1) h) x [k h, (k+1) h), so two meshes voxelised at the same h share their voxels exactly.
// Occupancy is FILLED, as the miniature's occupancy grids define it (MINIATURE.md): the voxels that
// intersect the surface, plus every voxel not reachable from outside the mesh's bounds through
// non-surface voxels (6-connected). A closed box is solid; a bowl is its walls; an open shell whose
// holes are wider than a voxel stays a shell.
//
// Surface voxels: triangle-box overlap by the separating-axis test (Akenine-Moller 2001, 13 axes,
// touching counts as overlap), over the voxels whose half-open cells hold the triangle's bounds.
#pragma once

#include "pipeline/physics/scene.h"

#include <Eigen/Core>

#include <cstdint>
#include <vector>

namespace simu::physics {

// Inclusive lattice index bounds.
struct LatticeBox {
  Eigen::Vector3i lo = Eigen::Vector3i::Zero(), hi = Eigen::Vector3i::Constant(-1);
  bool empty() const { return (hi.array() < lo.array()).any(); }
  int64_t voxels() const;  // 0 when empty
};
// The cells holding a mesh's vertex bounds at spacing h (floor(min / h) .. floor(max / h)).
LatticeBox lattice_bounds(const Mesh& world_mesh, double h);
// Intersection of two boxes (empty when they do not overlap).
LatticeBox intersect(const LatticeBox& a, const LatticeBox& b);

// A filled occupancy grid on the lattice, one voxel of empty padding around the mesh's cells.
struct SolidGrid {
  double h = 0;
  LatticeBox box;            // lattice indices the grid covers (padding included)
  Eigen::Vector3i dims = Eigen::Vector3i::Zero();
  std::vector<uint8_t> occ;  // uint8 [dims.x, dims.y, dims.z], 1 = occupied, index ((i * dims.y) + j) * dims.z + k
  int64_t count = 0;         // occupied voxels
  // Occupancy of lattice voxel (i, j, k) (0 outside the grid).
  uint8_t at(int i, int j, int k) const;
  double volume() const { return static_cast<double>(count) * h * h * h; }
};

// True when triangle (a, b, c) and the closed box centre +- half overlap (separating-axis test).
bool triangle_box_overlap(const Vec3& centre, const Vec3& half, const Vec3& a, const Vec3& b, const Vec3& c);

// The filled occupancy of a world-frame mesh at spacing h. Throws simu::Error when h <= 0, the mesh
// has no triangles or a non-finite vertex, or the grid would exceed max_voxels (naming its size).
SolidGrid voxelize_solid(const Mesh& world_mesh, double h, int64_t max_voxels = int64_t{1} << 24);

// Occupied voxels the two grids (same h) share.
int64_t overlap_count(const SolidGrid& a, const SolidGrid& b);

// Voxel IoU of two world meshes.
struct SolidIou {
  double iou = 0;
  double h = 0;               // the spacing used (metres)
  int64_t a = -1, b = -1;     // occupied voxels of each (-1: not voxelised, their cells are disjoint)
  int64_t both = 0;           // shared occupied voxels
};
// IoU |A n B| / |A u B| of the filled occupancies at spacing h. When the meshes' cells do not overlap
// the IoU is 0 without voxelising. When a grid would exceed max_voxels the spacing grows (for both)
// until it fits, and SolidIou::h says so. 0 when both are empty.
SolidIou solid_iou(const Mesh& a, const Mesh& b, double h, int64_t max_voxels = int64_t{1} << 24);

}  // namespace simu::physics
