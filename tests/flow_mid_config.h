// A mid-size Stage-1 generator config for the GPU tests: configs/stage1_small.yaml widened to
// 256 channels (4 heads of 64), 3 blocks and a 8^3 shape grid (512 tokens), the smallest shapes the
// fused CUDA kernels run on.
#pragma once

#include <fstream>
#include <iterator>
#include <string>
#include <utility>
#include <vector>

#include "common/source_dir.h"
#include "test_util.h"

namespace simu::testing {

// Writes the widened config into temp_dir(name) and returns its path.
inline std::string mid_flow_config(const std::string& name) {
  std::ifstream in(simu::source_dir() + "/configs/stage1_small.yaml");
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  for (const auto& [from, to] : std::vector<std::pair<std::string, std::string>>{
           {"model_channels: 64", "model_channels: 256"}, {"num_blocks: 2", "num_blocks: 3"}, {"resolution: 4", "resolution: 8"}}) {
    const auto at = text.find(from);
    if (at == std::string::npos) throw std::runtime_error("configs/stage1_small.yaml no longer has '" + from + "'");
    text.replace(at, from.size(), to);
  }
  const auto path = temp_dir(name) + "/stage1_mid.yaml";
  std::ofstream(path) << text;
  return path;
}

}  // namespace simu::testing
