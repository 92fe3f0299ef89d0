#include "models/dino.h"

#include <fmt/ranges.h>

#include <cmath>

#include "common/error.h"

namespace simu::models {

namespace F = torch::nn::functional;

// ---------------------------------------------------------------------------------------------
// Config

DinoVitConfig DinoVitConfig::from(config::Reader& r) {
  DinoVitConfig c;
  r.field("img_size", c.img_size);
  r.field("patch_size", c.patch_size);
  r.field("in_chans", c.in_chans);
  r.field("embed_dim", c.embed_dim);
  r.field("depth", c.depth);
  r.field("num_heads", c.num_heads);
  r.field("mlp_ratio", c.mlp_ratio);
  r.field("qkv_bias", c.qkv_bias);
  r.field("proj_bias", c.proj_bias);
  r.field("ffn_bias", c.ffn_bias);
  r.field("init_values", c.init_values);
  r.field("ffn_layer", c.ffn_layer);
  r.field("block_chunks", c.block_chunks);
  r.field("num_register_tokens", c.num_register_tokens);
  r.field("interpolate_antialias", c.interpolate_antialias);
  r.field("interpolate_offset", c.interpolate_offset);
  r.field("has_mask_token", c.has_mask_token);
  r.field("has_norm", c.has_norm);
  return c;
}

DinoVitConfig DinoVitConfig::hub_model(const std::string& name) {
  DinoVitConfig c;  // hub defaults: img_size 518, patch 14, init_values 1.0, mlp, block_chunks 0
  std::string base = name;
  const std::string reg_suffix = "_reg";
  const bool reg = base.size() > reg_suffix.size() &&
                   base.compare(base.size() - reg_suffix.size(), reg_suffix.size(), reg_suffix) == 0;
  if (reg) base = base.substr(0, base.size() - reg_suffix.size());
  if (base == "dinov2_vits14") {
    c.embed_dim = 384, c.depth = 12, c.num_heads = 6;
  } else if (base == "dinov2_vitb14") {
    c.embed_dim = 768, c.depth = 12, c.num_heads = 12;
  } else if (base == "dinov2_vitl14") {
    c.embed_dim = 1024, c.depth = 24, c.num_heads = 16;
  } else if (base == "dinov2_vitg14") {
    fail("dino_model '{}': ViT-g/14 uses the SwiGLU FFN, which is not ported (supported: dinov2_vit{{s,b,l}}14[_reg])",
         name);
  } else {
    fail("unknown dino_model '{}' (expected dinov2_vits14, dinov2_vitb14, dinov2_vitl14, optionally with _reg)", name);
  }
  if (reg) {
    c.num_register_tokens = 4;
    c.interpolate_antialias = true;
    c.interpolate_offset = 0.0;
  } else {
    c.num_register_tokens = 0;
    c.interpolate_antialias = false;
    c.interpolate_offset = 0.1;
  }
  return c;
}

DinoEmbedderConfig DinoEmbedderConfig::from(config::Reader& r) {
  DinoEmbedderConfig c;
  if (r.has("dino_model")) c.vit = DinoVitConfig::hub_model(r.require<std::string>("dino_model"));
  if (r.has("vit")) {
    auto v = r.child("vit");
    c.vit = DinoVitConfig::from(v);
  }
  r.field("input_size", c.input_size);
  r.field("normalize_images", c.normalize_images);
  r.field("prenorm_features", c.prenorm_features);
  return c;
}

// ---------------------------------------------------------------------------------------------
// Layers

LayerScaleImpl::LayerScaleImpl(int64_t dim, double init_values) {
  gamma = register_parameter("gamma", torch::full({dim}, init_values));
}

VitAttentionImpl::VitAttentionImpl(int64_t dim, int64_t heads, bool qkv_bias, bool proj_bias) : num_heads(heads) {
  SIMU_CHECK(dim % heads == 0, "attention: dim {} is not divisible by num_heads {}", dim, heads);
  qkv = register_module("qkv", Linear(dim, 3 * dim, qkv_bias));
  proj = register_module("proj", Linear(dim, dim, proj_bias));
}

torch::Tensor VitAttentionImpl::forward(const torch::Tensor& x) {
  const int64_t B = x.size(0), N = x.size(1), C = x.size(2);
  // [B, N, 3, H, D] -> q, k, v [B, H, N, D]
  auto qkv5 = qkv(x).reshape({B, N, 3, num_heads, C / num_heads});
  auto q = qkv5.select(2, 0).transpose(1, 2);
  auto k = qkv5.select(2, 1).transpose(1, 2);
  auto v = qkv5.select(2, 2).transpose(1, 2);
  // softmax(q k^T / sqrt(D)) v, then heads back to channels: [B, N, C]
  auto o = at::scaled_dot_product_attention(q, k, v);
  o = o.transpose(1, 2).reshape({B, N, C});
  return proj(o);
}

VitMlpImpl::VitMlpImpl(int64_t dim, int64_t hidden, bool bias) {
  fc1 = register_module("fc1", Linear(dim, hidden, bias));
  fc2 = register_module("fc2", Linear(hidden, dim, bias));
}

VitBlockImpl::VitBlockImpl(int64_t dim, int64_t num_heads, double mlp_ratio, bool qkv_bias, bool proj_bias,
                           bool ffn_bias, double layer_scale_init) {
  norm1 = register_module("norm1", torch::nn::LayerNorm(torch::nn::LayerNormOptions({dim}).eps(1e-6)));
  attn = register_module("attn", VitAttention(dim, num_heads, qkv_bias, proj_bias));
  if (layer_scale_init > 0) ls1 = register_module("ls1", LayerScale(dim, layer_scale_init));
  norm2 = register_module("norm2", torch::nn::LayerNorm(torch::nn::LayerNormOptions({dim}).eps(1e-6)));
  mlp = register_module("mlp", VitMlp(dim, static_cast<int64_t>(dim * mlp_ratio), ffn_bias));
  if (layer_scale_init > 0) ls2 = register_module("ls2", LayerScale(dim, layer_scale_init));
}

torch::Tensor VitBlockImpl::forward(const torch::Tensor& x_in) {
  // Attention residual branch.
  auto a = attn(norm1(x_in));
  if (ls1) a = ls1(a);
  auto x = x_in + a;
  // MLP residual branch.
  auto m = mlp(norm2(x));
  if (ls2) m = ls2(m);
  return x + m;
}

DinoPatchEmbedImpl::DinoPatchEmbedImpl(int64_t in_chans, int64_t embed_dim, int64_t p) : patch_size(p) {
  proj = register_module("proj", torch::nn::Conv2d(torch::nn::Conv2dOptions(in_chans, embed_dim, p).stride(p)));
}

torch::Tensor DinoPatchEmbedImpl::forward(const torch::Tensor& x) {
  SIMU_CHECK(x.dim() == 4 && x.size(2) % patch_size == 0 && x.size(3) % patch_size == 0,
             "patch embedding: input [{}] must be [B, C, H, W] with H and W multiples of {}",
             fmt::join(x.sizes(), ", "), patch_size);
  // [B, C, H/p, W/p] -> [B, N, C]
  return proj(x).flatten(2).transpose(1, 2);
}

// ---------------------------------------------------------------------------------------------
// Vision transformer

DinoVisionTransformerImpl::DinoVisionTransformerImpl(const DinoVitConfig& c) : config(c) {
  SIMU_CHECK(c.ffn_layer == "mlp", "DINOv2 ffn_layer '{}' is not supported (only 'mlp')", c.ffn_layer);
  SIMU_CHECK(c.block_chunks == 0, "DINOv2 block_chunks {} is not supported (only 0, the hub default)",
             c.block_chunks);
  SIMU_CHECK(c.img_size % c.patch_size == 0, "DINOv2 img_size {} is not a multiple of patch_size {}", c.img_size,
             c.patch_size);
  const int64_t grid = c.img_size / c.patch_size;
  patch_embed = register_module("patch_embed", DinoPatchEmbed(c.in_chans, c.embed_dim, c.patch_size));
  cls_token = register_parameter("cls_token", torch::randn({1, 1, c.embed_dim}) * 1e-6);
  pos_embed = register_parameter("pos_embed", torch::randn({1, grid * grid + 1, c.embed_dim}) * 0.02);
  if (c.num_register_tokens > 0)
    register_tokens = register_parameter("register_tokens", torch::randn({1, c.num_register_tokens, c.embed_dim}) * 1e-6);
  for (int64_t i = 0; i < c.depth; ++i)
    blocks->push_back(VitBlock(c.embed_dim, c.num_heads, c.mlp_ratio, c.qkv_bias, c.proj_bias, c.ffn_bias,
                               c.init_values));
  register_module("blocks", blocks);
  if (c.has_norm)
    norm = register_module("norm", torch::nn::LayerNorm(torch::nn::LayerNormOptions({c.embed_dim}).eps(1e-6)));
  if (c.has_mask_token) mask_token = register_parameter("mask_token", torch::zeros({1, c.embed_dim}));
}

torch::Tensor DinoVisionTransformerImpl::interpolate_pos_encoding(int64_t h, int64_t w, torch::ScalarType dtype) {
  const int64_t p = config.patch_size;
  const int64_t gh = h / p, gw = w / p;  // dinov2 calls these w0 (dim 2) and h0 (dim 3)
  const int64_t npatch = gh * gw;
  const int64_t N = pos_embed.size(1) - 1;
  if (npatch == N && h == w) return pos_embed.to(dtype);
  const int64_t dim = pos_embed.size(2);
  const auto M = static_cast<int64_t>(std::sqrt(static_cast<double>(N)));
  SIMU_CHECK(M * M == N, "pos_embed holds {} patch positions, not a square grid", N);
  auto pe = pos_embed.to(torch::kFloat32);
  auto cls_pe = pe.select(1, 0);  // [1, C]
  // [1, M*M, C] -> [1, C, M, M]
  auto grid = pe.slice(1, 1).reshape({1, M, M, dim}).permute({0, 3, 1, 2});
  auto opts = F::InterpolateFuncOptions().mode(torch::kBicubic).align_corners(false).antialias(config.interpolate_antialias);
  if (config.interpolate_offset != 0.0) {
    // Scale factors (g + offset) / M, passed through to the kernel (not recomputed), as in dinov2.
    const double sx = (static_cast<double>(gh) + config.interpolate_offset) / static_cast<double>(M);
    const double sy = (static_cast<double>(gw) + config.interpolate_offset) / static_cast<double>(M);
    opts.scale_factor(std::vector<double>{sx, sy}).recompute_scale_factor(false);
  } else {
    opts.size(std::vector<int64_t>{gh, gw});
  }
  grid = F::interpolate(grid, opts);
  SIMU_CHECK(grid.size(2) == gh && grid.size(3) == gw,
             "pos_embed interpolation gave a {}x{} grid, {}x{} expected (interpolate_offset {})", grid.size(2),
             grid.size(3), gh, gw, config.interpolate_offset);
  // [1, C, gh, gw] -> [1, gh*gw, C]
  grid = grid.permute({0, 2, 3, 1}).reshape({1, gh * gw, dim});
  return torch::cat({cls_pe.unsqueeze(0), grid}, 1).to(dtype);
}

DinoFeatures DinoVisionTransformerImpl::forward_features(const torch::Tensor& x) {
  SIMU_CHECK(x.dim() == 4 && x.size(1) == config.in_chans, "DINOv2: input [{}] expected [B, {}, H, W]",
             fmt::join(x.sizes(), ", "), config.in_chans);
  const int64_t B = x.size(0), h = x.size(2), w = x.size(3);
  // Tokens [cls, patches] + position embedding, then registers after cls: [B, 1+R+N, C].
  auto t = patch_embed(x);
  t = torch::cat({cls_token.to(t.dtype()).expand({B, -1, -1}), t}, 1);
  t = t + interpolate_pos_encoding(h, w, t.scalar_type());
  if (register_tokens.defined())
    t = torch::cat({t.slice(1, 0, 1), register_tokens.to(t.dtype()).expand({B, -1, -1}), t.slice(1, 1)}, 1);
  // Transformer blocks.
  for (const auto& blk : *blocks) t = blk->as<VitBlockImpl>()->forward(t);
  // Final norm and split.
  DinoFeatures out;
  out.x_prenorm = t;
  auto xn = norm ? norm(t) : t;
  const int64_t R = config.num_register_tokens;
  out.x_norm_clstoken = xn.select(1, 0);
  out.x_norm_regtokens = xn.slice(1, 1, 1 + R);
  out.x_norm_patchtokens = xn.slice(1, 1 + R);
  return out;
}

// ---------------------------------------------------------------------------------------------
// Dino embedder

DinoImpl::DinoImpl(const DinoEmbedderConfig& c) : config(c) {
  SIMU_CHECK(c.input_size % c.vit.patch_size == 0, "Dino: input_size {} is not a multiple of patch_size {}",
             c.input_size, c.vit.patch_size);
  backbone = register_module("backbone", DinoVisionTransformer(c.vit));
}

int64_t DinoImpl::num_tokens() const {
  const int64_t g = config.input_size / config.vit.patch_size;
  return 1 + g * g + (config.prenorm_features ? config.vit.num_register_tokens : 0);
}

torch::Tensor DinoImpl::preprocess_input(const torch::Tensor& x) const {
  SIMU_CHECK(x.dim() == 4 && (x.size(1) == 1 || x.size(1) == 3), "Dino: input [{}] expected [B, 1 or 3, H, W]",
             fmt::join(x.sizes(), ", "));
  // Bilinear resize (align_corners false, no antialias) to input_size x input_size.
  auto r = F::interpolate(x, F::InterpolateFuncOptions()
                                 .size(std::vector<int64_t>{config.input_size, config.input_size})
                                 .mode(torch::kBilinear)
                                 .align_corners(false));
  // Masks (1 channel) are repeated to 3 channels.
  if (r.size(1) == 1) r = r.repeat({1, 3, 1, 1});
  // ImageNet normalisation.
  if (config.normalize_images) {
    // Subtract then divide in float32 with a rounding to the input dtype after each step, like the
    // official in-place sub_/div_ with float32 buffers.
    const auto dt = r.scalar_type();
    auto mean = torch::tensor({0.485, 0.456, 0.406}, torch::kFloat32).to(r.device()).view({1, 3, 1, 1});
    auto std = torch::tensor({0.229, 0.224, 0.225}, torch::kFloat32).to(r.device()).view({1, 3, 1, 1});
    r = (r.to(torch::kFloat32) - mean).to(dt);
    r = (r.to(torch::kFloat32) / std).to(dt);
  }
  return r;
}

torch::Tensor DinoImpl::forward(const torch::Tensor& x) { return forward_preprocessed(preprocess_input(x), x.scalar_type()); }

torch::Tensor DinoImpl::forward_preprocessed(const torch::Tensor& pre, torch::ScalarType out_dtype) {
  auto f = backbone->forward_features(pre);
  torch::Tensor tokens;
  if (config.prenorm_features) {
    // Plain layer norm (no affine, eps 1e-5) of every pre-norm token.
    tokens = torch::layer_norm(f.x_prenorm, {f.x_prenorm.size(-1)});
  } else {
    // [cls, patch tokens]: [B, 1+N, C]
    tokens = torch::cat({f.x_norm_clstoken.unsqueeze(1), f.x_norm_patchtokens}, 1);
  }
  return tokens.to(out_dtype);
}

}  // namespace simu::models
