// The trainer on CUDA with the generator policy: bf16 autocast steps keep the adapters fp32 on the
// GPU and follow an fp32 CPU run of the same model, pairs, noise and schedule within bf16 rounding.
// Its read-ahead (pinned staging, uploads on a side stream) against the plain upload path, and its
// device-side update (no host wait before AdamW) against the reference path.
#include <ATen/CPUGeneratorImpl.h>

#include <fstream>
#include <limits>

#include "flow_mid_config.h"
#include "models/generator.h"
#include "test_util.h"
#include "toy_policy.h"
#include "training/generator_policy.h"
#include "training/trainer.h"

using namespace simu::training;

namespace {

// Cosine of two flattened tensor lists.
double cosine(const std::vector<torch::Tensor>& a, const std::vector<torch::Tensor>& b) {
  double dot = 0, na = 0, nb = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    auto x = a[i].to(torch::kCPU, torch::kFloat64), y = b[i].to(torch::kCPU, torch::kFloat64);
    dot += (x * y).sum().item<double>();
    na += (x * x).sum().item<double>();
    nb += (y * y).sum().item<double>();
  }
  return dot / std::sqrt(na * nb);
}

}  // namespace

TEST(TrainerGpu, Bf16StepsKeepFp32AdaptersAndFollowFp32Cpu) {
  SIMU_REQUIRE_CUDA();
  const std::string model = simu::testing::mid_flow_config("trainer_gpu");
  // 8 pairs of the model's shape latent [512, 8] with 77 condition tokens; kinds alternate.
  auto gen = simu::models::load_generator(model, "", torch::kCPU);
  auto rng = at::make_generator<at::CPUGeneratorImpl>(21);
  const auto shape = gen->noise(1, rng, torch::kCPU).at("shape")[0].sizes().vec();
  auto pairs = std::make_shared<std::vector<Pair>>();
  for (int64_t i = 0; i < 8; ++i)
    pairs->push_back(Pair{i, static_cast<simu::data::PairKind>(i % 2), torch::randn(shape, rng), torch::randn(shape, rng),
                          torch::randn({77, gen->config().backbone.cond_channels}, rng)});
  auto source = [pairs](int rank, int world, int64_t gb, uint64_t seed, DataPosition pos) -> std::unique_ptr<PairSource> {
    return std::make_unique<MemoryPairSource>(pairs, rank, world, gb, seed, pos);
  };
  const int steps = 3;
  struct Run {
    std::vector<StepMetrics> metrics;
    std::vector<torch::Tensor> start, end;
  };
  auto train = [&](const std::string& device, const std::string& precision) {
    const std::string out = simu::testing::temp_dir("trainer_gpu_" + device);
    std::ofstream(out + "/cfg.yaml") << "model: {config: " << model << "}\n"
                                     << "lora: {r: 8, alpha: 16}\n"
                                        "objective: {beta: 50.0, weight_preservation: 1.0}\n"
                                        "optim: {lr: 0.001, warmup_steps: 0, clip_grad_norm: 1.0}\n"
                                        "data: {global_batch: 4, micro_batch: 2}\n"
                                     << "train: {steps: " << steps << ", device: " << device << ", precision: " << precision
                                     << ", seed: 3}\n"
                                     << "run: {out_dir: " << out << ", progress: false}\n";
    auto cfg = TrainConfig::load(out + "/cfg.yaml");
    const torch::Device dev = device == "cuda" ? torch::Device(torch::kCUDA) : torch::Device(torch::kCPU);
    auto policy = make_generator_policy(cfg, dev);
    Run r;
    for (auto& [name, p] : policy->adapter_parameters()) r.start.push_back(p.detach().to(torch::kCPU).clone());
    auto comm = Communicator::create(DistEnv{}, dev, std::chrono::seconds(60));  // a world of one
    Trainer tr(cfg, *policy, source, *comm, dev);
    for (int s = 0; s < steps; ++s) r.metrics.push_back(tr.step());
    for (auto& [name, p] : policy->adapter_parameters()) {
      // Adapters stay fp32 master weights on the training device (autocast computes in bf16).
      EXPECT_EQ(p.scalar_type(), torch::kFloat32) << name;
      EXPECT_EQ(p.device().type(), dev.type()) << name;
      r.end.push_back(p.detach().to(torch::kCPU).clone());
    }
    return r;
  };
  const Run cpu = train("cpu", "fp32");
  const Run gpu = train("cuda", "bf16");
  // Same start (train.seed fixes the LoRA init on every device).
  for (size_t i = 0; i < cpu.start.size(); ++i) ASSERT_TRUE(torch::equal(cpu.start[i], gpu.start[i])) << i;
  // Step 1: lora_B = 0, so d_theta = d_ref and every pair's loss is log 2 (both weights 1 here) on
  // both devices; the gradient is the first real comparison. bf16 operands: relative errors of 1e-3
  // to 1e-2 expected.
  const double first = std::log(2.0);
  EXPECT_NEAR(cpu.metrics[0].loss, first, 1e-6);
  EXPECT_NEAR(gpu.metrics[0].loss, first, 1e-6);
  for (int s = 0; s < steps; ++s) {
    SCOPED_TRACE("step " + std::to_string(s + 1));
    EXPECT_NEAR(gpu.metrics[s].grad_norm, cpu.metrics[s].grad_norm, 3e-2 * cpu.metrics[s].grad_norm);
    EXPECT_NEAR(gpu.metrics[s].loss, cpu.metrics[s].loss, 3e-2 * cpu.metrics[s].loss);
    for (const auto& [k, v] : cpu.metrics[s].per_kind) EXPECT_NEAR(gpu.metrics[s].per_kind.at(k), v, 2e-2 * v) << k;
  }
  // The adapters moved the same way: AdamW's early steps are close to lr x sign(gradient), so
  // elements whose gradient is within bf16 noise of zero may go the other way; the displacement as
  // a whole must agree.
  std::vector<torch::Tensor> dc, dg;
  for (size_t i = 0; i < cpu.end.size(); ++i) {
    dc.push_back(cpu.end[i] - cpu.start[i]);
    dg.push_back(gpu.end[i] - gpu.start[i]);
  }
  const double cos = cosine(dc, dg);
  EXPECT_GT(cos, 0.9) << "GPU bf16 and CPU fp32 adapter updates point different ways";
  RecordProperty("update_cosine", std::to_string(cos));
}

// Read-ahead on CUDA (the default there: the next batch stacked into pinned memory and copied on a side
// stream while a step runs, each forward group waiting for its copies) trains like the reference path
// (each batch read at its step's start, stack(...).to(device)): long f16 conditions of two lengths
// (two forward groups per micro-batch) make the copies take a while, so a forward that did not wait
// for them would read stale or partial memory.
TEST(TrainerGpu, ReadAheadUploadsMatchThePlainUpload) {
  SIMU_REQUIRE_CUDA();
  const int64_t T = 64, C = 8, Cc = 64, R = 4, steps = 5;
  auto pairs = simu::testing::toy_pairs(12, T, C, 20000, Cc, 41);  // 12 pairs, 3 batches of 4 per epoch
  for (size_t i = 0; i < pairs->size(); ++i) {
    auto& p = (*pairs)[i];
    if (i % 2) p.cond = torch::randn({19000, Cc});
    p.cond = p.cond.to(torch::kHalf);  // the cache's stored dtype: converted on the device
  }
  const torch::Device dev(torch::kCUDA);
  auto run = [&](bool read_ahead) {
    simu::testing::ToyPolicy m(C, Cc, R, 5);
    m.to(dev);
    auto cfg = simu::testing::toy_config(simu::testing::temp_dir(read_ahead ? "gpu_ahead_on" : "gpu_ahead_off"), steps, 4, 2);
    cfg.train.device = "cuda";
    auto comm = Communicator::create(DistEnv{}, dev, std::chrono::seconds(60));  // a world of one
    Trainer tr(cfg, m, simu::testing::memory_source(pairs), *comm, dev);
    tr.set_read_ahead(read_ahead);
    std::vector<double> losses;
    for (int s = 0; s < steps; ++s) losses.push_back(tr.step().loss);
    torch::cuda::synchronize();
    return std::make_pair(losses, std::vector<torch::Tensor>{m.A.detach().cpu(), m.B.detach().cpu()});
  };
  const auto [loss_off, ad_off] = run(false);
  const auto [loss_on, ad_on] = run(true);
  for (int s = 0; s < steps; ++s) EXPECT_NEAR(loss_on[s], loss_off[s], 1e-6 * std::abs(loss_off[s])) << "step " << s + 1;
  for (size_t i = 0; i < ad_off.size(); ++i) EXPECT_TRUE(simu::testing::close(ad_on[i], ad_off[i], 1e-6, i ? "B" : "A"));
  EXPECT_FALSE(torch::equal(ad_on[0], simu::testing::ToyPolicy(C, Cc, R, 5).A)) << "training did not move the adapter";
}

namespace {
// A trainer run on CUDA over toy pairs: its metrics, adapters and optimizer state at the end.
struct UpdateRun {
  std::vector<StepMetrics> metrics;
  std::vector<torch::Tensor> adapters;
  std::map<std::string, torch::Tensor> state;
};
UpdateRun train_toy_on_cuda(const std::shared_ptr<std::vector<Pair>>& pairs, bool device_update, double clip,
                            const std::string& name) {
  const int64_t C = 8, Cc = 64, R = 4, steps = 5;
  const torch::Device dev(torch::kCUDA);
  simu::testing::ToyPolicy m(C, Cc, R, 5);
  m.to(dev);
  auto cfg = simu::testing::toy_config(simu::testing::temp_dir(name), steps, 4, 2);
  cfg.train.device = "cuda";
  cfg.optim.clip_grad_norm = clip;
  auto comm = Communicator::create(DistEnv{}, dev, std::chrono::seconds(60));  // a world of one
  Trainer tr(cfg, m, simu::testing::memory_source(pairs), *comm, dev);
  tr.set_device_update(device_update);
  UpdateRun r;
  for (int s = 0; s < steps; ++s) r.metrics.push_back(tr.step());
  r.adapters = {m.A.detach().cpu(), m.B.detach().cpu()};
  r.state = tr.optimizer().state_dict();
  return r;
}
}  // namespace

// The device-side update (all-reduce, norm, clipping and AdamW issued with no host wait, one copy of
// the metrics at the step's end) against the reference path that waits for the metrics and the norm
// first: bit-identical metrics, adapters and optimizer state, with clipping in every step (a tiny
// clip_grad_norm) and in none (a huge one: the device multiplies by exactly 1).
TEST(TrainerGpu, DeviceUpdateMatchesTheHostPath) {
  SIMU_REQUIRE_CUDA();
  auto pairs = simu::testing::toy_pairs(12, 64, 8, 300, 64, 43);
  for (const double clip : {1e-4, 1e9}) {
    SCOPED_TRACE("clip_grad_norm " + std::to_string(clip));
    const auto ref = train_toy_on_cuda(pairs, false, clip, "gpu_update_host");
    const auto dev = train_toy_on_cuda(pairs, true, clip, "gpu_update_device");
    for (size_t s = 0; s < ref.metrics.size(); ++s) {
      SCOPED_TRACE("step " + std::to_string(s + 1));
      EXPECT_EQ(dev.metrics[s].loss, ref.metrics[s].loss);
      EXPECT_EQ(dev.metrics[s].grad_norm, ref.metrics[s].grad_norm);
      EXPECT_EQ(dev.metrics[s].accuracy, ref.metrics[s].accuracy);
      EXPECT_EQ(dev.metrics[s].margin, ref.metrics[s].margin);
      EXPECT_EQ(dev.metrics[s].lr, ref.metrics[s].lr);
      EXPECT_EQ(dev.metrics[s].per_kind, ref.metrics[s].per_kind);
      if (clip < 1) EXPECT_GT(ref.metrics[s].grad_norm, clip) << "the tiny clip must clip";
      if (clip > 1) EXPECT_LT(ref.metrics[s].grad_norm, clip);
    }
    for (size_t i = 0; i < ref.adapters.size(); ++i) EXPECT_TRUE(torch::equal(dev.adapters[i], ref.adapters[i])) << i;
    ASSERT_EQ(dev.state.size(), ref.state.size());
    for (const auto& [k, v] : ref.state) EXPECT_TRUE(torch::equal(dev.state.at(k), v)) << k;
  }
}

// With the device-side update a non-finite loss still stops training with the step named, and the
// update it skipped on the device left the adapters and the optimizer state (moments, step counts)
// as they were.
TEST(TrainerGpu, DeviceUpdateSkipsANonFiniteStep) {
  SIMU_REQUIRE_CUDA();
  auto pairs = simu::testing::toy_pairs(8, 64, 8, 300, 64, 21);
  const torch::Device dev(torch::kCUDA);
  simu::testing::ToyPolicy m(8, 64, 4, 6);
  m.to(dev);
  auto cfg = simu::testing::toy_config(simu::testing::temp_dir("gpu_update_nonfinite"), 6, 8, 8);
  cfg.train.device = "cuda";
  auto comm = Communicator::create(DistEnv{}, dev, std::chrono::seconds(60));
  Trainer tr(cfg, m, simu::testing::memory_source(pairs), *comm, dev);
  tr.set_read_ahead(false);  // the poisoned pair must be read at step 3 itself
  tr.step();
  tr.step();
  (*pairs)[3].x_pos = (*pairs)[3].x_pos.clone();
  (*pairs)[3].x_pos[0][0] = std::numeric_limits<float>::quiet_NaN();
  const std::vector<torch::Tensor> before = {m.A.detach().cpu(), m.B.detach().cpu()};
  const auto state_before = tr.optimizer().state_dict();
  const std::string msg = simu::testing::error_of([&] { tr.step(); });
  EXPECT_NE(msg.find("step 3: non-finite loss"), std::string::npos) << msg;
  EXPECT_EQ(tr.steps_done(), 2);
  EXPECT_TRUE(torch::equal(m.A.detach().cpu(), before[0]));
  EXPECT_TRUE(torch::equal(m.B.detach().cpu(), before[1]));
  const auto state_after = tr.optimizer().state_dict();
  ASSERT_EQ(state_after.size(), state_before.size());
  for (const auto& [k, v] : state_before) EXPECT_TRUE(torch::equal(state_after.at(k), v)) << k;
}
