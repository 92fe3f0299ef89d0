// Stage-1 pretraining on CUDA with the tiny model: bf16 autocast steps keep every parameter fp32 on the
// GPU and start from the loss of an fp32 CPU step on the same model, samples and draws; the read-ahead
// (pinned gathers, uploads on a side stream) and the device-side update give the plain paths' step.
#include "stage1_fixture.h"
#include "test_util.h"

using namespace simu::training;
using simu::testing::tiny_objective;
using simu::testing::tiny_samples;
using simu::testing::tiny_stage1_config;

namespace {

// `steps` steps of the tiny model on device in precision, read-ahead and device update as given.
std::vector<StepMetrics> train_tiny(const std::string& name, const std::string& device, const std::string& precision,
                                    int steps, bool read_ahead = true, bool device_update = true,
                                    std::vector<torch::Tensor>* weights = nullptr) {
  auto cfg = tiny_stage1_config(simu::testing::temp_dir(name), steps, 4, 2,
                                "objective: {p_unconditional: 0.3, shortcut_fraction: 0.3}\n");
  cfg.train.device = device;
  cfg.train.precision = precision;
  const torch::Device dev = device == "cuda" ? torch::Device(torch::kCUDA, 0) : torch::Device(torch::kCPU);
  auto solo = make_solo_communicator();
  Trainer tr(cfg, tiny_objective(cfg, tiny_samples(8, 31), nullptr, -1, dev), *solo, dev);
  if (dev.is_cuda()) {
    tr.set_read_ahead(read_ahead);
    tr.set_device_update(device_update);
  }
  std::vector<StepMetrics> m;
  for (int s = 0; s < steps; ++s) m.push_back(tr.step());
  if (weights)
    for (const auto& [n, p] : tr.objective().parameters()) weights->push_back(p.detach().clone());
  return m;
}

}  // namespace

// bf16 on the GPU vs fp32 on the CPU: the first step's loss (before any update) within bf16 rounding
// (2^-8 per product through ~6 layers: 3e-2 relative), every step finite, parameters fp32 on CUDA.
TEST(Stage1Gpu, Bf16StepsKeepFp32ParametersAndStartFromTheFp32Loss) {
  SIMU_REQUIRE_CUDA();
  const auto cpu = train_tiny("s1gpu_cpu", "cpu", "fp32", 1);
  std::vector<torch::Tensor> w;
  const auto gpu = train_tiny("s1gpu_bf16", "cuda", "bf16", 3, true, true, &w);
  EXPECT_NEAR(gpu[0].loss, cpu[0].loss, 3e-2 * cpu[0].loss);
  for (const auto& m : gpu) EXPECT_TRUE(std::isfinite(m.loss) && std::isfinite(m.grad_norm));
  for (const auto& t : w) {
    EXPECT_TRUE(t.is_cuda());
    EXPECT_EQ(t.scalar_type(), torch::kFloat32);
  }
}

// The fast paths against the reference paths on the GPU (fp32): the first step's loss and metrics
// are bit-identical (the same forward on the same staged data); its gradient norm agrees within the
// run-to-run spread of the attention backward's atomics (fp32 sums reordered: 1e-5 relative).
TEST(Stage1Gpu, ReadAheadAndDeviceUpdateMatchThePlainPaths) {
  SIMU_REQUIRE_CUDA();
  const auto fast = train_tiny("s1gpu_fast", "cuda", "fp32", 2, true, true);
  const auto plain = train_tiny("s1gpu_plain", "cuda", "fp32", 2, false, false);
  EXPECT_EQ(fast[0].loss, plain[0].loss);
  EXPECT_EQ(fast[0].per_kind, plain[0].per_kind);
  EXPECT_NEAR(fast[0].grad_norm, plain[0].grad_norm, 1e-5 * plain[0].grad_norm);
  EXPECT_NEAR(fast[1].loss, plain[1].loss, 1e-4 * plain[1].loss);  // after one update of ~lr
}
