#include "pipeline/resample/voxel_ply.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <array>
#include <vector>

#include "common/error.h"
#include "common/fs.h"

namespace simu::resample {


int64_t write_voxel_ply(const torch::Tensor& coords_in, const std::string& path, const VoxelPlyOptions& options) {
  SIMU_CHECK(coords_in.dim() == 2 && (coords_in.size(1) == 3 || coords_in.size(1) == 4),
             "write_voxel_ply({}): expected coords [N, 3] or [N, 4], got {}", path, coords_in.sizes());
  auto coords = coords_in.to(torch::kCPU, torch::kLong).contiguous();
  // Keep the requested batch, drop the batch column.
  if (coords.size(1) == 4) {
    if (options.batch >= 0) coords = coords.index({coords.select(1, 0) == options.batch});
    coords = coords.slice(1, 1, 4).contiguous();
  }
  const int64_t n = coords.size(0);
  const auto c = coords.accessor<int64_t, 2>();
  const double res = static_cast<double>(options.resolution);
  auto pos = [&](double p) { return options.resolution > 0 ? p / res - 0.5 : p; };

  std::string body;
  std::string header = "ply\nformat ascii 1.0\ncomment simuscene occupied voxels\n";
  if (options.style == VoxelPlyStyle::Points) {
    // One vertex per voxel.
    header += fmt::format("element vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n", n);
    for (int64_t i = 0; i < n; ++i)
      body += fmt::format("{} {} {}\n", static_cast<float>(pos(c[i][0])), static_cast<float>(pos(c[i][1])),
                          static_cast<float>(pos(c[i][2])));
  } else {
    // Eight corners (bit k of corner = offset along axis k) and six outward quads per voxel.
    static const int quads[6][4] = {{0, 4, 6, 2}, {1, 3, 7, 5}, {0, 1, 5, 4}, {2, 6, 7, 3}, {0, 2, 3, 1}, {4, 5, 7, 6}};
    header += fmt::format(
        "element vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\n"
        "property list uchar int vertex_indices\nend_header\n",
        8 * n, 6 * n);
    std::string faces;
    for (int64_t i = 0; i < n; ++i) {
      for (int k = 0; k < 8; ++k)
        body += fmt::format("{} {} {}\n", static_cast<float>(pos(c[i][0] + (k & 1))),
                            static_cast<float>(pos(c[i][1] + ((k >> 1) & 1))),
                            static_cast<float>(pos(c[i][2] + ((k >> 2) & 1))));
      for (const auto& q : quads)
        faces += fmt::format("4 {} {} {} {}\n", 8 * i + q[0], 8 * i + q[1], 8 * i + q[2], 8 * i + q[3]);
    }
    body += faces;
  }
  simu::fs::atomic_write(path, header + body);
  return n;
}

}  // namespace simu::resample
