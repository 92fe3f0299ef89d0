// The frozen MLP's epilogue path (src/models/mlp_epilogue.h) on the CPU: its reference is linear ->
// tanh-GELU -> linear (fp64 math written out), and nothing takes the cuBLASLt path off CUDA (the
// FeedForwardNet's CPU forward is unchanged). The CUDA comparisons are in mlp_epilogue_gpu.cpp.
#include <cmath>

#include "models/flow_model.h"
#include "models/mlp_epilogue.h"
#include "test_util.h"

namespace me = simu::models::mlp_epilogue;

// mlp_reference = (gelu_tanh(x W1^T + b1)) W2^T + b2, values and input gradient, in fp64.
TEST(MlpEpilogue, ReferenceIsLinearTanhGeluLinear) {
  torch::manual_seed(1);
  const auto f64 = torch::TensorOptions().dtype(torch::kFloat64);
  auto x = torch::randn({2, 5, 16}, f64).requires_grad_();
  auto w1 = torch::randn({32, 16}, f64) / 4, b1 = torch::randn({32}, f64), w2 = torch::randn({8, 32}, f64) / 6,
       b2 = torch::randn({8}, f64);
  auto y = me::mlp_reference(x, w1, b1, w2, b2);
  ASSERT_EQ(y.sizes(), (std::vector<int64_t>{2, 5, 8}));
  // Written out: u = x W1^T + b1, gelu(u) = u/2 (1 + tanh(sqrt(2/pi) (u + 0.044715 u^3))).
  auto x2 = x.detach().clone().requires_grad_();
  auto u = torch::matmul(x2, w1.t()) + b1;
  auto g = 0.5 * u * (1 + torch::tanh(std::sqrt(2.0 / M_PI) * (u + 0.044715 * u.pow(3))));
  auto want = torch::matmul(g, w2.t()) + b2;
  // Two float64 evaluations: 16-term product, GELU (~8 roundings), 32-term product; the gradient adds
  // the backward through the same (twice the chain) and the 8-term sum of the output gradient.
  const double chain = 16 + 8 + 32;
  EXPECT_TRUE(simu::testing::close(y, want, simu::testing::two_paths(chain, simu::testing::kFp64Unit), "output"));
  y.sum().backward();
  want.sum().backward();
  EXPECT_TRUE(simu::testing::close(x.grad(), x2.grad(), simu::testing::two_paths(2 * chain + 8, simu::testing::kFp64Unit),
                                   "input gradient"));
}

// Off CUDA the epilogue path declines (undefined) and the module computes fc2(gelu(fc1(x))) as before.
TEST(MlpEpilogue, NoEpilogueOnTheCpu) {
  torch::manual_seed(2);
  simu::models::FeedForwardNet ffn(16, 4.0);
  for (auto& p : ffn->parameters()) p.set_requires_grad(false);
  ffn->inference_kernels = false;
  auto x = torch::randn({2, 3, 16}).requires_grad_();
  EXPECT_FALSE(me::frozen_mlp(x, *ffn->fc1, *ffn->fc2).defined());
  EXPECT_FALSE(me::mlp(x, ffn->fc1->weight, ffn->fc1->bias, ffn->fc2->weight, ffn->fc2->bias).defined());
  const auto n0 = me::launch_count();
  auto y = ffn->forward(x);
  EXPECT_EQ(me::launch_count(), n0);
  EXPECT_TRUE(torch::equal(y, ffn->fc2->forward(torch::gelu(ffn->fc1->forward(x), "tanh"))));
}

// The heuristic ranks of the epilogue products: kept as set, per epilogue; out-of-range ranks are refused
// with the rank named; nothing is reported before a product has run on this (CPU-only) process.
TEST(MlpEpilogue, AlgoRanksAreCheckedAndKept) {
  const auto before = me::algo_ranks();
  EXPECT_EQ(before, std::make_pair(0, 0));  // the default: the heuristic's first, both epilogues
  me::set_algo_ranks(1, 3);
  EXPECT_EQ(me::algo_ranks(), std::make_pair(1, 3));
  const auto err = simu::testing::error_of([] { me::set_algo_ranks(16, 0); });
  EXPECT_NE(err.find("16"), std::string::npos) << err;
  EXPECT_NE(err.find("[0, 15]"), std::string::npos) << err;
  EXPECT_EQ(me::algo_ranks(), std::make_pair(1, 3));  // unchanged by the refused call
  EXPECT_THROW(me::set_algo_ranks(0, -1), std::exception);
  me::set_algo_ranks(before.first, before.second);
  EXPECT_EQ(me::last_algo().rank, -1);  // no product ran on the CPU
}
