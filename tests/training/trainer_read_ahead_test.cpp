// The trainer's read-ahead (Trainer::set_read_ahead; on by default on CUDA, where it also stages the
// batches in pinned memory and uploads them on a side stream): reading and staging the next step's
// batch while a step runs trains exactly like reading each batch at its step's start (bit-identical
// on the CPU, with several forward groups per micro-batch), a checkpoint taken while a batch waits
// stores the data position before that batch, and resuming from it is bit-exact.
#include "test_util.h"
#include "toy_policy.h"
#include "training/trainer.h"

using namespace simu::training;
using simu::testing::memory_source;
using simu::testing::toy_config;
using simu::testing::ToyPolicy;

namespace {

constexpr int64_t T = 6, C = 4, L = 3, Cc = 5, R = 2;

// n toy pairs whose condition lengths alternate between L and L + 2: every micro-batch of 2 runs as
// two forward groups.
std::shared_ptr<std::vector<Pair>> mixed_pairs(int64_t n, uint64_t seed) {
  auto pairs = simu::testing::toy_pairs(n, T, C, L, Cc, seed);
  for (int64_t i = 1; i < n; i += 2) (*pairs)[i].cond = torch::randn({L + 2, Cc});
  return pairs;
}

struct Trained {
  std::vector<StepMetrics> metrics;
  std::vector<torch::Tensor> adapters;
};

// `steps` steps of a fresh toy policy (global batch 4, micro 2) with read-ahead on or off.
Trained train(const std::shared_ptr<std::vector<Pair>>& pairs, bool read_ahead, int steps, const std::string& name) {
  auto solo = make_solo_communicator();
  ToyPolicy m(C, Cc, R, 5);
  Trainer tr(toy_config(simu::testing::temp_dir(name), steps, 4, 2), m, memory_source(pairs), *solo, torch::kCPU);
  tr.set_read_ahead(read_ahead);
  Trained r;
  for (int s = 0; s < steps; ++s) r.metrics.push_back(tr.step());
  r.adapters = {m.A.detach().clone(), m.B.detach().clone()};
  return r;
}

}  // namespace

// Read-ahead on and off: the same adapters and the same metrics, bit for bit, over steps that cross
// an epoch (10 pairs, 2 batches per epoch).
TEST(TrainerReadAhead, TrainsLikeReadingEachStep) {
  auto pairs = mixed_pairs(10, 31);
  const Trained off = train(pairs, false, 5, "read_ahead_off"), on = train(pairs, true, 5, "read_ahead_on");
  for (size_t i = 0; i < off.adapters.size(); ++i) EXPECT_TRUE(torch::equal(on.adapters[i], off.adapters[i])) << i;
  for (int s = 0; s < 5; ++s) {
    SCOPED_TRACE("step " + std::to_string(s + 1));
    EXPECT_EQ(on.metrics[s].loss, off.metrics[s].loss);
    EXPECT_EQ(on.metrics[s].grad_norm, off.metrics[s].grad_norm);
    EXPECT_EQ(on.metrics[s].accuracy, off.metrics[s].accuracy);
    EXPECT_EQ(on.metrics[s].per_kind, off.metrics[s].per_kind);
    // Reading ahead is counted as data time, not compute; the phases still fit in the step (disjoint
    // intervals of one clock; 1 ns for the float64 sum of four durations).
    EXPECT_LE(on.metrics[s].seconds_data + on.metrics[s].seconds_compute + on.metrics[s].seconds_allreduce +
                  on.metrics[s].seconds_optimizer,
              on.metrics[s].seconds_step + 1e-9);
  }
  EXPECT_FALSE(torch::equal(on.adapters[0], ToyPolicy(C, Cc, R, 5).A)) << "training did not move the adapter";
}

// A checkpoint after step 3 with step 4's batch already read: its data position is the one a trainer
// without read-ahead stores (before step 4's batch), and a fresh trainer resumed from it finishes with
// the adapters and losses of an uninterrupted run.
TEST(TrainerReadAhead, CheckpointAndResumeWithABatchReadAhead) {
  auto pairs = mixed_pairs(10, 32);
  const Trained whole = train(pairs, true, 6, "read_ahead_whole");
  auto solo = make_solo_communicator();
  const std::string out = simu::testing::temp_dir("read_ahead_resume");
  nlohmann::json position;
  {
    ToyPolicy m(C, Cc, R, 5);
    Trainer tr(toy_config(out, 6, 4, 2), m, memory_source(pairs), *solo, torch::kCPU);
    tr.set_read_ahead(true);
    for (int s = 0; s < 3; ++s) tr.step();
    position = tr.checkpoint_data().state.at("data_position");
    tr.save();
    tr.step();  // work lost by the "crash"
  }
  {
    ToyPolicy m(C, Cc, R, 5);
    Trainer tr(toy_config(simu::testing::temp_dir("read_ahead_ref"), 6, 4, 2), m, memory_source(pairs), *solo,
               torch::kCPU);
    tr.set_read_ahead(false);
    for (int s = 0; s < 3; ++s) tr.step();
    EXPECT_EQ(position, tr.checkpoint_data().state.at("data_position"));
  }
  EXPECT_EQ(position.at("epoch").get<int64_t>(), 1);  // 3 batches of 2 per epoch: epoch 1, batch 1
  EXPECT_EQ(position.at("step").get<int64_t>(), 1);
  ToyPolicy m(C, Cc, R, 5, 99);  // another adapter init: everything must come from the checkpoint
  Trainer tr(toy_config(out, 6, 4, 2), m, memory_source(pairs), *solo, torch::kCPU);
  tr.set_read_ahead(true);
  tr.resume(resolve_resume(out + "/checkpoints", "latest"));
  ASSERT_EQ(tr.steps_done(), 3);
  for (int s = 3; s < 6; ++s) EXPECT_EQ(tr.step().loss, whole.metrics[s].loss) << "step " << s + 1;
  EXPECT_TRUE(torch::equal(m.A, whole.adapters[0]) && torch::equal(m.B, whole.adapters[1])) << "adapters differ";
}
