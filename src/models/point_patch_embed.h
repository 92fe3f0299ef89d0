// Point-map embedder of SAM 3D: PointRemapper and PointPatchEmbed.
//
// Port of sam-3d-objects `sam3d_objects/model/backbone/dit/embedder/{point_remapper,pointmap}.py`.
// Parameter names follow the official state dict:
//   point_proj.{weight [D,3], bias [D]}, invalid_xyz_token [D], (dropped_xyz_token [D] when
//   dropout_prob > 0), pos_embed [1, D, n, n] (n = input_size / patch_size),
//   pos_embed_window [1, 1 + p*p, D], cls_token [1, 1, D],
//   blocks.0.{norm1, attn.qkv, attn.proj, norm2, mlp.fc1, mlp.fc2}.*  (timm Block, no LayerScale)
#pragma once

#include <torch/torch.h>

#include <string>

#include "common/config.h"
#include "models/dino.h"
#include "models/linear.h"

namespace simu::models {

// Remaps (x, y, z) points to a better-conditioned range, and back. Types (last dim is xyz):
//   linear:        p
//   sinh:          asinh(p)
//   exp:           (x/(1+z), y/(1+z), log1p(z))
//   exp_disparity: (x/z, y/z, log z)
//   sinh_exp:      (asinh x, asinh y, log(max(z, 1e-8)))
class PointRemapper {
 public:
  enum class Type { kLinear, kSinh, kExp, kSinhExp, kExpDisparity };
  explicit PointRemapper(const std::string& type = "exp");
  // points: [..., 3] -> [..., 3]
  torch::Tensor forward(const torch::Tensor& points) const;
  torch::Tensor inverse(const torch::Tensor& points) const;
  Type type() const { return type_; }
  const std::string& name() const { return name_; }

 private:
  Type type_;
  std::string name_;
};

struct PointPatchEmbedConfig {
  int64_t input_size = 256;         // point maps are resized (nearest) to input_size x input_size
  int64_t patch_size = 8;           // window size; one output token per window
  int64_t embed_dim = 768;
  std::string remap_output = "exp"; // PointRemapper type
  int64_t num_heads = 16;           // fixed to 16 in the official code
  double mlp_ratio = 2.0;           // fixed to 2.0 in the official code
  double dropout_prob = 0.0;        // > 0 adds dropped_xyz_token
  bool force_dropout_always = false;
  // `exp` remap only: points with z <= -1 (nearer than the object by more than the scene scale; the
  // domain of log1p ends there). The official code has no case for them: log1p gives NaN/-inf, the
  // window's token becomes NaN and, through cross-attention, so does every generated latent.
  //   "invalid" (default): they take invalid_xyz_token, as points without depth do; every other point
  //       is embedded exactly as the official code does;
  //   "nan": the official arithmetic, NaN included.
  // Other remaps have no such domain (linear: near points are ordinary values).
  std::string exp_near_points = "invalid";
  // Reads input_size, patch_size, embed_dim, remap_output, dropout_prob, force_dropout_always,
  // exp_near_points and the
  // fixture's block_heads / block_mlp_ratio (also accepted as num_heads / mlp_ratio).
  static PointPatchEmbedConfig from(config::Reader& r);
};

// PointPatchEmbed: xyz [B, 3, H, W] -> [B, (S/p)^2, D].
//  1. nearest resize to S = input_size; invalid = any non-finite coordinate (or the given mask), and
//     for the exp remap z <= -1 (see exp_near_points);
//  2. invalid points set to 0, PointRemapper, point_proj; invalid points take invalid_xyz_token;
//  3. per p x p window: [cls_token, p*p point tokens] + pos_embed_window -> one timm Block;
//  4. window cls tokens + pos_embed (bilinear resize of the [1, D, n, n] grid to the window grid);
//  5. pointmap dropout (training, or always with force_dropout_always when dropout_prob > 0).
class PointPatchEmbedImpl : public torch::nn::Module {
 public:
  explicit PointPatchEmbedImpl(const PointPatchEmbedConfig& config);
  // valid_mask: optional [B, H', W'] bool at input_size resolution (after the resize).
  torch::Tensor forward(const torch::Tensor& xyz, const torch::Tensor& valid_mask = {});
  // Steps 1-2 alone (official embed_pointmap_windows): per-point features [B, S, S, D].
  torch::Tensor embed_points(const torch::Tensor& xyz, const torch::Tensor& valid_mask = {});
  int64_t embed_dim() const { return config.embed_dim; }
  int64_t num_tokens() const {
    const int64_t n = config.input_size / config.patch_size;
    return n * n;
  }

  PointPatchEmbedConfig config;
  PointRemapper point_remapper;
  Linear point_proj{nullptr};
  torch::Tensor invalid_xyz_token, dropped_xyz_token, pos_embed, pos_embed_window, cls_token;
  torch::nn::ModuleList blocks;

 private:
  // pos_embed resized (bilinear, align_corners false) to h x w windows: [1, h*w, D].
  torch::Tensor window_pos_embed(int64_t h, int64_t w, torch::ScalarType dtype);
};
TORCH_MODULE(PointPatchEmbed);

}  // namespace simu::models
