#include "training/stage1_targets.h"

#include <ATen/CPUGeneratorImpl.h>

#include <filesystem>

#include "common/error.h"
#include "models/ss_encoder.h"

namespace simu::training {

torch::Tensor grid_to_shape_tokens(const torch::Tensor& grid) {
  SIMU_CHECK(grid.dim() == 5, "shape latent grid: expected [B, C, k, k, k], got {} dimensions", grid.dim());
  const int64_t B = grid.size(0), C = grid.size(1);
  // [B, C, k, k, k] -> [B, C, k^3] -> [B, k^3, C]
  return grid.reshape({B, C, -1}).permute({0, 2, 1}).contiguous();
}

ShapeTargetFn random_linear_targets(const models::LatentSpec& shape, int64_t R, uint64_t seed, torch::Device device) {
  const int64_t k = shape.resolution / shape.patch_size, C = shape.in_channels;
  SIMU_CHECK(k > 0 && R % k == 0, "random linear targets: occupancy side {} is not a multiple of the latent side {}", R, k);
  const int64_t s = R / k;
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  auto weight = (at::randn({C, 1, s, s, s}, gen, torch::TensorOptions().dtype(torch::kFloat32)) /
                 std::sqrt(static_cast<double>(s * s * s)))
                    .to(device);
  return [weight, s](const torch::Tensor& occupancy) {
    auto x = occupancy.to(torch::kFloat32).unsqueeze(1) - 0.5;  // [B, 1, R, R, R]
    return grid_to_shape_tokens(torch::conv3d(x, weight, {}, s));  // [B, k^3, C]
  };
}

ShapeTargetFn encoder_targets(models::SparseStructureEncoder encoder) {
  return [encoder](const torch::Tensor& occupancy) mutable {
    // The posterior mean of [B, 1, R, R, R] float occupancy: [B, C, k, k, k] -> tokens [B, k^3, C].
    return grid_to_shape_tokens(encoder->posterior(occupancy.to(torch::kFloat32).unsqueeze(1)).first);
  };
}

ShapeTargetFn make_shape_targets(const TargetsConfig& config, const models::LatentSpec& shape,
                                 int64_t occupancy_resolution, torch::Device device, const std::string& config_file) {
  if (config.kind == "random_linear") return random_linear_targets(shape, occupancy_resolution, config.seed, device);
  for (const auto& [key, path] : {std::pair{"encoder_config", config.encoder_config}, std::pair{"encoder_weights", config.encoder_weights}})
    if (!std::filesystem::exists(path))
      fail_hint("train the sparse-structure VAE first (train_ss_vae --config configs/miniature/ss_vae.yaml) or set the key",
                "{}: key 'targets.{}': '{}' does not exist", config_file, key, path);
  const auto ec = models::SSEncoderConfig::load(config.encoder_config);
  const int64_t k = shape.resolution / shape.patch_size;
  if (ec.latent_channels != shape.in_channels || occupancy_resolution != k * ec.downsample_factor() || ec.in_channels != 1)
    fail_hint("train the VAE for this flow model's shape latent and the cache's occupancy side",
              "{}: targets.encoder_config {} maps [1, {}^3] occupancy to [{}, {}^3] latents; the flow model's shape latent "
              "is [{}, {}^3] and the cache's occupancy is {}^3",
              config_file, config.encoder_config, occupancy_resolution, ec.latent_channels,
              occupancy_resolution / ec.downsample_factor(), shape.in_channels, k, occupancy_resolution);
  auto encoder = models::load_ss_encoder(config.encoder_config, config.encoder_weights, device);
  encoder->eval();
  for (auto& p : encoder->parameters()) p.set_requires_grad(false);
  return encoder_targets(encoder);
}

}  // namespace simu::training
