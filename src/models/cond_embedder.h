// Stage-1 condition embedder of SAM 3D Objects: the `EmbedderFuser` over DINOv2 image/mask
// embedders and the point-map embedder, producing the condition tokens the flow model reads.
//
// Port of sam-3d-objects `sam3d_objects/model/backbone/dit/embedder/embedder_fuser.py` and
// `sam3d_objects/model/layers/llama3/ff.py`. State-dict names are the official ones:
//   module_list.<i>.<embedder keys>   (Dino: backbone.*, PointPatchEmbed: point_proj.*, blocks.0.*, ...)
//   projection_nets.<i>.0.{weight,bias}          LayerNorm (when projection_pre_norm)
//   projection_nets.<i>.1.{w1,w2,w3}.weight      llama3 SwiGLU FeedForward
//   idx_emb [G+1, C] (learned) or [G+1, 1, C] buffer (random)   modality / position-group embedding
//   compression_projector.{0,1}.*                (only with compression_projection_multiplier > 0)
// In the released checkpoints (ss_generator.ckpt / .safetensors) these keys carry the prefix
// `_base_models.condition_embedder.` (kOfficialCondEmbedderPrefix), next to the generator's
// `_base_models.generator.` keys; sam3d_objects/pipeline/inference_pipeline.py strips it the same way.
//
// Usage:
//   auto emb = simu::models::load_cond_embedder("configs/cond_embedder_sam3d_stage1.yaml",
//                                              "checkpoints/ss_generator.safetensors", "auto", torch::kCUDA);
//   auto inputs = simu::data::prepare_condition_inputs(rgb, mask, pointmap, cfg);   // data/preprocess.h
//   torch::Tensor cond = emb->forward(inputs.tensors);                              // [B, L, C]
#pragma once

#include <torch/torch.h>

#include <map>
#include <string>
#include <utility>
#include <vector>

#include "common/config.h"
#include "models/dino.h"
#include "models/linear.h"
#include "models/point_patch_embed.h"

namespace simu::models {

// Checkpoint prefix of the condition embedder in the official generator checkpoints.
inline constexpr const char* kOfficialCondEmbedderPrefix = "_base_models.condition_embedder.";

// llama3 FeedForward: w2(silu(w1 x) * w3 x), no biases. The hidden size is
// h = int(2*hidden_dim/3), optionally int(ffn_dim_multiplier*h), rounded up to a multiple of multiple_of.
class FeedForwardImpl : public torch::nn::Module {
 public:
  FeedForwardImpl(int64_t dim, int64_t hidden_dim, int64_t output_dim = -1, int64_t multiple_of = 256,
                  double ffn_dim_multiplier = 0.0 /* 0: none */, bool skip_w2 = false);
  // x: [..., dim] -> [..., output_dim] (or [..., hidden] with skip_w2)
  torch::Tensor forward(const torch::Tensor& x);
  // The rounded hidden size for these arguments.
  static int64_t hidden_size(int64_t hidden_dim, int64_t multiple_of = 256, double ffn_dim_multiplier = 0.0);
  Linear w1{nullptr}, w2{nullptr}, w3{nullptr};
};
TORCH_MODULE(FeedForward);

// Projection net of the fuser: `0` LayerNorm(in) (eps 1e-5, when pre_norm) then `1` FeedForward(in,
// hidden = int(multiplier * out), out).
class ProjectionNetImpl : public torch::nn::Module {
 public:
  ProjectionNetImpl(int64_t in_dim, int64_t out_dim, double multiplier, bool pre_norm);
  torch::Tensor forward(const torch::Tensor& x);
  torch::nn::LayerNorm norm{nullptr};  // registered as "0"
  FeedForward ff{nullptr};             // registered as "1"
};
TORCH_MODULE(ProjectionNet);

// One embedder of the fuser and the inputs (kwarg names) it embeds, each with its position group
// ("" = none). Inputs are embedded in list order; that order is the token order of the output.
struct CondEmbedderEntry {
  std::string name;  // for messages ("dino_image", or the official _target_ class name)
  enum class Kind { kDino, kPointPatch } kind = Kind::kDino;
  DinoEmbedderConfig dino;
  PointPatchEmbedConfig point;
  std::vector<std::pair<std::string, std::string>> inputs;  // (kwarg, pos group)
};

struct CondEmbedderConfig {
  std::vector<CondEmbedderEntry> embedders;
  std::string use_pos_embedding = "learned";  // "learned" or "random" (the official code has no other)
  bool projection_pre_norm = true;
  double projection_net_hidden_dim_multiplier = 4.0;  // 0: no projection nets
  double compression_projection_multiplier = 0.0;     // > 0: concatenate channels + compression_projector
  // Training-time modality dropout: with probability dropout_prob one of these kwarg sets (picked by
  // weight) is zeroed per sample.
  double dropout_prob = 0.0;
  std::vector<std::pair<std::vector<std::string>, double>> drop_modalities_weight;
  // Kwargs whose tokens are always multiplied by 0 (the point-map CFG variant drops pointmaps).
  std::vector<std::string> force_drop_modalities;

  // Reads either layout, detected from the root:
  //  - fixture layout (cond_embedder_small.json): keys vit, dino_<name>_input_size, pointpatch, fuser;
  //  - official Hydra layout (ss_generator.yaml): module.condition_embedder.backbone (or a mapping
  //    whose _target_ is ...EmbedderFuser) with embedder_list: [[{_target_: ...Dino|...PointPatchEmbed,
  //    kwargs}, [[kwarg, group], ...]], ...]. Dino: dino_model (hub name), input_size,
  //    normalize_images, prenorm_features, prune_network, backbone_kwargs (ViT overrides).
  // Unknown keys are errors naming the file and key.
  static CondEmbedderConfig from_node(const YAML::Node& root, const std::string& file);
  static CondEmbedderConfig load(const std::string& path, const std::vector<std::string>& overrides = {});
  // The real Stage-1 embedder (see configs/cond_embedder_sam3d_stage1.yaml for the source):
  // Dino ViT-L/14 + 4 registers at 518 px for (image, rgb_image) and for (mask, rgb_image_mask),
  // PointPatchEmbed(256, patch 8, 512 dims, remap linear) for (pointmap, rgb_pointmap), 1024 dims out.
  static CondEmbedderConfig sam3d_stage1();
  // Fused tokens per object (L) and output channels (C) this config produces.
  int64_t num_tokens() const;
  int64_t embed_dims() const;
};

class CondEmbedderImpl : public torch::nn::Module {
 public:
  explicit CondEmbedderImpl(const CondEmbedderConfig& config);

  // inputs: official kwarg names -> tensors (all of one batch size B):
  //   image [B,3,H,W], rgb_image [B,3,H,W], mask [B,1,H,W], rgb_image_mask [B,1,H,W] (values in [0,1]),
  //   pointmap [B,3,H,W], rgb_pointmap [B,3,H,W] (normalised points, NaN = invalid).
  // Extra keys are ignored; a missing one is an error listing what was given.
  // Returns [B, L, C]: per kwarg in config order, embedder -> projection net -> + idx_emb[group],
  // forced drops applied, concatenated along tokens (or channels + compression with compression > 0).
  torch::Tensor forward(const std::map<std::string, torch::Tensor>& inputs);

  // Embedder i alone on one input (no projection): [B, T_i, C_i].
  torch::Tensor embed(size_t index, const torch::Tensor& x);
  // Tokens per object of the fused output (L).
  int64_t num_tokens() const;
  // Kwargs read by forward, in order.
  std::vector<std::string> input_names() const;
  int64_t embed_dims() const { return embed_dims_; }

  // Fast path (default on): the inputs of one Dino (e.g. image and rgb_image) are resized and
  // normalised separately, then run through the ViT and the projection net as one batch. Same math as
  // the official one-input-at-a-time loop (off), which stays as the reference.
  bool batch_dino_inputs = true;

  CondEmbedderConfig config;
  torch::nn::ModuleList module_list;
  torch::nn::ModuleList projection_nets;
  ProjectionNet compression_projector{nullptr};
  torch::Tensor idx_emb;
  std::map<std::string, int64_t> positional_embed_map;  // group -> row of idx_emb

 private:
  std::vector<Dino> dinos_;               // per entry (null for point embedders)
  std::vector<PointPatchEmbed> points_;   // per entry (null for Dino)
  int64_t embed_dims_ = 0;
};
TORCH_MODULE(CondEmbedder);

// Builds the embedder from `config_path` (either layout), loads `weights_path` (safetensors) strictly
// by official names and moves it to `device`, frozen (no grad) and in eval mode.
// prefix: checkpoint key prefix to select and strip ("" = none, e.g. the fixture;
// kOfficialCondEmbedderPrefix for ss_generator.safetensors; "auto" = the official prefix when any key
// has it, else none). Every missing/unexpected/mismatched key is reported in one error.
CondEmbedder load_cond_embedder(const std::string& config_path, const std::string& weights_path,
                                const std::string& prefix = "auto", torch::Device device = torch::kCPU);

}  // namespace simu::models
