// The fused LoRA layer (lora_linear.cpp: LoraAdapter::forward_with_base, one autograd node for a
// frozen base + adapter under autocast) against its reference path (Linear + add_to) and against
// independent fp64 math, on CPU autocast bf16; and when it must step aside.
#include <ATen/autocast_mode.h>

#include "lora/lora.h"
#include "models/linear.h"
#include "test_util.h"

namespace {

using simu::lora::LoraAdapter;
using simu::lora::LoraWeight;

constexpr int64_t kIn = 96, kOut = 160, kRank = 8;
constexpr double kScale = 2.0;

// bf16 roundings in series under CPU autocast (tests/tolerance.h), counted per result: y = x W + s B A x:
// x, W, the base product, A, A x, B, B A x, the sum (8) and the bias (9); dx = gy W + s (gy B) A: gy, W,
// the product, B, gy B, A, the product, the sum (8); dA = s (gy B)^T x and dB = s gy^T (x A^T): the
// inputs (2), the inner product's output, the outer's (5). Plus the fp32 accumulations (at most
// kIn + kRank + 3 x 40 rows terms).
constexpr double kBf16Y = 9, kBf16Dx = 8, kBf16DaDb = 5, kFp32Terms = kIn + kRank + 3 * 40;
double bf16_bound(double roundings) {
  return simu::testing::gamma(roundings, simu::testing::kBf16Unit) + simu::testing::gamma(kFp32Terms);
}

// A frozen Linear [kOut, kIn] with a random-weight adapter of rank kRank.
struct Layer {
  simu::models::Linear lin{kIn, kOut};
  LoraWeight A{kRank, kIn, torch::kCPU}, B{kOut, kRank, torch::kCPU};
  std::shared_ptr<LoraAdapter> adapter;
  Layer() {
    torch::manual_seed(7);
    for (auto& p : lin->parameters()) p.set_requires_grad(false);
    {
      torch::NoGradGuard ng;
      A->weight.normal_(0, 0.1);
      B->weight.normal_(0, 0.1);
    }
    adapter = std::make_shared<LoraAdapter>(A, B, kScale, 0.0);
    lin->set_adapter(adapter);
  }
};

// CPU autocast in bf16 for one scope.
struct CpuBf16 {
  CpuBf16() {
    at::autocast::set_autocast_enabled(at::kCPU, true);
    at::autocast::set_autocast_dtype(at::kCPU, at::kBFloat16);
  }
  ~CpuBf16() {
    at::autocast::set_autocast_enabled(at::kCPU, false);
    at::autocast::clear_cache();
  }
};

// y and the gradients dx, dA, dB of sum(y * gy), all as fp64.
std::vector<torch::Tensor> run(Layer& l, const torch::Tensor& x_in, const torch::Tensor& gy, bool fused) {
  l.adapter->fused_base = fused;
  auto x = x_in.detach().clone().requires_grad_();
  torch::Tensor y;
  {
    CpuBf16 ac;
    y = l.lin->forward(x);
  }
  auto g = torch::autograd::grad({y}, {x, l.A->weight, l.B->weight}, {gy.to(y.scalar_type())});
  std::vector<torch::Tensor> out{y.detach()};
  for (auto& t : g) out.push_back(t);
  for (auto& t : out) t = t.to(torch::kFloat64);
  return out;
}

}  // namespace

// Fused and reference paths compute the same layer: equal outputs, gradients within bf16 rounding,
// and both as close to the fp64 layer as bf16 allows.
TEST(LoraLinear, FusedNodeMatchesReferenceAndFp64) {
  Layer l;
  auto x = torch::randn({3, 40, kIn});
  auto gy = torch::randn({3, 40, kOut});
  auto got = run(l, x, gy, true), ref = run(l, x, gy, false);
  // Same products, same order: the forward is the same arithmetic.
  EXPECT_TRUE(torch::equal(got[0], ref[0]));
  const char* names[] = {"y", "dx", "dA", "dB"};
  const double roundings[] = {kBf16Y, kBf16Dx, kBf16DaDb, kBf16DaDb};
  // Two bf16 paths (the fused one rounds dx once fewer): each within its count of the exact value.
  for (int i = 1; i < 4; ++i) EXPECT_TRUE(simu::testing::close(got[i], ref[i], 2 * bf16_bound(roundings[i]), names[i]));
  // fp64 layer and its gradients (independent math).
  auto x64 = x.to(torch::kFloat64).requires_grad_();
  auto a64 = l.A->weight.detach().to(torch::kFloat64).requires_grad_();
  auto b64 = l.B->weight.detach().to(torch::kFloat64).requires_grad_();
  auto y64 = torch::linear(x64, l.lin->weight.to(torch::kFloat64), l.lin->bias.to(torch::kFloat64)) +
             kScale * torch::linear(torch::linear(x64, a64), b64);
  auto g64 = torch::autograd::grad({y64}, {x64, a64, b64}, {gy.to(torch::kFloat64)});
  std::vector<torch::Tensor> want{y64.detach(), g64[0], g64[1], g64[2]};
  for (int i = 0; i < 4; ++i) {
    const double e_fused = simu::testing::rel_err(got[i], want[i]), e_ref = simu::testing::rel_err(ref[i], want[i]);
    EXPECT_LT(e_fused, bf16_bound(roundings[i])) << names[i];
    // One rounding fewer in dx (the sum accumulates in the product): never much worse than the reference.
    // Statistical, not a bound: each is the largest of 4,800 to 15,360 errors of like size, which stay
    // within ~20% of each other; 1.5x plus a quarter of a bf16 step (1e-3) holds for any kernels.
    EXPECT_LE(e_fused, 1.5 * e_ref + 1e-3) << names[i] << ": fused " << e_fused << ", reference " << e_ref;
  }
}

// An input without gradient (the condition into to_kv): only the adapter's gradients, still right.
TEST(LoraLinear, InputWithoutGradientGivesAdapterGradientsOnly) {
  Layer l;
  auto x = torch::randn({2, 30, kIn});
  torch::Tensor y;
  {
    CpuBf16 ac;
    y = l.lin->forward(x);
  }
  ASSERT_TRUE(y.requires_grad());
  auto gy = torch::randn({2, 30, kOut});
  auto g = torch::autograd::grad({y}, {l.A->weight, l.B->weight}, {gy.to(y.scalar_type())});
  EXPECT_EQ(g[0].scalar_type(), torch::kFloat32);
  // dA = s (gy B)^T x, dB = s gy^T (x A^T), in fp64 over the flattened rows.
  auto x2 = x.reshape({-1, kIn}).to(torch::kFloat64), gy2 = gy.reshape({-1, kOut}).to(torch::kFloat64);
  auto a64 = l.A->weight.detach().to(torch::kFloat64), b64 = l.B->weight.detach().to(torch::kFloat64);
  EXPECT_TRUE(simu::testing::close(g[0], kScale * gy2.mm(b64).t().mm(x2), bf16_bound(kBf16DaDb), "dA"));
  EXPECT_TRUE(simu::testing::close(g[1], kScale * gy2.t().mm(x2.mm(a64.t())), bf16_bound(kBf16DaDb), "dB"));
}

// The node only takes the case it was made for: autocast on, a frozen base, no dropout at work.
TEST(LoraLinear, StepsAsideOutsideItsCase) {
  Layer l;
  auto x = torch::randn({2, 5, kIn});
  // No autocast: the caller's path.
  EXPECT_FALSE(l.adapter->forward_with_base(x, l.lin->weight, l.lin->bias).defined());
  CpuBf16 ac;
  EXPECT_TRUE(l.adapter->forward_with_base(x, l.lin->weight, l.lin->bias).defined());
  // A base weight that trains: its gradient needs the unfused path.
  auto w = l.lin->weight.detach().clone().requires_grad_();
  EXPECT_FALSE(l.adapter->forward_with_base(x, w, l.lin->bias).defined());
  // Dropout in training mode.
  l.adapter->dropout = 0.1;
  l.A->train(true);
  EXPECT_FALSE(l.adapter->forward_with_base(x, l.lin->weight, l.lin->bias).defined());
  l.A->train(false);
  EXPECT_TRUE(l.adapter->forward_with_base(x, l.lin->weight, l.lin->bias).defined());
  // Switched off: the reference path.
  l.adapter->fused_base = false;
  EXPECT_FALSE(l.adapter->forward_with_base(x, l.lin->weight, l.lin->bias).defined());
}
