// The whole Stage-1 model as one trainable module (train_stage1): the generator, whose MoT flow
// model (shape + pose latents) is what trains, and the condition embedder (DINOv2-architecture ViTs,
// PointPatchEmbed, fuser). Made from config files, initialised as the official code does, every
// parameter trainable, and exported in the released checkpoint's layout, which lift and the other
// programs load as generator weights and as embedder weights alike:
//   _base_models.generator.reverse_fn.backbone.<...>      the flow model
//   _base_models.condition_embedder.<...>                 the condition embedder
#pragma once

#include <torch/torch.h>

#include <string>
#include <utility>
#include <vector>

#include "models/cond_embedder.h"
#include "models/generator.h"

namespace simu::training {

// Checkpoint prefixes of the released ss_generator.safetensors.
inline constexpr const char* kGeneratorPrefix = "_base_models.generator.";

class Stage1ModelImpl : public torch::nn::Module {
 public:
  Stage1ModelImpl(const models::GeneratorConfig& generator_config, const models::CondEmbedderConfig& embedder_config);
  models::SparseStructureFlowTdfyWrapper backbone() { return generator->backbone(); }
  // Every parameter under its released name, in module order (what AdamW, EMA and checkpoints use).
  std::vector<std::pair<std::string, torch::Tensor>> named_weights();
  // Every buffer under its released name (fixed position embeddings and the like; exported too).
  std::vector<std::pair<std::string, torch::Tensor>> named_fixed();

  models::Generator generator{nullptr};
  models::CondEmbedder embedder{nullptr};
};
TORCH_MODULE(Stage1Model);

// The official initialisation of a model trained from scratch. Flow model (TRELLIS/SAM 3D
// initialize_weights): every Linear xavier-uniform with zero bias, the timestep embedder's two
// Linears N(0, 0.02), the shortcut d embedder's last Linear zero, every adaLN modulation Linear zero
// (each block starts as the identity). Embedder: the DINOv2 ViTs' Linears N(0, 0.02) with zero bias
// (dinov2's init_weights; its cls / register / position tokens are drawn so at construction); the
// point-patch embedder and the fuser keep their constructors' initialisation (PyTorch defaults).
// Draws from the default CPU generator (seed it first).
void init_stage1_weights(Stage1Model& model);

// Builds the model from its config files: seeded with `seed` (every rank alike), initialised with
// init_stage1_weights or loaded from `init_weights` (released layout, strict), moved to device, in
// training mode and trainable. The flow model runs its ATen reference path (its fused CUDA kernels
// compute no weight gradients: they are for sampling and the frozen base of FM-DPO).
Stage1Model make_stage1_model(const std::string& generator_config, const std::string& embedder_config,
                              const std::string& init_weights, torch::Device device, uint64_t seed);

// Writes tensors (released names) as one safetensors file, atomically, converted to dtype (float32 or
// float16; integer buffers keep theirs).
void save_stage1_weights(const std::string& path, const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                         torch::ScalarType dtype);

// Matrix-product FLOPs (2 per multiply-add) of one sample's forwards, counted analytically: the flow
// model's (models::flow_forward_flops at the embedder's condition length) and the embedder's (per
// DINOv2 input: patch embedding, blocks over 1 + registers + patches tokens incl. attention, the
// projection net; per point map: point_proj, one block over every p*p+1-token window, the projection
// net). A training sample costs about 3x their sum (backward = 2x forward), plus 2 to 4 extra flow
// forwards per shortcut sample.
struct Stage1Flops {
  double flow_forward = 0, embedder_forward = 0;
  int64_t condition_tokens = 0;
  double training_per_sample() const { return 3 * (flow_forward + embedder_forward); }
};
Stage1Flops stage1_flops(const models::GeneratorConfig& generator, const models::CondEmbedderConfig& embedder);

// Parameter counts of a model: the flow model's, the embedder's.
struct Stage1Counts {
  int64_t flow = 0, embedder = 0;
};
Stage1Counts count_parameters(Stage1Model& model);

}  // namespace simu::training
