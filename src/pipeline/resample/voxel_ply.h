// PLY export of occupied voxels (the Stage-1 sparse structure) as points or as cubes.
#pragma once

#include <torch/torch.h>

#include <string>

namespace simu::resample {


enum class VoxelPlyStyle {
  Points,  // one vertex per voxel at its position
  Cubes,   // one closed cube (8 vertices, 6 quads, outward) per voxel, side 1/resolution
};

struct VoxelPlyOptions {
  VoxelPlyStyle style = VoxelPlyStyle::Points;
  // Positions in the official Stage-1 voxel frame: index p -> p / resolution - 0.5 (cube corners at
  // p/res - 0.5 and (p+1)/res - 0.5). resolution <= 0 writes raw grid indices instead.
  int64_t resolution = 64;
  // With [N, 4] (batch, x, y, z) coordinates: only rows of this batch index (-1: all rows).
  int64_t batch = -1;
};

// coords: integer [N, 3] (x, y, z) or [N, 4] (batch, x, y, z), e.g. models::occupied_coords().
// Writes an ASCII PLY atomically; returns the number of voxels written.
int64_t write_voxel_ply(const torch::Tensor& coords, const std::string& path, const VoxelPlyOptions& options = {});

}  // namespace simu::resample
