// Shape-latent targets of Stage-1 pretraining: a sample's ground-truth occupancy -> the flow model's
// shape latent, made inside train_stage1 (so the sample cache does not depend on the VAE). The real
// maker is the trained, frozen sparse-structure encoder (its posterior mean); a fixed random linear
// map stands in for tests and smoke runs.
#pragma once

#include <torch/torch.h>

#include <functional>

#include "models/flow_model.h"
#include "models/ss_encoder.h"
#include "training/stage1_config.h"

namespace simu::training {

// occupancy [B, R, R, R] (uint8 0/1 on the training device) -> the shape latent as the flow model
// reads it, tokens [B, k^3, C] float32 (token t = (x k + y) k + z of the latent grid [B, C, k, k, k],
// the inverse of models::shape_tokens_to_grid). Called without gradients.
using ShapeTargetFn = std::function<torch::Tensor(const torch::Tensor& occupancy)>;

// Grid [B, C, k, k, k] -> tokens [B, k^3, C] (inverse of models::shape_tokens_to_grid).
torch::Tensor grid_to_shape_tokens(const torch::Tensor& grid);

// A fixed random linear map: a strided 3-D convolution (kernel = stride = R / k, 1 -> C channels, no
// bias) with weights N(0, 1 / (R/k)^3) drawn from `seed`, applied to occupancy - 0.5: each latent
// token is a random linear function of its own block of voxels. Not a shape model.
ShapeTargetFn random_linear_targets(const models::LatentSpec& shape, int64_t occupancy_resolution, uint64_t seed,
                                    torch::Device device);

// The posterior mean of a (frozen) sparse-structure encoder, as tokens.
ShapeTargetFn encoder_targets(models::SparseStructureEncoder encoder);

// The maker a config asks for (targets.kind; "encoder" loads the frozen encoder on device, eval mode,
// no gradients). Checks that its latents fit the flow model's shape latent (channels, k^3 tokens) and
// the cache's R, naming the config and both shapes.
ShapeTargetFn make_shape_targets(const TargetsConfig& config, const models::LatentSpec& shape,
                                 int64_t occupancy_resolution, torch::Device device, const std::string& config_file);

}  // namespace simu::training
