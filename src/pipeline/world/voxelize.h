// Filled occupancy of a canonical mesh (the sparse-structure VAE's input and the Stage-1 shape target).
//
// Grid (MINIATURE.md, like resample::occupancy_grid): uint8 [R, R, R], flat index (x * R + y) * R + z;
// voxel p covers the canonical (= official voxel-frame) coordinates [p/R - 0.5, (p+1)/R - 0.5) per
// axis, so the canonical cube [-0.5, 0.5]^3 is the whole grid.
// Filled: 1 for every voxel whose closed cell the surface touches (exact triangle-box overlap, the
// separating-axis test of Akenine-Moller 2001), then 1 for every voxel that no 6-connected path of
// non-surface voxels joins to the grid border (the enclosed inside). A closed box comes out solid, an
// open bowl as its walls only (its inside reaches the border over the rim).
#pragma once

#include "pipeline/physics/scene.h"

#include <cstdint>
#include <vector>

namespace simu::world {

// Filled occupancy [R, R, R] of a canonical mesh (vertices outside the cube are clipped by the grid).
// Throws simu::Error when R < 2 or R > 512 or the mesh is empty / has an index out of range.
std::vector<uint8_t> voxelize_filled(const physics::Mesh& canonical, int R);

// Only the surface voxels (the first step of voxelize_filled).
std::vector<uint8_t> voxelize_surface(const physics::Mesh& canonical, int R);

// Number of set voxels.
int64_t count_occupied(const std::vector<uint8_t>& grid);

}  // namespace simu::world
