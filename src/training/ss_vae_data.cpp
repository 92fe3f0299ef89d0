#include "training/ss_vae_data.h"

#include <ATen/CPUGeneratorImpl.h>

#include <cstring>
#include <map>

#include "common/error.h"
#include "common/parallel.h"
#include "common/random.h"

namespace simu::training {

OccupancyFn cached_occupancy(OccupancyFn fn, int64_t resolution) {
  struct Memo {
    std::mutex mutex;
    std::map<std::pair<std::string, uint64_t>, std::vector<uint8_t>> packed;  // 8 voxels a byte
  };
  auto memo = std::make_shared<Memo>();
  const size_t n = static_cast<size_t>(resolution * resolution * resolution);
  return [fn = std::move(fn), memo, n](const ShapeKey& key) {
    const auto k = std::make_pair(key.family, key.seed);
    {
      std::lock_guard<std::mutex> lock(memo->mutex);
      if (auto it = memo->packed.find(k); it != memo->packed.end()) {
        std::vector<uint8_t> grid(n);
        for (size_t i = 0; i < n; ++i) grid[i] = (it->second[i >> 3] >> (i & 7)) & 1;
        return grid;
      }
    }
    // Made outside the lock (other threads make other shapes meanwhile), then kept.
    auto grid = fn(key);
    SIMU_CHECK(grid.size() == n, "shape {} seed {}: occupancy of {} voxels, {} expected", key.family, key.seed,
               grid.size(), n);
    std::vector<uint8_t> packed((n + 7) / 8, 0);
    for (size_t i = 0; i < n; ++i) packed[i >> 3] |= static_cast<uint8_t>((grid[i] != 0) << (i & 7));
    std::lock_guard<std::mutex> lock(memo->mutex);
    memo->packed.emplace(k, std::move(packed));
    return grid;
  };
}

torch::Tensor sample_noise(uint64_t seed, int64_t index, at::IntArrayRef shape) {
  auto gen = at::make_generator<at::CPUGeneratorImpl>(splitmix64(splitmix64(seed) ^ static_cast<uint64_t>(index)));
  return at::randn(shape, gen, torch::TensorOptions().dtype(torch::kFloat32));
}

// ---------------------------------------------------------------------------------------------
BatchLoader::BatchLoader(std::shared_ptr<const ShapeSet> shapes, LoaderOptions options)
    : shapes_(std::move(shapes)), options_(std::move(options)), next_step_(options_.start_step) {
  SIMU_CHECK(options_.world >= 1 && options_.global_batch % options_.world == 0,
             "batch loader: global batch {} is not divisible by the world size {}", options_.global_batch, options_.world);
  SIMU_CHECK(shapes_ && shapes_->occupancy && shapes_->train, "batch loader: the shape set has no training stream");
  thread_ = std::thread([this] { produce(); });
}

BatchLoader::~BatchLoader() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

VaeBatch BatchLoader::next() {
  std::unique_lock<std::mutex> lock(mutex_);
  cv_.wait(lock, [&] { return !ready_.empty() || error_; });
  // Batches made before a failure are still handed out in order; the failure comes at its own batch.
  if (ready_.empty()) std::rethrow_exception(error_);
  VaeBatch b = std::move(ready_.front());
  ready_.pop_front();
  SIMU_CHECK(b.step == next_step_, "batch loader: batch of step {} where step {} was expected", b.step, next_step_);
  ++next_step_;
  lock.unlock();
  cv_.notify_all();
  return b;
}

void BatchLoader::produce() {
  try {
    for (int64_t step = options_.start_step;; ++step) {
      {
        std::unique_lock<std::mutex> lock(mutex_);
        cv_.wait(lock, [&] { return stop_ || static_cast<int64_t>(ready_.size()) < options_.prefetch; });
        if (stop_) return;
      }
      auto batch = make(*shapes_, options_, step);
      {
        std::lock_guard<std::mutex> lock(mutex_);
        ready_.push_back(std::move(batch));
      }
      cv_.notify_all();
    }
  } catch (...) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      error_ = std::current_exception();
    }
    cv_.notify_all();
  }
}

VaeBatch BatchLoader::make(const ShapeSet& shapes, const LoaderOptions& o, int64_t step) {
  const int64_t b = o.global_batch / o.world, R = shapes.resolution;
  VaeBatch batch;
  batch.step = step;
  for (int64_t j = 0; j < b; ++j) batch.index.push_back(step * o.global_batch + o.rank * b + j);
  std::vector<int64_t> noise_shape = {b};
  noise_shape.insert(noise_shape.end(), o.latent_shape.begin(), o.latent_shape.end());
  batch.occupancy = torch::empty({b, 1, R, R, R}, torch::TensorOptions().dtype(torch::kUInt8).pinned_memory(o.pin_memory));
  batch.noise = torch::empty(noise_shape, torch::TensorOptions().dtype(torch::kFloat32).pinned_memory(o.pin_memory));
  const int64_t Ri = shapes.input_resolution;
  if (shapes.input_occupancy)
    batch.input = torch::empty({b, 1, Ri, Ri, Ri}, torch::TensorOptions().dtype(torch::kUInt8).pinned_memory(o.pin_memory));
  // Each sample writes its own rows: [j] of the grid and of the noise.
  parallel_for_each(b, o.workers, [&](int64_t j) {
    const int64_t i = batch.index[j];
    const ShapeKey key = shapes.train(i);
    const auto grid = shapes.occupancy(key);
    SIMU_CHECK(static_cast<int64_t>(grid.size()) == R * R * R, "shape {} seed {} (sample {}): occupancy of {} voxels, {} expected",
               key.family, key.seed, i, grid.size(), R * R * R);
    std::memcpy(batch.occupancy[j].data_ptr<uint8_t>(), grid.data(), grid.size());
    if (shapes.input_occupancy) {
      const auto in = shapes.input_occupancy(key);
      SIMU_CHECK(static_cast<int64_t>(in.size()) == Ri * Ri * Ri,
                 "shape {} seed {} (sample {}): encoder input of {} voxels, {} expected", key.family, key.seed, i,
                 in.size(), Ri * Ri * Ri);
      std::memcpy(batch.input[j].data_ptr<uint8_t>(), in.data(), in.size());
    }
    batch.noise[j].copy_(sample_noise(o.noise_seed, i, o.latent_shape));
  });
  return batch;
}

}  // namespace simu::training
