#include "models/point_patch_embed.h"

#include <fmt/ranges.h>

#include "common/error.h"

namespace simu::models {

namespace F = torch::nn::functional;

// ---------------------------------------------------------------------------------------------
// PointRemapper

PointRemapper::PointRemapper(const std::string& type) : name_(type) {
  if (type == "linear") type_ = Type::kLinear;
  else if (type == "sinh") type_ = Type::kSinh;
  else if (type == "exp") type_ = Type::kExp;
  else if (type == "sinh_exp") type_ = Type::kSinhExp;
  else if (type == "exp_disparity") type_ = Type::kExpDisparity;
  else fail("invalid point remap type '{}' (expected linear, sinh, exp, sinh_exp or exp_disparity)", type);
}

torch::Tensor PointRemapper::forward(const torch::Tensor& p) const {
  SIMU_CHECK(p.size(-1) == 3, "PointRemapper: last dimension must be 3 (xyz), got [{}]", fmt::join(p.sizes(), ", "));
  switch (type_) {
    case Type::kLinear:
      return p;
    case Type::kSinh:
      return torch::asinh(p);
    case Type::kExp: {
      // xy / (1 + z), log1p(z)
      auto xy = p.narrow(-1, 0, 2), z = p.narrow(-1, 2, 1);
      return torch::cat({xy / (1 + z), torch::log1p(z)}, -1);
    }
    case Type::kExpDisparity: {
      // xy / z, log(z)
      auto xy = p.narrow(-1, 0, 2), z = p.narrow(-1, 2, 1);
      return torch::cat({xy / z, torch::log(z)}, -1);
    }
    case Type::kSinhExp: {
      // asinh(xy), log(max(z, 1e-8))
      auto xy = p.narrow(-1, 0, 2), z = p.narrow(-1, 2, 1);
      return torch::cat({torch::asinh(xy), torch::log(z.clamp_min(1e-8))}, -1);
    }
  }
  return p;
}

torch::Tensor PointRemapper::inverse(const torch::Tensor& p) const {
  SIMU_CHECK(p.size(-1) == 3, "PointRemapper: last dimension must be 3 (xyz), got [{}]", fmt::join(p.sizes(), ", "));
  switch (type_) {
    case Type::kLinear:
      return p;
    case Type::kSinh:
      return torch::sinh(p);
    case Type::kExp: {
      auto xy = p.narrow(-1, 0, 2), z = torch::expm1(p.narrow(-1, 2, 1));
      return torch::cat({xy * (1 + z), z}, -1);
    }
    case Type::kExpDisparity: {
      auto xy = p.narrow(-1, 0, 2), z = torch::exp(p.narrow(-1, 2, 1));
      return torch::cat({xy * z, z}, -1);
    }
    case Type::kSinhExp:
      return torch::cat({torch::sinh(p.narrow(-1, 0, 2)), torch::exp(p.narrow(-1, 2, 1))}, -1);
  }
  return p;
}

// ---------------------------------------------------------------------------------------------
// PointPatchEmbed

PointPatchEmbedConfig PointPatchEmbedConfig::from(config::Reader& r) {
  PointPatchEmbedConfig c;
  r.field("input_size", c.input_size);
  r.field("patch_size", c.patch_size);
  r.field("embed_dim", c.embed_dim);
  r.field("remap_output", c.remap_output);
  r.field("dropout_prob", c.dropout_prob);
  r.field("force_dropout_always", c.force_dropout_always);
  r.field("exp_near_points", c.exp_near_points);
  SIMU_CHECK(c.exp_near_points == "invalid" || c.exp_near_points == "nan",
             "{}: exp_near_points '{}' (expected invalid or nan)", r.file(), c.exp_near_points);
  r.field("num_heads", c.num_heads);
  r.field("block_heads", c.num_heads);
  r.field("mlp_ratio", c.mlp_ratio);
  r.field("block_mlp_ratio", c.mlp_ratio);
  return c;
}

PointPatchEmbedImpl::PointPatchEmbedImpl(const PointPatchEmbedConfig& c) : config(c), point_remapper(c.remap_output) {
  SIMU_CHECK(c.input_size % c.patch_size == 0, "PointPatchEmbed: input_size {} is not a multiple of patch_size {}",
             c.input_size, c.patch_size);
  const int64_t D = c.embed_dim, n = c.input_size / c.patch_size, p = c.patch_size;
  point_proj = register_module("point_proj", Linear(3, D, true));
  invalid_xyz_token = register_parameter("invalid_xyz_token", torch::randn({D}) * 0.02);
  if (c.dropout_prob > 0) dropped_xyz_token = register_parameter("dropped_xyz_token", torch::randn({D}) * 0.02);
  pos_embed = register_parameter("pos_embed", torch::randn({1, D, n, n}) * 0.02);
  pos_embed_window = register_parameter("pos_embed_window", torch::randn({1, 1 + p * p, D}) * 0.02);
  cls_token = register_parameter("cls_token", torch::randn({1, 1, D}) * 0.02);
  blocks->push_back(VitBlock(D, c.num_heads, c.mlp_ratio, /*qkv_bias=*/true, /*proj_bias=*/true, /*ffn_bias=*/true,
                             /*layer_scale_init=*/0.0));
  register_module("blocks", blocks);
}

torch::Tensor PointPatchEmbedImpl::window_pos_embed(int64_t h, int64_t w, torch::ScalarType dtype) {
  // [1, D, n, n] -> [1, D, h, w] -> [1, h*w, D]
  auto pe = F::interpolate(pos_embed, F::InterpolateFuncOptions()
                                          .size(std::vector<int64_t>{h, w})
                                          .mode(torch::kBilinear)
                                          .align_corners(false));
  return pe.permute({0, 2, 3, 1}).reshape({1, h * w, config.embed_dim}).to(dtype);
}

torch::Tensor PointPatchEmbedImpl::embed_points(const torch::Tensor& xyz_in, const torch::Tensor& valid_in) {
  SIMU_CHECK(xyz_in.dim() == 4 && xyz_in.size(1) == 3, "PointPatchEmbed: input [{}] expected [B, 3, H, W]",
             fmt::join(xyz_in.sizes(), ", "));
  const int64_t D = config.embed_dim;
  torch::Tensor x, valid;
  {
    torch::NoGradGuard no_grad;
    // Nearest resize to input_size x input_size, channels last: [B, S, S, 3].
    auto xyz = F::interpolate(xyz_in, F::InterpolateFuncOptions()
                                          .size(std::vector<int64_t>{config.input_size, config.input_size})
                                          .mode(torch::kNearest))
                   .permute({0, 2, 3, 1});
    valid = valid_in.defined() ? valid_in.to(torch::kBool) : torch::isfinite(xyz).all(-1);  // [B, S, S]
    SIMU_CHECK(valid.sizes() == torch::IntArrayRef({xyz.size(0), xyz.size(1), xyz.size(2)}),
               "PointPatchEmbed: valid_mask [{}] expected [{}, {}, {}]", fmt::join(valid.sizes(), ", "), xyz.size(0),
               xyz.size(1), xyz.size(2));
    // exp remap: z <= -1 is outside log1p's domain (see exp_near_points).
    if (point_remapper.type() == PointRemapper::Type::kExp && config.exp_near_points == "invalid")
      valid = valid & (xyz.select(-1, 2) > -1);
    // Invalid points to 0 before remapping so nothing non-finite propagates.
    auto safe = torch::where(valid.unsqueeze(-1), xyz, torch::zeros_like(xyz));
    x = point_remapper.forward(safe);
  }
  // Point projection; invalid points take the invalid token: [B, S, S, D].
  x = point_proj(x);
  return torch::where(valid.unsqueeze(-1), x, invalid_xyz_token.to(x.dtype()).view({1, 1, 1, D}));
}

torch::Tensor PointPatchEmbedImpl::forward(const torch::Tensor& xyz_in, const torch::Tensor& valid_in) {
  const int64_t p = config.patch_size, D = config.embed_dim;
  torch::Tensor x = embed_points(xyz_in, valid_in);  // [B, S, S, D]
  const int64_t B = x.size(0), H = x.size(1), W = x.size(2);

  // Windows: [B, h, p, w, p, D] -> [B*h*w, p*p, D]
  const int64_t h = H / p, w = W / p;
  x = x.view({B, h, p, w, p, D}).permute({0, 1, 3, 2, 4, 5}).reshape({-1, p * p, D});
  // Window cls token + in-window position embedding, one transformer block.
  auto toks = torch::cat({cls_token.to(x.dtype()).expand({x.size(0), -1, -1}), x}, 1);
  toks = toks + pos_embed_window.to(x.dtype());
  for (const auto& blk : *blocks) toks = blk->as<VitBlockImpl>()->forward(toks);
  // Window cls tokens + window-grid position embedding: [B, h*w, D].
  auto pos = window_pos_embed(h, w, toks.scalar_type());
  auto out = toks.select(1, 0).reshape({B, h * w, D}) + pos;

  // Pointmap dropout (training, or forced at inference).
  if ((is_training() || config.force_dropout_always) && config.dropout_prob > 0) {
    torch::Tensor drop;
    if (config.force_dropout_always && !is_training())
      drop = torch::ones({B}, torch::TensorOptions().dtype(torch::kBool).device(out.device()));
    else
      drop = torch::rand({B}, torch::TensorOptions().device(out.device())) < config.dropout_prob;
    auto dropped = dropped_xyz_token.to(out.dtype()).view({1, 1, D}) + pos;  // [1, h*w, D]
    out = torch::where(drop.view({B, 1, 1}), dropped.expand_as(out), out);
  }
  return out;
}

}  // namespace simu::models
