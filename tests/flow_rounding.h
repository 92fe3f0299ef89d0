// Rounding bounds of the Stage-1 models in fp32 (the flow model, the condition embedder before it, the
// decoder after it), from their configs, in the model of tests/tolerance.h: how many roundings a value
// passes through in series in one forward, what guidance and sampling make of it, and the FM-DPO
// objective and first optimizer step built on it. The suites that compare these models' outputs
// (models, lora, training, resample) derive their bounds from here, so a fixture regenerated at other
// sizes gets its own bound. docs/testing.md has the table.
#pragma once

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>

#include <torch/torch.h>

#include "models/cond_embedder.h"
#include "models/flow_model.h"
#include "models/ss_decoder.h"
#include "tolerance.h"

namespace simu::testing {

// Sum of the reduction lengths on a token's longest path through one backbone forward: per block,
// LayerNorm (2C: mean, variance), qkv (C), q/k RMS norm (D), scores (D), softmax sum and weighted sum
// over all T tokens (2T), out projection (C); cross attention after its LayerNorm (2C) with q (C),
// [RMS norm D], scores (D), softmax and weighted sum over Lc condition tokens (2 Lc), out (C); the
// MLP after its LayerNorm (2C): fc1 (C), fc2 (H = mlp_ratio C). Once: the input projection (its
// in_channels), the time embedding (256 frequencies) and modulation (2C + C), the output LayerNorm
// and projection (3C).
inline double flow_forward_chain(const models::FlowModelConfig& c, int64_t cond_tokens) {
  const double C = static_cast<double>(c.model_channels), D = static_cast<double>(c.head_dim());
  const double H = c.mlp_ratio * C, Lc = static_cast<double>(cond_tokens);
  double T = 0, in = 0;
  for (const auto& l : c.latents) {
    T += static_cast<double>(l.tokens());
    in = std::max(in, static_cast<double>(l.in_channels));
  }
  const double self = 2 * C + C + D + D + 2 * T + C;
  const double cross = 2 * C + C + (c.qk_rms_norm_cross ? D : 0) + D + 2 * Lc + C;
  const double mlp = 2 * C + C + H;
  return static_cast<double>(c.num_blocks) * (self + cross + mlp) + in + 256 + 3 * C + 3 * C;
}

// Two fp32 evaluations of one backbone forward (other kernels, batch layout, cache or port).
inline double flow_forward_bound(const models::FlowModelConfig& c, int64_t cond_tokens) {
  return two_paths(flow_forward_chain(c, cond_tokens));
}

// Two fp32 evaluations of a parameter gradient of one forward: the forward, the backward through the
// same layers (the same reduction lengths, transposed: chain again), then the weight gradient's sum
// over `rows` token rows.
inline double flow_gradient_bound(const models::FlowModelConfig& c, int64_t cond_tokens, int64_t rows) {
  return two_paths(2 * flow_forward_chain(c, cond_tokens) + static_cast<double>(rows));
}

// Two fp32 evaluations of a guided velocity y = (1 + s) y_cond - s y_uncond: each branch's error,
// weighted by (1 + s) and s.
inline double flow_guided_bound(const models::FlowModelConfig& c, int64_t cond_tokens, double strength) {
  return (1 + 2 * std::abs(strength)) * flow_forward_bound(c, cond_tokens);
}

// Two fp32 runs of an Euler sampler with guidance strength s: the end point x0 + sum_i dt_i v_i
// carries the velocities' error weighted by the dt_i, which sum to 1 (first order).
inline double flow_sample_bound(const models::FlowModelConfig& c, int64_t cond_tokens, double strength) {
  return flow_guided_bound(c, cond_tokens, strength);
}

// Rounding chain of the sparse-structure decoder that follows the flow, from its config: every
// 3x3x3 convolution sums 27 in_channels terms, every channel norm 2 C (mean, variance): the input conv,
// the middle residual blocks (two norms and convs each), per level its residual blocks and the
// upsampling conv, the head.
inline double decoder_chain(const models::SSDecoderConfig& c) {
  auto res = [](double ch) { return 2 * (2 * ch + 27 * ch); };
  const auto& ch = c.channels;
  double n = 27.0 * static_cast<double>(c.latent_channels) + static_cast<double>(c.num_res_blocks_middle) * res(ch[0]);
  for (size_t level = 0; level < ch.size(); ++level) {
    n += static_cast<double>(c.num_res_blocks) * res(static_cast<double>(ch[level]));
    if (level + 1 < ch.size()) n += 27.0 * static_cast<double>(ch[level]);
  }
  return n + 2.0 * static_cast<double>(ch.back()) + 27.0 * static_cast<double>(ch.back());
}

// Rounding chain of the condition embedder from its config: the longest of its embedders' chains, then
// the projection net. A Dino token: the 3 p^2 patch projection, per block two LayerNorms (2 x 2C), qkv,
// out and fc1 (C each), fc2 (mlp C), scores (D) and softmax + weighted sum over its T tokens (2T), the
// final LayerNorm (2C). A point-patch window token: the 3-term point projection, then one such block
// over the window's p^2 + 1 tokens. The projection net: LayerNorm (2C), w1 (C), w2 (its hidden H).
inline double embedder_chain(const models::CondEmbedderConfig& c) {
  double longest = 0, widest = 0;
  for (const auto& e : c.embedders) {
    double C = 0, chain = 0;
    if (e.kind == models::CondEmbedderEntry::Kind::kDino) {
      const auto& v = e.dino.vit;
      C = static_cast<double>(v.embed_dim);
      const double p = static_cast<double>(v.patch_size), side = std::floor(static_cast<double>(e.dino.input_size) / p);
      const double T = 1 + static_cast<double>(v.num_register_tokens) + side * side;
      chain = 3 * p * p + static_cast<double>(v.depth) * (7 * C + v.mlp_ratio * C + C / static_cast<double>(v.num_heads) + 2 * T) + 2 * C;
    } else {
      const auto& pp = e.point;
      C = static_cast<double>(pp.embed_dim);
      const double T = static_cast<double>(pp.patch_size * pp.patch_size) + 1;
      chain = 3 + 7 * C + pp.mlp_ratio * C + C / static_cast<double>(pp.num_heads) + 2 * T + 2 * C;
    }
    longest = std::max(longest, chain);
    widest = std::max(widest, C);
  }
  double projection = 0;
  if (c.projection_net_hidden_dim_multiplier > 0) {
    const auto hidden = static_cast<int64_t>(c.projection_net_hidden_dim_multiplier * static_cast<double>(c.embed_dims()));
    projection = 3 * widest + static_cast<double>(models::FeedForwardImpl::hidden_size(hidden));
  }
  return longest + projection;
}

// Two fp32 evaluations of a flow-matching loss mean((pred - target)^2) over `elems` elements: the
// square doubles the forward's relative error (|pred - target| is of the order of |pred|), the mean
// adds a sum of elems terms.
inline double fm_loss_bound(double forward_bound, int64_t elems) {
  return 2 * forward_bound + two_paths(static_cast<double>(elems));
}

// Absolute bound of FM-DPO's per-pair term softplus(beta/2 ((pos - neg) - (ref_pos - ref_neg))): the
// four losses, each within loss_tol of its magnitude (at most max_loss), meet in a difference, and the
// softplus' slope (a sigmoid, <= 1) times beta/2 carries that absolute error; plus the softplus' own
// few roundings of max_per_pair.
inline double dpo_per_pair_abs_bound(double beta, double loss_tol, double max_loss, double max_per_pair) {
  return beta / 2 * 4 * loss_tol * max_loss + gamma(4) * max_per_pair;
}

// FM-DPO's parameter gradient sum_b c_b (grad L_pos,b - grad L_neg,b), relative to its largest value
// g_max: the members' gradients (each within member_tol of its largest value, pos_max / neg_max) can
// cancel in the difference, and the weights c_b = w_b sigmoid(.) beta / (2B) carry the per-pair term's
// error (relative: d log sigmoid <= 1 times beta/2 of the difference, the absolute per-pair bound).
inline double dpo_grad_bound(double member_tol, double per_pair_abs, double pos_max, double neg_max, double g_max) {
  return (member_tol + per_pair_abs) * (pos_max + neg_max) / g_max;
}

// Elementwise bound on the parameters after a first AdamW step from zero moments (the update is
// lr (g / (|g| + eps)) after the decay p (1 - lr wd)), for a gradient g known to within dg
// (absolute, elementwise): where |dg| < |g| the update moves by at most lr |dg| eps / (|g| - |dg| + eps)^2,
// elsewhere by at most 2 lr (its sign may flip); plus the update's own ~10 roundings (moments, bias
// corrections, sqrt, division: lr gamma(10)) and the parameter's 3 (decay, subtraction).
inline torch::Tensor adamw_first_step_bound(const torch::Tensor& g, const torch::Tensor& dg, const torch::Tensor& p,
                                            double lr, double eps) {
  const auto g64 = g.to(torch::kFloat64).abs(), d64 = dg.to(torch::kFloat64).abs().expand_as(g64);
  const auto near = (g64 - d64).clamp_min(0) + eps;
  const auto moved = torch::where(d64 < g64, d64 * eps / (near * near), torch::full_like(g64, 2.0)).clamp_max(2.0);
  return lr * (moved + gamma(10)) + gamma(3) * p.to(torch::kFloat64).abs();
}

// Every |got - want| within its elementwise bound; the message names the tensor and the worst excess.
inline ::testing::AssertionResult within_bound(const torch::Tensor& got, const torch::Tensor& want,
                                               const torch::Tensor& bound, const std::string& what) {
  if (got.sizes() != want.sizes())
    return ::testing::AssertionFailure() << what << ": shape " << got.sizes() << " vs expected " << want.sizes();
  const auto err = (got.to(torch::kFloat64) - want.to(torch::kFloat64)).abs();
  const double excess = (err - bound.to(torch::kFloat64)).max().item<double>();
  if (excess <= 0 && torch::isfinite(err).all().item<bool>()) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << what << ": an element is off by " << excess << " beyond its bound";
}

}  // namespace simu::testing
