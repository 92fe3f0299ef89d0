// Where the trainer's pairs come from: the sharding contract (one epoch order for every rank and
// every source: data::epoch_permutation), the HDF5 pair cache source and an in-memory one.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "data/pair_cache.h"
#include "training/objective.h"

namespace simu::training {

// One preference pair as the trainer sees it.
struct Pair {
  int64_t id = 0;      // stable record index in the cache (seeds its noise)
  data::PairKind kind = data::PairKind::OcclusionCompletion;
  torch::Tensor x_pos, x_neg;  // [T, C] float32
  torch::Tensor cond;          // [l, Cc] float32 (l may differ between pairs); undefined for inputs
  // Inputs-mode pairs: the condition embedder's inputs (kwarg -> [ch, S, S] float32), embedded in the
  // step by the trainer's condition embedder (Trainer::set_condition_embedder).
  std::map<std::string, torch::Tensor> inputs;
};

// A pair cache record as the trainer sees it (id = the record index).
Pair pair_from_record(const data::PairRecord& r);

// Source of this rank's share of each global batch (the HDF5 PairStream or an in-memory one).
class PairSource {
 public:
  virtual ~PairSource() = default;
  // This rank's pairs of the next global batch (global_batch / world of them).
  virtual std::vector<Pair> next_batch() = 0;
  // Position of the next batch (what a checkpoint stores).
  virtual DataPosition position() const = 0;
};
// Opens a source for (rank, world, global batch, seed) at a position.
using PairSourceFactory =
    std::function<std::unique_ptr<PairSource>(int rank, int world, int64_t global_batch, uint64_t seed, DataPosition)>;

// The order of n in-memory samples with the stream's contract: each epoch the permutation
// data::epoch_permutation(n, seed, epoch) that the HDF5 PairStream uses too (one order for every
// source), that every rank computes alike; global batch b of the epoch = perm[b*G, (b+1)*G) (the tail
// that does not fill a batch is skipped); rank r takes the contiguous slice [r*G/W, (r+1)*G/W).
class EpochOrder {
 public:
  EpochOrder(int64_t n, int rank, int world, int64_t global_batch, uint64_t seed, DataPosition start);
  // This rank's sample indices of the next global batch (G / W of them).
  std::vector<int64_t> next();
  DataPosition position() const { return pos_; }

 private:
  int64_t n_;
  int rank_, world_;
  int64_t global_;
  uint64_t seed_;
  DataPosition pos_;
  std::vector<int64_t> perm_;
  int64_t perm_epoch_ = -1;
};

// In-memory pairs in EpochOrder.
class MemoryPairSource : public PairSource {
 public:
  MemoryPairSource(std::shared_ptr<const std::vector<Pair>> pairs, int rank, int world, int64_t global_batch,
                   uint64_t seed, DataPosition start);
  std::vector<Pair> next_batch() override;
  DataPosition position() const override { return order_.position(); }

 private:
  std::shared_ptr<const std::vector<Pair>> pairs_;
  EpochOrder order_;
};

// Source over the HDF5 pair cache (data/pair_cache.h PairStream) with `prefetch` batches read ahead.
PairSourceFactory pair_cache_source(const std::string& path, int64_t prefetch);

}  // namespace simu::training
