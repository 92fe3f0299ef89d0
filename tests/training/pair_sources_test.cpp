// Tests that every pair source reads the same epoch order: the HDF5 cache source (pair_cache_source,
// data::PairStream) and MemoryPairSource give identical record sequences for one (seed, rank, world),
// both following data::epoch_permutation.
#include <memory>
#include <vector>

#include "common/fs.h"
#include "data/pair_cache.h"
#include "test_util.h"
#include "training/generator_policy.h"
#include "training/trainer.h"

using namespace simu::training;

TEST(PairSources, CacheAndMemorySourcesGiveTheSameOrder) {
  const auto dir = simu::testing::temp_dir("pair_sources");
  const std::string path = dir + "/pairs.h5";
  // 13 pairs, global batch 4: three batches per epoch, one pair left out of each epoch.
  simu::data::make_synthetic_cache(path, 13, {4, 3}, {5, 6}, /*seed=*/3, torch::kFloat32);
  const auto reader = simu::data::PairCacheReader::open(path);
  auto pairs = std::make_shared<std::vector<Pair>>();
  for (int64_t i = 0; i < reader.size(); ++i) pairs->push_back(pair_from_record(reader.read(i)));
  const uint64_t seed = 11;
  for (int world : {1, 2}) {
    for (int rank = 0; rank < world; ++rank) {
      auto cache = pair_cache_source(path, /*prefetch=*/1)(rank, world, 4, seed, DataPosition{});
      MemoryPairSource memory(pairs, rank, world, 4, seed, DataPosition{});
      // Three epochs: the order is the same batch by batch, and it is data::epoch_permutation's.
      for (int64_t b = 0; b < 9; ++b) {
        const auto perm = simu::data::epoch_permutation(13, seed, b / 3);
        const auto from_cache = cache->next_batch();
        const auto from_memory = memory.next_batch();
        ASSERT_EQ(from_cache.size(), from_memory.size());
        for (size_t i = 0; i < from_cache.size(); ++i) {
          EXPECT_EQ(from_cache[i].id, from_memory[i].id) << "world " << world << " rank " << rank << " batch " << b;
          const int64_t want = perm[static_cast<size_t>((b % 3) * 4 + rank * (4 / world) + static_cast<int64_t>(i))];
          EXPECT_EQ(from_memory[i].id, want) << "world " << world << " rank " << rank << " batch " << b;
        }
      }
      // The same place in the stream (the cache source rolls over to the next epoch eagerly, the memory
      // source on the next call): 9 batches of 3 per epoch read.
      const auto at = [](DataPosition p) { return p.epoch * 3 + p.step; };
      EXPECT_EQ(at(cache->position()), 9);
      EXPECT_EQ(at(memory.position()), 9);
    }
  }
  simu::fs::remove_tree(dir);
}
