// LoRA on CUDA under bf16 autocast: adapter parameters stay fp32 (and get fp32 gradients) while the
// compute follows autocast; losses stay close to the fp32 fixture; merge works on the device.
#include <fmt/format.h>

#include "data/safetensors.h"
#include "lora/lora.h"
#include "models/generator.h"
#include "models/precision.h"
#include "models/linear.h"
#include "test_util.h"

namespace {

torch::Tensor fm_loss_cuda(simu::models::Generator& gen, const std::map<std::string, torch::Tensor>& m,
                           const std::string& which) {
  const torch::Device dev(torch::kCUDA);
  auto t = m.at("in.t").to(dev);
  auto tb = t.view({-1, 1, 1});
  auto x = m.at("in.x_" + which).to(dev), eps = m.at("in.eps_" + which).to(dev);
  simu::models::Latents latents;
  latents["shape"] = (1 - tb) * eps + tb * x;
  for (const auto& [k, v] : m)
    if (k.rfind("in.pose.", 0) == 0) latents[k.substr(8)] = v.to(dev);
  simu::models::Autocast autocast(simu::models::Precision::kBf16);
  auto pred = gen->backbone()->forward(latents, t * 1000, m.at("in.cond").to(dev), torch::zeros_like(t));
  return (pred.at("shape").to(torch::kFloat32) - (x - eps)).pow(2).mean({1, 2});
}

}  // namespace

TEST(LoraGpu, Bf16AutocastKeepsFp32AdaptersAndMatchesFixture) {
  SIMU_REQUIRE_CUDA();
  auto gen = simu::models::load_generator(simu::testing::fixture("ss_generator_small.json"),
                                          simu::testing::fixture("ss_generator_small.safetensors"), torch::kCUDA);
  simu::lora::load_peft(simu::testing::fixture("lora_small"), *gen);
  const auto m = simu::data::load_safetensors(simu::testing::fixture("fmdpo_small_io.safetensors"));
  auto pos = fm_loss_cuda(gen, m, "pos");
  EXPECT_TRUE(simu::testing::close(pos, m.at("out.loss_pos_policy"), 3e-2, "bf16 loss_pos_policy"));
  fmt::print("bf16 policy rel err {:.3g}\n", simu::testing::rel_err(pos, m.at("out.loss_pos_policy")));
  pos.sum().backward();
  for (auto& [name, p] : simu::lora::lora_parameters(*gen)) {
    EXPECT_EQ(p.scalar_type(), torch::kFloat32) << name;
    EXPECT_TRUE(p.is_cuda()) << name;
    ASSERT_TRUE(p.grad().defined()) << name;
    EXPECT_EQ(p.grad().scalar_type(), torch::kFloat32) << name;
  }
  // Merge on the device: same losses to bf16 tolerance; adapters off = reference losses.
  torch::NoGradGuard ng;
  simu::lora::merge_lora(*gen);
  EXPECT_TRUE(simu::testing::close(fm_loss_cuda(gen, m, "pos"), m.at("out.loss_pos_policy"), 3e-2, "merged bf16"));
  simu::lora::set_lora_enabled(*gen, false);
  EXPECT_TRUE(simu::testing::close(fm_loss_cuda(gen, m, "neg"), m.at("out.loss_neg_ref"), 3e-2, "ref bf16"));
}

TEST(LoraGpu, FusedSumUnderAutocastMatchesDelta) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  torch::manual_seed(21);
  simu::models::Linear lin(256, 768);
  lin->to(dev);
  for (auto& p : lin->parameters()) p.set_requires_grad(false);
  simu::lora::LoraWeight A(16, 256, dev), B(768, 16, dev);
  {
    torch::NoGradGuard ng;
    A->weight.normal_(0, 0.05);
    B->weight.normal_(0, 0.05);
  }
  auto adapter = std::make_shared<simu::lora::LoraAdapter>(A, B, 2.0, 0.0);
  lin->set_adapter(adapter);
  auto x = torch::randn({2, 100, 256}, torch::TensorOptions().device(dev)).requires_grad_();
  auto gy = torch::randn({2, 100, 768}, torch::TensorOptions().device(dev));
  // The wrapped layer (frozen base under autocast: LoraAdapter::forward_with_base, one node whose
  // up-projection and input gradient accumulate in place) vs base + delta, values and gradients.
  auto grads = [&](bool fused) {
    simu::models::Autocast ac(simu::models::Precision::kBf16);
    auto y = fused ? lin->forward(x) : torch::linear(x, lin->weight, lin->bias) + adapter->delta(x);
    EXPECT_EQ(y.scalar_type(), torch::kBFloat16);
    auto g = torch::autograd::grad({y}, {x, A->weight, B->weight}, {gy.to(torch::kBFloat16)});
    g.push_back(y.detach());
    return g;
  };
  auto got = grads(true), want = grads(false);
  const char* names[] = {"dx", "dA", "dB", "y"};
  for (int i = 0; i < 4; ++i)
    EXPECT_TRUE(simu::testing::close(got[i].to(torch::kFloat32), want[i].to(torch::kFloat32), 2e-2, names[i]));
  // Independent fp64 value: y = x W^T + b + 2 * (x A^T) B^T.
  auto x64 = x.detach().to(torch::kFloat64);
  auto y64 = torch::linear(x64, lin->weight.to(torch::kFloat64), lin->bias.to(torch::kFloat64)) +
             2.0 * torch::linear(torch::linear(x64, A->weight.to(torch::kFloat64)), B->weight.to(torch::kFloat64));
  EXPECT_TRUE(simu::testing::close(got[3].to(torch::kFloat64), y64, 1e-2, "y vs fp64"));
}
