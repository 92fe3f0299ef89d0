// The samples of Stage-1 pretraining in memory: every record of one split of a stage-1 cache
// (data/stage1_cache.h) loaded once, stacked in its storage dtypes (uint8 images and masks, float16 or
// float32 point maps), so that a step's batch is a gather of rows (no file reads while training).
// 60,000 samples at 112 / 64 px with compact storage and a 32^3 occupancy take ~11 GB.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "data/stage1_cache.h"

namespace simu::training {

struct Stage1Samples {
  std::vector<int64_t> ids;                     // each row's record index in the cache (seeds its draws)
  std::map<std::string, torch::Tensor> inputs;  // condition_input_names() -> [N, ch, s, s] storage dtype
  torch::Tensor occupancy;                      // [N, R, R, R] uint8 0/1
  std::map<std::string, torch::Tensor> pose;    // stage1_pose_latents() -> [N, k] float32
  int64_t size() const { return static_cast<int64_t>(ids.size()); }
  int64_t occupancy_resolution() const { return occupancy.size(1); }
};

// Loads every record of `split` (`chunk` records at a time on `threads` threads, checked in bulk; a
// progress bar when `progress`). Throws naming the cache when the split is empty.
std::shared_ptr<const Stage1Samples> load_stage1_samples(const std::string& cache, data::SampleSplit split,
                                                         bool progress = false, int64_t chunk = 256, int threads = 8);

// n synthetic samples (benchmarks and smoke runs; seeded): smooth random images stored as uint8,
// box masks, smooth point maps in [-1, 1] stored as float16 with an invalid (NaN) corner, random
// occupancy (about 30% set), pose latents N(0, 1); images and masks S px, point maps P px, occupancy R^3.
std::shared_ptr<Stage1Samples> synthetic_stage1_samples(int64_t n, int64_t S, int64_t P, int64_t R, uint64_t seed);

// Samples in memory as condition inputs decoded to float32 (uint8 level k -> float(k) * float(1/255),
// bit-identical to the cache reader; float16 -> float32): kwarg -> [m, ch, s, s] on x's device.
std::map<std::string, torch::Tensor> decode_inputs(const std::map<std::string, torch::Tensor>& stored);

// The pose latents of rows as the flow model reads them: latent -> [m, 1, k] float32.
std::map<std::string, torch::Tensor> pose_latents(const std::map<std::string, torch::Tensor>& pose_rows);

}  // namespace simu::training
