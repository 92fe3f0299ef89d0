// The sparse-structure VAE's data: which shapes it sees (a ShapeSet: the app wires the shape world in,
// tests use synthetic shapes) and the background loader that turns them into batches ahead of the steps.
//
// The training stream is indexed: step s, rank r of W takes samples i = s*G + r*G/W + j, j < G/W
// (G = the global batch). A sample's shape and its posterior noise are functions of i alone, so a
// resumed run (from the step) and any number of ranks see the same samples with the same noise.
#pragma once

#include <torch/torch.h>

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <exception>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

namespace simu::training {

// One shape: a shape-world family and instance seed (world::make_shape's arguments).
struct ShapeKey {
  std::string family;
  uint64_t seed = 0;
};

// Filled occupancy of a shape: uint8 [R^3], flat index (x*R + y)*R + z.
using OccupancyFn = std::function<std::vector<uint8_t>(const ShapeKey&)>;

// Where the VAE's shapes come from.
struct ShapeSet {
  int64_t resolution = 32;
  // The occupancy of a shape (the decoder's target); called from several threads at once.
  OccupancyFn occupancy;
  // The encoder's input when it reads another grid than the target (a coarser one: a decoder trained to
  // up-sample a frozen encoder's latent); unset = the encoder reads `occupancy`.
  int64_t input_resolution = 0;
  OccupancyFn input_occupancy;
  // The index-th shape of the training stream (any index >= 0; deterministic in index).
  std::function<ShapeKey(int64_t index)> train;
  // Fixed evaluation lists, decided before training: validation (tuning, logged during training) and
  // test (reported at the end; includes the held-out family's instances).
  std::vector<ShapeKey> val, test;
  std::string held_out_family;  // reported apart in IoU tables ("" = none)
};

// A thread-safe memo of an OccupancyFn (grids kept bit-packed, R^3 / 8 bytes each), for a training
// stream that cycles through fixed instances.
OccupancyFn cached_occupancy(OccupancyFn fn, int64_t resolution);

// Posterior noise of training sample `index`: standard normal float32 [shape], a function of
// (seed, index) alone.
torch::Tensor sample_noise(uint64_t seed, int64_t index, at::IntArrayRef shape);

// One rank's share of one step.
struct VaeBatch {
  int64_t step = 0;
  std::vector<int64_t> index;  // the samples' stream indices
  torch::Tensor occupancy;     // uint8 [b, 1, R, R, R] (pinned host memory when the loader pins)
  torch::Tensor input;         // uint8 [b, 1, Ri, Ri, Ri]: the encoder's grid when the set has input_occupancy, else undefined
  torch::Tensor noise;         // float32 [b, C, r, r, r] (pinned likewise)
};

struct LoaderOptions {
  int rank = 0, world = 1;
  int64_t global_batch = 1;
  int64_t start_step = 0;            // the first step to make a batch for
  uint64_t noise_seed = 0;           // sample_noise's seed
  std::vector<int64_t> latent_shape; // [C, r, r, r]
  int workers = 1;                   // threads making the samples of a batch
  int prefetch = 2;                  // batches kept ready ahead of next()
  bool pin_memory = false;           // batches in pinned host memory (CUDA training: asynchronous copies)
};

// Makes this rank's batches for steps start_step, start_step + 1, ... on a background thread (its
// samples on `workers` threads), keeping up to `prefetch` of them ready. An error while making a batch
// (a shape that cannot be made, say) is rethrown by the next() that reaches that batch.
class BatchLoader {
 public:
  BatchLoader(std::shared_ptr<const ShapeSet> shapes, LoaderOptions options);
  ~BatchLoader();  // stops the threads (a batch being made is finished first)
  BatchLoader(const BatchLoader&) = delete;
  BatchLoader& operator=(const BatchLoader&) = delete;
  // The next step's batch; waits when it is not made yet.
  VaeBatch next();
  // Makes the batch of `step` now, on the calling thread (what the background thread does).
  static VaeBatch make(const ShapeSet& shapes, const LoaderOptions& options, int64_t step);

 private:
  void produce();

  std::shared_ptr<const ShapeSet> shapes_;
  LoaderOptions options_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<VaeBatch> ready_;
  std::exception_ptr error_;
  int64_t next_step_;  // the step next() returns
  bool stop_ = false;
  std::thread thread_;
};

}  // namespace simu::training
