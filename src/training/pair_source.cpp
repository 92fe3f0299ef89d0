#include "training/pair_source.h"

#include "common/error.h"

namespace simu::training {

Pair pair_from_record(const data::PairRecord& r) {
  Pair p;
  p.id = r.index;
  p.kind = r.kind;
  p.x_pos = r.latent_pos;
  p.x_neg = r.latent_neg;
  p.cond = r.cond;
  p.inputs = r.inputs;
  return p;
}

EpochOrder::EpochOrder(int64_t n, int rank, int world, int64_t global_batch, uint64_t seed, DataPosition start)
    : n_(n), rank_(rank), world_(world), global_(global_batch), seed_(seed), pos_(start) {
  SIMU_CHECK(global_ % world_ == 0, "global batch {} is not divisible by the world size {}", global_, world_);
  SIMU_CHECK(n_ >= global_, "{} samples cannot fill one global batch of {}", n_, global_);
}

std::vector<int64_t> EpochOrder::next() {
  if (pos_.step >= n_ / global_) {
    ++pos_.epoch;
    pos_.step = 0;
  }
  if (perm_epoch_ != pos_.epoch) {
    perm_ = simu::data::epoch_permutation(n_, seed_, pos_.epoch);
    perm_epoch_ = pos_.epoch;
  }
  const int64_t share = global_ / world_;
  std::vector<int64_t> out;
  for (int64_t i = 0; i < share; ++i) out.push_back(perm_[pos_.step * global_ + rank_ * share + i]);
  ++pos_.step;
  return out;
}

MemoryPairSource::MemoryPairSource(std::shared_ptr<const std::vector<Pair>> pairs, int rank, int world,
                                   int64_t global_batch, uint64_t seed, DataPosition start)
    : pairs_(std::move(pairs)), order_(static_cast<int64_t>(pairs_->size()), rank, world, global_batch, seed, start) {}

std::vector<Pair> MemoryPairSource::next_batch() {
  std::vector<Pair> out;
  for (int64_t i : order_.next()) out.push_back((*pairs_)[i]);
  return out;
}

namespace {

// PairStream seen through PairSource.
class CacheSource : public PairSource {
 public:
  CacheSource(const std::string& path, int rank, int world, int64_t global_batch, uint64_t seed, DataPosition pos,
              int64_t prefetch)
      : stream_(path, rank, world, global_batch, seed, simu::data::StreamPosition{pos.epoch, pos.step}, prefetch) {}
  std::vector<Pair> next_batch() override {
    std::vector<Pair> out;
    for (const auto& r : stream_.next_batch()) out.push_back(pair_from_record(r));
    return out;
  }
  DataPosition position() const override {
    auto p = stream_.position();
    return {p.epoch, p.step};
  }

 private:
  simu::data::PairStream stream_;
};

}  // namespace

PairSourceFactory pair_cache_source(const std::string& path, int64_t prefetch) {
  return [path, prefetch](int rank, int world, int64_t gb, uint64_t seed, DataPosition pos) -> std::unique_ptr<PairSource> {
    return std::make_unique<CacheSource>(path, rank, world, gb, seed, pos, prefetch);
  };
}

}  // namespace simu::training
