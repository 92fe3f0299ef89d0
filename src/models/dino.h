// DINOv2 vision transformer (with optional register tokens) and the SAM 3D `Dino` image embedder.
//
// Port of facebookresearch/dinov2 `DinoVisionTransformer` (dinov2/models/vision_transformer.py,
// dinov2/layers/{patch_embed,attention,block,layer_scale,mlp}.py) and of sam-3d-objects
// `sam3d_objects/model/backbone/dit/embedder/dino.py::Dino`. Parameter names follow the official
// state dicts, so a `Dino` loads the keys `backbone.<dinov2 key>` unchanged:
//   backbone.cls_token [1,1,C], backbone.pos_embed [1,1+N,C], backbone.register_tokens [1,R,C],
//   backbone.mask_token [1,C], backbone.patch_embed.proj.{weight,bias},
//   backbone.blocks.<i>.{norm1,attn.qkv,attn.proj,ls1.gamma,norm2,mlp.fc1,mlp.fc2,ls2.gamma}.*,
//   backbone.norm.{weight,bias}
#pragma once

#include <torch/torch.h>

#include <string>

#include "common/config.h"
#include "models/linear.h"

namespace simu::models {

// Shape of a DINOv2 ViT (the keyword arguments of dinov2's `_make_dinov2_model` / `vit_*`).
struct DinoVitConfig {
  int64_t img_size = 518;       // size the learnt position embedding was made for (grid img_size/patch)
  int64_t patch_size = 14;
  int64_t in_chans = 3;
  int64_t embed_dim = 1024;
  int64_t depth = 24;
  int64_t num_heads = 16;
  double mlp_ratio = 4.0;
  bool qkv_bias = true;
  bool proj_bias = true;
  bool ffn_bias = true;
  double init_values = 1.0;     // LayerScale on (ls1/ls2 with `gamma`) when > 0
  std::string ffn_layer = "mlp";  // only "mlp" (ViT-S/B/L); "swiglu" (ViT-g) is refused
  int64_t block_chunks = 0;     // only 0 (dinov2 hub default; other values rename the block keys)
  int64_t num_register_tokens = 0;
  bool interpolate_antialias = false;
  double interpolate_offset = 0.1;
  // SAM 3D's Dino(prune_network=True) removes mask_token (and norm when prenorm_features): then
  // those keys are absent from the checkpoint. False keeps them (the dinov2 layout).
  bool has_mask_token = true;
  bool has_norm = true;

  // Reads the keys above (dinov2 names: img_size, patch_size, embed_dim, depth, num_heads, mlp_ratio,
  // init_values, ffn_layer, block_chunks, num_register_tokens, interpolate_antialias, interpolate_offset,
  // qkv_bias, proj_bias, ffn_bias, in_chans).
  static DinoVitConfig from(config::Reader& r);
  // The torch.hub entry points of dinov2 ("dinov2_vits14", "dinov2_vitl14_reg", ...): architecture
  // plus the hub defaults (img_size 518, patch 14, init_values 1.0; *_reg: 4 registers,
  // interpolate_antialias true, interpolate_offset 0.0). ViT-g is refused (SwiGLU FFN not ported).
  static DinoVitConfig hub_model(const std::string& name);
};

// LayerScale: x * gamma (parameter `gamma` [C]).
class LayerScaleImpl : public torch::nn::Module {
 public:
  LayerScaleImpl(int64_t dim, double init_values);
  torch::Tensor forward(const torch::Tensor& x) { return x * gamma; }
  torch::Tensor gamma;
};
TORCH_MODULE(LayerScale);

// Multi-head self-attention with a fused qkv projection (dinov2 `Attention` == timm `Attention`
// without q/k norm): qkv [B,N,3C] -> SDPA per head -> proj.
class VitAttentionImpl : public torch::nn::Module {
 public:
  VitAttentionImpl(int64_t dim, int64_t num_heads, bool qkv_bias, bool proj_bias);
  // x: [B, N, C] -> [B, N, C]
  torch::Tensor forward(const torch::Tensor& x);
  int64_t num_heads;
  Linear qkv{nullptr}, proj{nullptr};
};
TORCH_MODULE(VitAttention);

// Two-layer GELU MLP (`fc1`, `fc2`), exact (erf) GELU as torch.nn.GELU().
class VitMlpImpl : public torch::nn::Module {
 public:
  VitMlpImpl(int64_t dim, int64_t hidden, bool bias);
  torch::Tensor forward(const torch::Tensor& x) { return fc2(torch::gelu(fc1(x))); }
  Linear fc1{nullptr}, fc2{nullptr};
};
TORCH_MODULE(VitMlp);

// Pre-norm transformer block: x + ls1(attn(norm1 x)); x + ls2(mlp(norm2 x)). LayerNorm eps 1e-6.
// With layer_scale_init <= 0 there is no ls1/ls2 (no parameters): that is exactly timm's
// `Block(dim, num_heads, mlp_ratio, qkv_bias=True, norm_layer=LayerNorm(eps=1e-6))` (GELU MLP, hidden
// int(dim*mlp_ratio)), which PointPatchEmbed uses, so both share this class.
class VitBlockImpl : public torch::nn::Module {
 public:
  VitBlockImpl(int64_t dim, int64_t num_heads, double mlp_ratio, bool qkv_bias, bool proj_bias, bool ffn_bias,
               double layer_scale_init);
  // x: [B, N, C] -> [B, N, C]
  torch::Tensor forward(const torch::Tensor& x);
  torch::nn::LayerNorm norm1{nullptr}, norm2{nullptr};
  VitAttention attn{nullptr};
  VitMlp mlp{nullptr};
  LayerScale ls1{nullptr}, ls2{nullptr};  // null without LayerScale
};
TORCH_MODULE(VitBlock);

// Patch embedding: Conv2d(in, C, kernel = stride = patch) then flatten -> [B, N, C] (`proj`).
class DinoPatchEmbedImpl : public torch::nn::Module {
 public:
  DinoPatchEmbedImpl(int64_t in_chans, int64_t embed_dim, int64_t patch_size);
  // x: [B, in, H, W] -> [B, (H/p)*(W/p), C], row-major over the patch grid.
  torch::Tensor forward(const torch::Tensor& x);
  int64_t patch_size;
  torch::nn::Conv2d proj{nullptr};
};
TORCH_MODULE(DinoPatchEmbed);

// Outputs of DinoVisionTransformer::forward_features (dinov2's dict).
struct DinoFeatures {
  torch::Tensor x_norm_clstoken;    // [B, C]
  torch::Tensor x_norm_regtokens;   // [B, R, C]
  torch::Tensor x_norm_patchtokens; // [B, N, C]
  torch::Tensor x_prenorm;          // [B, 1+R+N, C] before the final norm
};

class DinoVisionTransformerImpl : public torch::nn::Module {
 public:
  explicit DinoVisionTransformerImpl(const DinoVitConfig& config);
  // x: [B, in_chans, H, W] with H, W multiples of patch_size.
  DinoFeatures forward_features(const torch::Tensor& x);
  // Position embedding for an input of h x w pixels: [1, 1 + (h/p)*(w/p), C]. The stored one when
  // the grid matches, else dinov2's bicubic interpolation (interpolate_offset > 0: scale factors
  // (g+offset)/M; else target size; antialias flag), computed in float32, cast to `dtype`.
  torch::Tensor interpolate_pos_encoding(int64_t h, int64_t w, torch::ScalarType dtype);

  DinoVitConfig config;
  DinoPatchEmbed patch_embed{nullptr};
  torch::Tensor cls_token, pos_embed, register_tokens, mask_token;
  torch::nn::ModuleList blocks;
  torch::nn::LayerNorm norm{nullptr};  // null when config.has_norm is false
};
TORCH_MODULE(DinoVisionTransformer);

// Settings of the SAM 3D `Dino` embedder (constructor arguments of dino.py::Dino).
struct DinoEmbedderConfig {
  DinoVitConfig vit;
  int64_t input_size = 518;     // inputs are resized (bilinear, align_corners false) to this square
  bool normalize_images = true; // ImageNet mean/std normalisation after resizing
  bool prenorm_features = false;
  static DinoEmbedderConfig from(config::Reader& r);
};

// dino.py::Dino: resize -> (1 channel -> 3) -> ImageNet normalisation -> ViT.
// Output: [B, 1 + N, C] = [cls, patch tokens] after the final norm (registers dropped); with
// prenorm_features: layer_norm (no affine, eps 1e-5) of the whole pre-norm sequence
// [B, 1 + R + N, C] (cls, registers and patches, as the official code returns it).
class DinoImpl : public torch::nn::Module {
 public:
  explicit DinoImpl(const DinoEmbedderConfig& config);
  // x: [B, 1 or 3, H, W] in [0, 1]; returns tokens in x's dtype.
  torch::Tensor forward(const torch::Tensor& x);
  // The resized, channel-expanded, normalised input fed to the ViT: [B, 3, S, S].
  torch::Tensor preprocess_input(const torch::Tensor& x) const;
  // Tokens of already preprocessed inputs ([B, 3, S, S]), cast to out_dtype. forward(x) ==
  // forward_preprocessed(preprocess_input(x), x.dtype); preprocessed inputs of several images can be
  // concatenated along the batch and run at once.
  torch::Tensor forward_preprocessed(const torch::Tensor& pre, torch::ScalarType out_dtype);
  int64_t embed_dim() const { return config.vit.embed_dim; }
  // Tokens per input: 1 + (S/p)^2 (+R with prenorm_features).
  int64_t num_tokens() const;

  DinoEmbedderConfig config;
  DinoVisionTransformer backbone{nullptr};
};
TORCH_MODULE(Dino);

}  // namespace simu::models
