// The training stream over a pair cache: epoch_permutation, PairStream and collate (pair_cache.h).
#include <fmt/ranges.h>

#include <algorithm>
#include <random>

#include "common/error.h"
#include "common/random.h"
#include "data/pair_cache.h"

namespace simu::data {

std::vector<int64_t> epoch_permutation(int64_t n, uint64_t seed, int64_t epoch) {
  std::vector<int64_t> perm(static_cast<size_t>(std::max<int64_t>(n, 0)));
  std::iota(perm.begin(), perm.end(), 0);
  std::mt19937_64 rng(splitmix64(seed ^ splitmix64(static_cast<uint64_t>(epoch) + 0x5851F42D4C957F2DULL)));
  // Fisher-Yates with an unbiased bounded draw by rejection (exactly specified, unlike
  // std::uniform_int_distribution, whose algorithm differs between standard libraries).
  for (int64_t i = n - 1; i > 0; --i) {
    const uint64_t range = static_cast<uint64_t>(i) + 1;
    const uint64_t limit = std::numeric_limits<uint64_t>::max() - std::numeric_limits<uint64_t>::max() % range;
    uint64_t x;
    do x = rng();
    while (x >= limit);
    std::swap(perm[i], perm[static_cast<int64_t>(x % range)]);
  }
  return perm;
}

PairStream::PairStream(std::string path, int rank, int world, int64_t global_batch, uint64_t seed, StreamPosition start,
                       int prefetch)
    : reader_(PairCacheReader::open(path)),
      rank_(rank),
      world_(world),
      global_batch_(global_batch),
      seed_(seed),
      prefetch_(static_cast<size_t>(std::max(prefetch, 1))) {
  SIMU_CHECK(world >= 1 && rank >= 0 && rank < world, "pair stream '{}': rank {} is not in 0..{}", path, rank, world - 1);
  SIMU_CHECK(global_batch >= 1 && global_batch % world == 0,
             "pair stream '{}': global batch {} must be a positive multiple of the world size {}", path, global_batch,
             world);
  const int64_t n = reader_.size();
  if (n < global_batch)
    fail_hint("use a larger cache or a smaller global batch",
              "pair stream '{}': the cache has {} pairs, fewer than one global batch of {}", path, n, global_batch);
  SIMU_CHECK(start.epoch >= 0 && start.step >= 0, "pair stream '{}': start position ({}, {}) is negative", path,
             start.epoch, start.step);
  local_batch_ = global_batch / world;
  steps_per_epoch_ = n / global_batch;
  // Normalize the start (a step past the epoch's end rolls over).
  start.epoch += start.step / steps_per_epoch_;
  start.step %= steps_per_epoch_;
  position_ = start;
  thread_ = std::thread([this, start] { produce(start); });
}

PairStream::~PairStream() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void PairStream::produce(StreamPosition pos) {
  std::vector<int64_t> perm;
  int64_t perm_epoch = -1;
  try {
    while (true) {
      // This rank's slice of the global batch at pos.
      if (perm_epoch != pos.epoch) {
        perm = epoch_permutation(reader_.size(), seed_, pos.epoch);
        perm_epoch = pos.epoch;
      }
      Item item;
      const int64_t base = pos.step * global_batch_ + rank_ * local_batch_;
      item.batch.reserve(static_cast<size_t>(local_batch_));
      for (int64_t k = 0; k < local_batch_; ++k) {
        {
          std::lock_guard<std::mutex> lock(mutex_);
          if (stop_) return;
        }
        item.batch.push_back(reader_.read(perm[base + k]));
      }
      // Advance, rolling over at the epoch's end.
      pos.step += 1;
      if (pos.step == steps_per_epoch_) {
        pos.step = 0;
        pos.epoch += 1;
      }
      item.after = pos;
      // Wait for room in the queue.
      std::unique_lock<std::mutex> lock(mutex_);
      cv_.wait(lock, [&] { return stop_ || queue_.size() < prefetch_; });
      if (stop_) return;
      queue_.push_back(std::move(item));
      cv_.notify_all();
    }
  } catch (...) {
    std::lock_guard<std::mutex> lock(mutex_);
    Item item;
    item.error = std::current_exception();
    queue_.push_back(std::move(item));
    cv_.notify_all();
  }
}

std::vector<PairRecord> PairStream::next_batch() {
  std::unique_lock<std::mutex> lock(mutex_);
  cv_.wait(lock, [&] { return !queue_.empty(); });
  auto& front = queue_.front();
  if (front.error) std::rethrow_exception(front.error);  // stays queued: every later call rethrows too
  Item item = std::move(front);
  queue_.pop_front();
  position_ = item.after;
  cv_.notify_all();
  return std::move(item.batch);
}

StreamPosition PairStream::position() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return position_;
}

// ---------------------------------------------------------------------------------------------
// Collate.

PairBatch collate(const std::vector<PairRecord>& records) {
  SIMU_CHECK(!records.empty(), "collate: no records");
  const auto& first = records.front();
  int64_t max_len = 0;
  for (const auto& r : records) {
    SIMU_CHECK(r.cond.defined(), "collate: pair '{}' has no condition tokens (an inputs-mode record: its tokens are "
               "made by the condition embedder at training time)", r.id);
    SIMU_CHECK(r.latent_pos.sizes() == first.latent_pos.sizes() && r.latent_neg.sizes() == first.latent_pos.sizes(),
               "collate: pair '{}' has latents [{}], expected [{}]", r.id, fmt::join(r.latent_pos.sizes(), ", "),
               fmt::join(first.latent_pos.sizes(), ", "));
    SIMU_CHECK(r.cond.dim() == 2 && r.cond.size(1) == first.cond.size(1),
               "collate: pair '{}' has cond [{}], expected [l, {}]", r.id, fmt::join(r.cond.sizes(), ", "),
               first.cond.size(1));
    max_len = std::max(max_len, r.cond.size(0));
  }
  const int64_t b = static_cast<int64_t>(records.size());
  PairBatch out;
  std::vector<torch::Tensor> pos, neg;
  out.cond = torch::zeros({b, max_len, first.cond.size(1)}, torch::kFloat32);  // [B, Lmax, Cc]
  out.cond_mask = torch::zeros({b, max_len}, torch::kBool);                    // [B, Lmax]
  out.weight = torch::empty({b}, torch::kFloat32);
  out.kind = torch::empty({b}, torch::kUInt8);
  for (int64_t i = 0; i < b; ++i) {
    const auto& r = records[i];
    pos.push_back(r.latent_pos.to(torch::kFloat32));
    neg.push_back(r.latent_neg.to(torch::kFloat32));
    const int64_t len = r.cond.size(0);
    out.cond[i].narrow(0, 0, len).copy_(r.cond);
    out.cond_mask[i].narrow(0, 0, len).fill_(true);
    out.weight[i] = r.weight;
    out.kind[i] = static_cast<int64_t>(r.kind);
    out.ids.push_back(r.id);
  }
  out.latent_pos = torch::stack(pos);  // [B, T, C]
  out.latent_neg = torch::stack(neg);  // [B, T, C]
  return out;
}

}  // namespace simu::data
