// The flow model's cross attention layer (src/models/flow_layers.cpp, CrossAttentionImpl): the shared
// condition with pair-major token rows against attending each row on its own, and the condition's
// key/value split against the projection's two halves computed separately (CPU, float32).
#include <ATen/CPUGeneratorImpl.h>

#include "common/error.h"
#include "graph_nodes.h"
#include "models/flow_model.h"
#include "test_util.h"

namespace {

using simu::models::CrossAttention;

constexpr int64_t C = 32, Cc = 24, H = 4, D = C / H;

// Rounding chain of one cross attention over Lc condition tokens (tolerance.h): to_q (C), the q RMS
// norm (D), scores (D), softmax sum and weighted sum (2 Lc), to_out (C).
constexpr double cross_chain(int64_t Lc) { return C + D + D + 2.0 * Lc + C; }

// A cross attention layer with random weights, the RMS norm gains included (not the ones of the init).
CrossAttention random_layer(uint64_t seed) {
  torch::manual_seed(seed);
  CrossAttention ca(C, Cc, H, /*qk_rms_norm=*/true);
  torch::NoGradGuard ng;
  for (auto& p : ca->parameters()) p.copy_(torch::randn_like(p) * 0.3);
  return ca;
}

// Gradients of loss w.r.t. the given leaves (the graph is freed).
std::vector<torch::Tensor> grads_of(const torch::Tensor& loss, const std::vector<torch::Tensor>& leaves) {
  return torch::autograd::grad({loss}, leaves);
}

}  // namespace

// x rows b*G + g share condition row b (pair-major): no copy of the queries or the output, and the same
// outputs and gradients (x, condition, to_q / to_kv / to_out weights) as attending each token row alone
// over its own condition row.
TEST(CrossAttentionLayer, SharedConditionPairMajorEqualsEachRowAlone) {
  auto ca = random_layer(5);
  const int64_t Bc = 3, G = 2, L = 5, Lc = 7;
  auto x = torch::randn({Bc * G, L, C}).requires_grad_(true);
  auto ctx = torch::randn({Bc, Lc, Cc}).requires_grad_(true);
  auto weight = torch::randn({Bc * G, L, C});  // a loss that weighs every output element differently
  const std::vector<torch::Tensor> leaves = {x, ctx, ca->to_q->weight, ca->to_kv->weight, ca->to_out->weight};
  for (auto& p : leaves) p.requires_grad_(true);
  // Shared: one call, Bc condition rows for Bc*G token rows.
  auto shared = ca->forward(x, ctx);  // [Bc*G, L, C]
  // The shared query sequence and the way back are views (CPU's fused attention keeps [B, L, H, D]).
  EXPECT_EQ(simu::testing::count_graph_nodes(shared, "CloneBackward0"), 0);
  auto g_shared = grads_of((shared * weight).sum(), leaves);
  // Alone: token row r over condition row r / G, one call per row.
  std::vector<torch::Tensor> rows;
  for (int64_t r = 0; r < Bc * G; ++r) rows.push_back(ca->forward(x.narrow(0, r, 1), ctx.narrow(0, r / G, 1)));
  auto alone = torch::cat(rows);
  auto g_alone = grads_of((alone * weight).sum(), leaves);
  // Two fp32 evaluations of the layer; its gradients: the forward, the backward through the same
  // reductions, and a weight's sum over all Bc G L token rows and the Lc condition tokens.
  EXPECT_TRUE(simu::testing::close(shared.detach(), alone.detach(), simu::testing::two_paths(cross_chain(Lc)), "output"));
  const double grad_tol = simu::testing::two_paths(2 * cross_chain(Lc) + Bc * G * L + Lc);
  const char* names[] = {"x", "condition", "to_q", "to_kv", "to_out"};
  for (size_t i = 0; i < leaves.size(); ++i) {
    EXPECT_TRUE(simu::testing::close(g_shared[i], g_alone[i], grad_tol, names[i]));
    EXPECT_GT(g_shared[i].abs().max().item<double>(), 0) << names[i];
  }
  // The member-major order (row g*Bc + b over condition b) is a different function: the layout matters.
  std::vector<torch::Tensor> member_major;
  for (int64_t r = 0; r < Bc * G; ++r) member_major.push_back(ca->forward(x.narrow(0, r, 1), ctx.narrow(0, r % Bc, 1)));
  EXPECT_GT(simu::testing::rel_err(shared, torch::cat(member_major)), simu::testing::two_paths(cross_chain(Lc)));
  // Token rows that are not a multiple of the condition rows are refused.
  EXPECT_THROW(ca->forward(x.narrow(0, 0, 5), ctx.narrow(0, 0, 2)), simu::Error);
}

// context_kv: k = RMS norm of the first C outputs of to_kv, v = the last C, as [B, Lc, H, D]; v is a
// view of the projection (no copy for the attention kernel), split by unbind (its backward stacks both
// halves' gradients in one tensor); to_kv's gradient equals the one through the two halves computed as
// separate products.
TEST(CrossAttentionLayer, ConditionKeyValueSplitMatchesSeparateHalves) {
  auto ca = random_layer(8);
  const int64_t B = 2, Lc = 6;
  auto ctx = torch::randn({B, Lc, Cc});
  auto& W = ca->to_kv->weight;  // [2C, Cc]
  auto& bias = ca->to_kv->bias;  // [2C]
  W.requires_grad_(true);
  auto [k, v] = ca->context_kv(ctx);
  ASSERT_EQ(k.sizes(), (std::vector<int64_t>{B, Lc, H, D}));
  ASSERT_EQ(v.sizes(), (std::vector<int64_t>{B, Lc, H, D}));
  EXPECT_EQ(v.stride(1), 2 * C) << "v is not a view of the [B, Lc, 2C] projection";
  ASSERT_TRUE(v.grad_fn());
  EXPECT_EQ(v.grad_fn()->name(), "UnbindBackward0");
  // Reference: each half its own product; the RMS norm written out (x / |x| * gamma * sqrt(D)).
  auto w_ref = W.detach().clone().requires_grad_(true);
  auto k_lin = torch::linear(ctx, w_ref.narrow(0, 0, C), bias.detach().narrow(0, 0, C)).view({B, Lc, H, D});
  auto v_ref = torch::linear(ctx, w_ref.narrow(0, C, C), bias.detach().narrow(0, C, C)).view({B, Lc, H, D});
  auto k_ref = k_lin / k_lin.norm(2, {-1}, true) * ca->k_rms_norm->gamma.detach() * std::sqrt(double(D));
  // Two fp32 evaluations: k = the Cc-term product, its D-term norm, sqrt, division, two products;
  // v = the Cc-term product alone (the fused and the split products may block K differently).
  const double k_chain = Cc + D + 4;
  EXPECT_TRUE(simu::testing::close(k.detach(), k_ref.detach(), simu::testing::two_paths(k_chain), "k"));
  EXPECT_TRUE(simu::testing::close(v.detach(), v_ref.detach(), simu::testing::two_paths(Cc), "v"));
  // Gradients of a loss over both halves.
  auto a = torch::randn({B, Lc, H, D}), b = torch::randn({B, Lc, H, D});
  auto g = grads_of((k * a).sum() + (v * b).sum(), {W})[0];
  auto g_ref = grads_of((k_ref * a).sum() + (v_ref * b).sum(), {w_ref})[0];
  // Forward and backward through the same reductions, then the sum over the B Lc condition rows.
  const double grad_tol = simu::testing::two_paths(2 * k_chain + B * Lc);
  EXPECT_TRUE(simu::testing::close(g, g_ref, grad_tol, "to_kv.weight grad"));
  // Only the value half used: the key half's gradient is zero (unbind fills the missing one).
  auto g_v = grads_of((ca->context_kv(ctx).second * b).sum(), {W})[0];
  EXPECT_EQ(g_v.narrow(0, 0, C).abs().max().item<double>(), 0.0);
  EXPECT_TRUE(simu::testing::close(g_v.narrow(0, C, C), g_ref.narrow(0, C, C), grad_tol, "value half"));
}
