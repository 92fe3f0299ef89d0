// The cross attention layer (src/models/flow_layers.cpp, CrossAttentionImpl) on CUDA under bf16
// autocast, where a fused attention kernel runs: pair-major shared-condition attention equals each token
// row attending alone within bf16 rounding (outputs and to_kv / to_q gradients), and its graph holds no
// copy (CloneBackward0) of the queries or the output: the shared query sequence and the way back are
// views of the kernel's [B, L, H, D] layout.
#include "graph_nodes.h"
#include "models/flow_model.h"
#include "models/precision.h"
#include "test_util.h"

TEST(CrossAttentionLayerGpu, SharedConditionPairMajorIsViewsAndMatchesEachRow) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  const int64_t C = 256, Cc = 96, H = 4, Bc = 2, G = 2, L = 192, Lc = 300;  // head dim 64
  torch::manual_seed(11);
  simu::models::CrossAttention ca(C, Cc, H, /*qk_rms_norm=*/true);
  {
    torch::NoGradGuard ng;
    for (auto& p : ca->parameters()) p.copy_(torch::randn_like(p) * 0.1);
  }
  ca->to(dev);
  auto x = torch::randn({Bc * G, L, C}, dev);
  auto ctx = torch::randn({Bc, Lc, Cc}, dev);
  auto weight = torch::randn({Bc * G, L, C}, dev);
  const std::vector<torch::Tensor> leaves = {ca->to_q->weight, ca->to_kv->weight};
  for (auto p : leaves) p.requires_grad_(true);
  simu::models::Autocast ac(simu::models::Precision::kBf16);
  // Shared: Bc condition rows for Bc*G token rows (row b*G + g over condition b).
  auto shared = ca->forward(x, ctx);
  EXPECT_EQ(simu::testing::count_graph_nodes(shared, "CloneBackward0"), 0) << "the shared-condition attention copies its queries or output";
  auto g_shared = torch::autograd::grad({(shared.to(torch::kFloat32) * weight).sum()}, leaves);
  // Alone: token row r over condition row r / G.
  std::vector<torch::Tensor> rows;
  for (int64_t r = 0; r < Bc * G; ++r) rows.push_back(ca->forward(x.narrow(0, r, 1), ctx.narrow(0, r / G, 1)));
  auto alone = torch::cat(rows);
  auto g_alone = torch::autograd::grad({(alone.to(torch::kFloat32) * weight).sum()}, leaves);
  EXPECT_TRUE(simu::testing::close(shared.detach(), alone.detach(), 2e-2, "output"));
  EXPECT_TRUE(simu::testing::close(g_shared[0], g_alone[0], 3e-2, "to_q grad"));
  EXPECT_TRUE(simu::testing::close(g_shared[1], g_alone[1], 3e-2, "to_kv grad"));
}

// Zero-condition rows (CFG's unconditional half) under fp16 autocast with compute copies, as sampling
// runs them: the output written in place (attended rows' projection into the output, zero rows filled
// from a precomputed zero_out) equals the concatenation of to_out(attended rows) and to_out(v(0)) bit
// for bit, with and without zero_out given.
TEST(CrossAttentionLayerGpu, ZeroConditionRowsWrittenInPlaceMatchConcatenation) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  const int64_t C = 256, Cc = 96, H = 4, B = 2, Bk = 1, L = 192, Lc = 300;
  torch::manual_seed(12);
  simu::models::CrossAttention ca(C, Cc, H, /*qk_rms_norm=*/false);
  {
    torch::NoGradGuard ng;
    for (auto& p : ca->parameters()) p.copy_(torch::randn_like(p) * 0.1);
  }
  ca->to(dev);
  simu::models::set_compute_copies(*ca, torch::kHalf, /*frozen_only=*/false);
  torch::NoGradGuard ng;
  auto x = torch::randn({B, L, C}, dev);
  auto ctx = torch::randn({Bk, Lc, Cc}, dev);
  simu::models::Autocast ac(simu::models::Precision::kFp16);
  auto [k, v] = ca->context_kv(ctx);
  auto zero_out = ca->zero_condition_output(ctx);
  ASSERT_EQ(zero_out.sizes(), (std::vector<int64_t>{1, 1, C}));
  auto got = ca->attend(x, k, v, zero_out);
  auto got_recomputed = ca->attend(x, k, v);
  // Reference: the attended row through the plain layer, then the zero row's output appended.
  auto head = ca->attend(x.narrow(0, 0, Bk), k, v);
  auto want = torch::cat({head, zero_out.expand({B - Bk, L, C})}, 0);
  EXPECT_EQ(got.scalar_type(), torch::kHalf);
  EXPECT_TRUE(torch::equal(got, want));
  EXPECT_TRUE(torch::equal(got_recomputed, want));
  // And the zero row is what attention over an all-zero condition gives.
  auto zero_ctx = ca->forward(x.narrow(0, Bk, B - Bk), torch::zeros({1, Lc, Cc}, dev));
  EXPECT_TRUE(simu::testing::close(got.narrow(0, Bk, B - Bk).to(torch::kFloat32), zero_ctx.to(torch::kFloat32), 1e-2, "zero row"));
}
