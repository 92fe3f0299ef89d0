// The frozen MLP with its GELU in cuBLASLt epilogues (src/models/mlp_epilogue.h) against the plain-ATen
// reference (addmm -> gelu(tanh) -> addmm) and fp64 math written out here: fc1's GELU_AUX_BIAS outputs (h
// and the aux = the pre-activation), the DGELU product, the forward output and the input gradient, in bf16
// and fp16 with odd row counts; the FeedForwardNet takes it in training (same bits with and without a
// graph, and with or without compute copies) and takes its ATen path when a weight requires a gradient or
// the shapes do not fit. Tolerances: one unit in the last place of the storage type (1/128 bf16, 1/1024
// fp16) per rounding, relative to the largest value (tests/models/fused_ops_gpu.cpp explains the choice);
// gradients through the DGELU epilogue at bf16's for both types (kGradTol: cuBLASLt does not document how
// it evaluates tanh in the GELU derivative, which near |u| ~ 3 amplifies an approximate tanh's error).
#include <cmath>

#include "models/flow_model.h"
#include "models/fused_ops.h"
#include "models/linear.h"
#include "models/mlp_epilogue.h"
#include "models/precision.h"
#include "test_util.h"

namespace {

namespace me = simu::models::mlp_epilogue;
using simu::testing::rel_err;

const std::vector<torch::ScalarType> kLow = {torch::kBFloat16, torch::kHalf};
double ulp(torch::ScalarType t) { return t == torch::kHalf ? 1.0 / 1024 : 1.0 / 128; }
const char* name(torch::ScalarType t) { return t == torch::kHalf ? "fp16" : "bf16"; }
const double kGradTol = 2.0 / 128;
simu::models::Precision precision(torch::ScalarType t) {
  return t == torch::kHalf ? simu::models::Precision::kFp16 : simu::models::Precision::kBf16;
}

// tanh-GELU and its derivative, written out (fp64 inputs).
const double kS = std::sqrt(2.0 / M_PI);
torch::Tensor gelu64(const torch::Tensor& u) { return 0.5 * u * (1 + torch::tanh(kS * (u + 0.044715 * u.pow(3)))); }
torch::Tensor dgelu64(const torch::Tensor& u) {
  auto t = torch::tanh(kS * (u + 0.044715 * u.pow(3)));
  return 0.5 * (1 + t) + 0.5 * u * (1 - t * t) * kS * (1 + 3 * 0.044715 * u * u);
}
torch::Tensor f64(const torch::Tensor& t) { return t.detach().to(torch::kFloat64); }

// The MLP's 16-bit operands on CUDA: x [rows..., K], w1 [N, K], b1 [N], w2 [C, N], b2 [C]; pre-activations of
// order 1 (the GELU's curved part).
struct Mlp {
  torch::Tensor x, w1, b1, w2, b2;
};
Mlp make(torch::ScalarType dt, std::vector<int64_t> xshape, int64_t K, int64_t N, int64_t C) {
  const auto o = torch::TensorOptions().device(torch::kCUDA);
  Mlp m;
  m.x = torch::randn(xshape, o).to(dt);
  m.w1 = (torch::randn({N, K}, o) / std::sqrt(static_cast<double>(K))).to(dt);
  m.b1 = (0.3 * torch::randn({N}, o)).to(dt);
  m.w2 = (torch::randn({C, N}, o) / std::sqrt(static_cast<double>(N))).to(dt);
  m.b2 = (0.3 * torch::randn({C}, o)).to(dt);
  return m;
}

// An adapter that adds nothing (what a fresh LoRA adds), to install on fc2.
struct ZeroAdapter : simu::models::LinearAdapter {
  torch::Tensor delta(const torch::Tensor& x) override {
    auto shape = x.sizes().vec();
    shape.back() = 256;
    return torch::zeros(shape, x.options());
  }
};

}  // namespace

// fc1 through GELU_AUX_BIAS: the aux is the pre-activation x W1^T + b1 rounded once, h its tanh-GELU.
TEST(MlpEpilogueGpu, AuxIsTheFc1PreActivation) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(me::compiled()) << "built without cuBLASLt: no epilogue to test";
  torch::manual_seed(1);
  for (const auto dt : kLow)
  for (const int64_t rows : {1, 7, 903}) {
    auto m = make(dt, {rows, 256}, 256, 1024, 256);
    const auto n0 = me::launch_count();
    auto [h, pre] = me::linear_gelu_aux(m.x, m.w1, m.b1);
    EXPECT_EQ(me::launch_count(), n0 + 1) << "no cuBLASLt algorithm: the ATen fallback ran";
    ASSERT_EQ(h.scalar_type(), dt);
    ASSERT_EQ(pre.scalar_type(), dt);
    auto pre64 = torch::addmm(f64(m.b1), f64(m.x), f64(m.w1).t());  // [rows, N]
    EXPECT_LE(rel_err(pre, pre64), ulp(dt)) << name(dt) << " rows " << rows;
    // ATen's product in the same dtype: the same fp32 value rounded once on both sides.
    EXPECT_LE(rel_err(pre, torch::addmm(m.b1, m.x, m.w1.t())), ulp(dt)) << name(dt) << " rows " << rows;
    // h: the GELU of the unrounded sum, rounded once (cuBLASLt's tanh may be an approximation: two ulp).
    EXPECT_LE(rel_err(h, gelu64(pre64)), 2 * ulp(dt)) << name(dt) << " rows " << rows;
  }
}

// The backward product through DGELU: (dy W2) * gelu_tanh'(aux), against fp64 and ATen's gelu_backward.
TEST(MlpEpilogueGpu, DgeluProductMatchesFp64) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(me::compiled());
  torch::manual_seed(2);
  for (const auto dt : kLow)
  for (const int64_t rows : {1, 7, 903}) {
    auto m = make(dt, {rows, 256}, 256, 1024, 256);
    auto pre = (1.5 * torch::randn({rows, 1024}, torch::TensorOptions().device(torch::kCUDA))).to(dt);
    auto dy = torch::randn({rows, 256}, torch::TensorOptions().device(torch::kCUDA)).to(dt);
    const auto n0 = me::launch_count();
    auto dpre = me::linear_dgelu(dy, m.w2, pre);
    EXPECT_EQ(me::launch_count(), n0 + 1) << "no cuBLASLt algorithm: the ATen fallback ran";
    ASSERT_EQ(dpre.scalar_type(), dt);
    auto want = torch::mm(f64(dy), f64(m.w2)) * dgelu64(f64(pre));  // [rows, N]
    EXPECT_LE(rel_err(dpre, want), kGradTol) << name(dt) << " rows " << rows;
    auto aten = at::gelu_backward(torch::mm(dy, m.w2), pre, "tanh");
    EXPECT_LE(rel_err(dpre, aten), kGradTol) << name(dt) << " rows " << rows;
    // ATen's own error against fp64 (two roundings): the scale the epilogue's is judged against.
    EXPECT_LE(rel_err(aten, want), 2 * ulp(dt)) << name(dt) << " rows " << rows << " (reference)";
  }
}

// Every rank the heuristic offers (set_algo_ranks) computes the same products: each rank's fc1 outputs and
// DGELU product against fp64 at the tolerances above, and the rank actually run is the one asked for while
// the heuristic has it (else its first).
TEST(MlpEpilogueGpu, EveryHeuristicRankMatchesFp64) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(me::compiled());
  torch::manual_seed(3);
  const auto before = me::algo_ranks();
  auto m = make(torch::kBFloat16, {903, 256}, 256, 1024, 256);
  auto pre64 = torch::addmm(f64(m.b1), f64(m.x), f64(m.w1).t());
  auto dy = torch::randn({903, 256}, torch::TensorOptions().device(torch::kCUDA)).to(torch::kBFloat16);
  for (int r = 0; r < 8; ++r) {
    me::set_algo_ranks(r, r);
    auto [h, pre] = me::linear_gelu_aux(m.x, m.w1, m.b1);
    const auto fwd = me::last_algo();
    ASSERT_GT(fwd.found, 0) << "rank " << r;
    EXPECT_EQ(fwd.rank, r < fwd.found ? r : 0) << fwd.config;
    EXPECT_LE(rel_err(pre, pre64), ulp(torch::kBFloat16)) << "rank " << r << ": " << fwd.config;
    EXPECT_LE(rel_err(h, gelu64(pre64)), 2 * ulp(torch::kBFloat16)) << "rank " << r << ": " << fwd.config;
    auto dpre = me::linear_dgelu(dy, m.w2, pre);
    const auto bwd = me::last_algo();
    EXPECT_EQ(bwd.rank, r < bwd.found ? r : 0) << bwd.config;
    EXPECT_LE(rel_err(dpre, torch::mm(f64(dy), f64(m.w2)) * dgelu64(f64(pre))), kGradTol) << "rank " << r << ": " << bwd.config;
  }
  me::set_algo_ranks(before.first, before.second);
}

// The whole MLP (autograd function): output and input gradient vs the ATen reference and fp64.
TEST(MlpEpilogueGpu, ForwardAndInputGradientMatchReference) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(me::compiled());
  torch::manual_seed(3);
  for (const auto dt : kLow)
  for (const auto& shape : std::vector<std::vector<int64_t>>{{3, 301, 256}, {1, 5, 256}}) {
    auto m = make(dt, shape, 256, 1024, 256);
    auto gy = torch::randn(shape, torch::TensorOptions().device(torch::kCUDA)).to(dt);  // C = K here
    // Fast path: one epilogue product forward, one backward.
    auto x = m.x.clone().requires_grad_();
    const auto n0 = me::launch_count();
    auto y = me::mlp(x, m.w1, m.b1, m.w2, m.b2);
    ASSERT_TRUE(y.defined()) << "operands not supported";
    EXPECT_EQ(me::launch_count(), n0 + 1);
    y.backward(gy);
    EXPECT_EQ(me::launch_count(), n0 + 2);
    ASSERT_EQ(y.scalar_type(), dt);
    ASSERT_EQ(x.grad().scalar_type(), dt);
    // ATen reference in the same dtype.
    auto xr = m.x.clone().requires_grad_();
    auto yr = me::mlp_reference(xr, m.w1, m.b1, m.w2, m.b2);
    yr.backward(gy);
    // fp64 on the same rounded operands: the error scale.
    auto x64 = f64(m.x).requires_grad_();
    auto h64 = gelu64(torch::matmul(x64, f64(m.w1).t()) + f64(m.b1));
    auto y64 = torch::matmul(h64, f64(m.w2).t()) + f64(m.b2);
    y64.backward(f64(gy));
    const std::string what = std::string(name(dt)) + " rows " + std::to_string(m.x.numel() / 256);
    EXPECT_LE(rel_err(y, y64), 2 * ulp(dt)) << what;
    EXPECT_LE(rel_err(yr, y64), 2 * ulp(dt)) << what << " (reference)";
    EXPECT_LE(rel_err(y, yr), 2 * ulp(dt)) << what;
    EXPECT_LE(rel_err(x.grad(), x64.grad()), kGradTol) << what;
    EXPECT_LE(rel_err(xr.grad(), x64.grad()), 2 * ulp(dt)) << what << " (reference)";
    EXPECT_LE(rel_err(x.grad(), xr.grad()), kGradTol) << what;
    // Without a graph: the same products, the same bits.
    torch::NoGradGuard ng;
    EXPECT_TRUE(torch::equal(me::mlp(m.x, m.w1, m.b1, m.w2, m.b2), y.detach())) << what;
  }
}

// The module in training (training kernels, frozen weights, 16-bit autocast): the epilogues run, match the
// ATen path, give the same bits without a graph and with compute copies; sampling keeps GELU_BIAS.
TEST(MlpEpilogueGpu, FeedForwardNetTakesTheEpiloguesInTraining) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(me::compiled() && simu::models::fused::compiled());
  torch::manual_seed(4);
  const auto o = torch::TensorOptions().device(torch::kCUDA);
  simu::models::FeedForwardNet ffn(256, 4.0);
  ffn->to(torch::kCUDA);
  for (auto& p : ffn->parameters()) p.set_requires_grad(false);
  ffn->inference_kernels = false;  // set_training_kernels(true)
  for (const auto dt : kLow) {
    simu::models::Autocast ac(precision(dt));
    auto x0 = torch::randn({2, 301, 256}, o).to(dt);  // a fused LayerNorm's 16-bit output
    auto gy = torch::randn({2, 301, 256}, o).to(dt);
    auto run = [&](bool fused, int64_t expect_launches) {
      ffn->fused_kernels = fused;
      auto x = x0.clone().requires_grad_();
      const auto n0 = me::launch_count();
      auto y = ffn->forward(x);
      y.backward(gy);
      EXPECT_EQ(me::launch_count() - n0, expect_launches) << name(dt) << " fused " << fused;
      return std::make_pair(y.detach(), x.grad());
    };
    const auto [y, dx] = run(true, 2);
    const auto [yr, dxr] = run(false, 0);
    EXPECT_LE(rel_err(y, yr), 2 * ulp(dt)) << name(dt);
    EXPECT_LE(rel_err(dx, dxr), kGradTol) << name(dt);
    ffn->fused_kernels = true;
    torch::NoGradGuard ng;
    // FM-DPO's reference pass (no graph, training kernels): the policy forward's bits.
    EXPECT_TRUE(torch::equal(ffn->forward(x0), y)) << name(dt);
    // Compute copies (the trainer's frozen base) hold the same 16-bit weights: the same bits.
    simu::models::set_compute_copies(*ffn, dt);
    const auto n1 = me::launch_count();
    EXPECT_TRUE(torch::equal(ffn->forward(x0), y)) << name(dt) << " with compute copies";
    EXPECT_EQ(me::launch_count(), n1 + 1);
    ASSERT_NE(ffn->fc2->compute_copy(), nullptr);
    simu::models::set_compute_copies(*ffn, c10::nullopt);
    // Sampling (no graph, inference kernels): the inference-only GELU_BIAS epilogue, not this one.
    ffn->inference_kernels = true;
    const auto n2 = me::launch_count(), f2 = simu::models::fused::launch_count();
    (void)ffn->forward(x0);
    EXPECT_EQ(me::launch_count(), n2);
    EXPECT_EQ(simu::models::fused::launch_count(), f2 + 1);
    ffn->inference_kernels = false;
  }
}

// Where the epilogue path does not apply the module takes its ATen path, with the same bits as
// fused_kernels off: a weight or bias that requires a gradient, an adapter (even switched off), widths that
// are not multiples of 8.
TEST(MlpEpilogueGpu, FallsBackToAtenWhenUnsupported) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(me::compiled());
  torch::manual_seed(5);
  const auto o = torch::TensorOptions().device(torch::kCUDA);
  auto check = [&](simu::models::FeedForwardNet& ffn, int64_t C, const std::string& what) {
    simu::models::Autocast ac(simu::models::Precision::kBf16);
    ffn->inference_kernels = false;
    auto x0 = torch::randn({2, 33, C}, o).to(torch::kBFloat16);
    std::vector<torch::Tensor> res[2];
    for (const bool fused : {true, false}) {
      ffn->fused_kernels = fused;
      for (auto& p : ffn->parameters()) p.mutable_grad() = torch::Tensor();
      auto x = x0.clone().requires_grad_();
      const auto n0 = me::launch_count();
      auto y = ffn->forward(x);
      y.to(torch::kFloat32).square().sum().backward();
      EXPECT_EQ(me::launch_count(), n0) << what << ": the epilogue ran";
      res[fused] = {y.detach(), x.grad()};
      for (auto& p : ffn->parameters())
        if (p.requires_grad()) res[fused].push_back(p.grad());
    }
    ASSERT_EQ(res[0].size(), res[1].size()) << what;
    for (size_t i = 0; i < res[0].size(); ++i) EXPECT_TRUE(torch::equal(res[0][i], res[1][i])) << what << " output " << i;
  };
  {
    simu::models::FeedForwardNet ffn(256, 4.0);
    ffn->to(torch::kCUDA);
    for (auto& p : ffn->parameters()) p.set_requires_grad(false);
    ffn->fc1->weight.set_requires_grad(true);
    check(ffn, 256, "fc1.weight requires grad");
    ASSERT_TRUE(ffn->fc1->weight.grad().defined());
    ffn->fc1->weight.set_requires_grad(false);
    ffn->fc2->bias.set_requires_grad(true);
    check(ffn, 256, "fc2.bias requires grad");
    ffn->fc2->bias.set_requires_grad(false);
    // An adapter installed but switched off (FM-DPO's reference pass) keeps the path its policy pass takes.
    ffn->fc2->set_adapter(std::make_shared<ZeroAdapter>());
    ffn->fc2->set_adapter_enabled(false);
    check(ffn, 256, "fc2 adapter off");
  }
  {
    simu::models::FeedForwardNet ffn(260, 4.0);  // K = C = 260: rows of 520 bytes, not a multiple of 16
    ffn->to(torch::kCUDA);
    for (auto& p : ffn->parameters()) p.set_requires_grad(false);
    check(ffn, 260, "260 channels");
  }
}
