// The flow model's cross attention layer (src/models/flow_layers.cpp, CrossAttentionImpl): the
// condition's key/value split against the projection's two halves computed separately (CPU, float32).
#include <ATen/CPUGeneratorImpl.h>

#include "common/error.h"
#include "models/flow_model.h"
#include "test_util.h"

namespace {

using simu::models::CrossAttention;

constexpr int64_t C = 32, Cc = 24, H = 4, D = C / H;

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
  EXPECT_TRUE(simu::testing::close(k.detach(), k_ref.detach(), 1e-5, "k"));
  EXPECT_TRUE(simu::testing::close(v.detach(), v_ref.detach(), 1e-6, "v"));
  // Gradients of a loss over both halves.
  auto a = torch::randn({B, Lc, H, D}), b = torch::randn({B, Lc, H, D});
  auto g = grads_of((k * a).sum() + (v * b).sum(), {W})[0];
  auto g_ref = grads_of((k_ref * a).sum() + (v_ref * b).sum(), {w_ref})[0];
  EXPECT_TRUE(simu::testing::close(g, g_ref, 1e-5, "to_kv.weight grad"));
  // Only the value half used: the key half's gradient is zero (unbind fills the missing one).
  auto g_v = grads_of((ca->context_kv(ctx).second * b).sum(), {W})[0];
  EXPECT_EQ(g_v.narrow(0, 0, C).abs().max().item<double>(), 0.0);
  EXPECT_TRUE(simu::testing::close(g_v.narrow(0, C, C), g_ref.narrow(0, C, C), 1e-5, "value half"));
}
