// Marching cubes on a dense 3-D scalar grid (the decoder's 64^3 occupancy logits) and the canonical
// object frame (AABB centred, longest side 1).
//
// Inside is value > iso. The grid is padded with a border below iso, so the surface is always closed.
// Each cube's case table is derived at start-up (no copied tables): on every cube face the crossing
// points are joined so that each inside corner is cut off on its own (a face whose two inside corners
// are diagonal gets two segments; the rule depends only on the face's four values, so the two cubes
// sharing a face agree, which makes the mesh watertight). The segments form closed loops; a loop of 3
// points is one triangle, longer loops are fanned from their first point, or, in cubes with such a
// two-segment face, from an extra vertex at the loop's centroid (so no edge is ever shared by more than
// two triangles). Triangles are counter-clockwise seen from outside (normals point from inside to
// outside); every edge of the result is shared by exactly two triangles with opposite directions.
#pragma once

#include <torch/torch.h>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include <array>
#include <string>

#include "pipeline/physics/scene.h"

namespace simu::resample {

// The one triangle mesh type of the project (physics/scene.h): V [n, 3] positions, F [m, 3] vertex
// indices, counter-clockwise seen from outside.
using physics::Mesh;

struct MarchingCubesOptions {
  double iso = 0.0;  // surface level; inside is value > iso
  // Slabs of cubes along x processed in parallel (at::parallel_for); 0 = 4 per ATen thread. The mesh
  // (vertex order, triangle order, values) does not depend on it nor on the thread count.
  int slabs = 0;
};

// grid: [X, Y, Z] (or [1, 1, X, Y, Z]) values on any device/dtype (copied to CPU float32).
// Vertex coordinates are in grid index units: grid[i][j][k] sits at (i, j, k).
// Parallel over x-slabs of cubes (pass 1: per slab, vertices in order of first use; pass 2: slabs
// concatenated, crossings shared with the previous slab resolved), so the result is identical to the
// sequential (x, y, z) cube scan of marching_cubes_reference.
Mesh marching_cubes(const torch::Tensor& grid, const MarchingCubesOptions& options = {});

// The simple sequential implementation (one cube at a time, x then y then z; vertices numbered in
// order of first use, triangles in cube order). Kept as the reference the fast path is tested against;
// ignores options.slabs.
Mesh marching_cubes_reference(const torch::Tensor& grid, const MarchingCubesOptions& options = {});

// Official Stage-1 voxel frame: index p -> p / resolution - 0.5 (the official `coords / 64 - 0.5`).
void grid_to_voxel_frame(Mesh& mesh, int64_t resolution);

// Canonical frame: centres the mesh's axis-aligned bounding box at the origin and scales its longest side
// to 1. Returns {centre, factor} such that canonical = (v - centre) * factor. Empty mesh: no change.
struct CanonicalTransform {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  double factor = 1.0;
};
CanonicalTransform canonicalize_mesh(Mesh& mesh);

// Moves every vertex by `distance` against its normal (the area-weighted mean of its triangles' outward
// normals): inward for distance > 0, in the mesh's own units. Vertices without area are left. The
// occupancy Stage 1 learns marks every voxel the surface touches (a conservative voxelisation:
// world::voxelize_filled, TRELLIS's sparse structure), so an iso-0 surface of its logits sits up to one
// voxel outside the true surface; the resampler moves it back by ResamplerConfig::surface_offset voxels.
void offset_surface(Mesh& mesh, double distance);

// Mesh checks used by the tests and the resampler: volume by the divergence theorem (positive when
// outward-oriented), and a description of the first closedness/orientation defect ("" when every
// undirected edge is used by exactly two triangles in opposite directions and no face is degenerate
// in its indices).
double mesh_signed_volume(const Mesh& mesh);
std::string mesh_closedness_problem(const Mesh& mesh);

// Writes the mesh as an ASCII PLY (vertex x y z as float, face vertex_indices), atomically.
void write_mesh_ply(const Mesh& mesh, const std::string& path);

}  // namespace simu::resample
