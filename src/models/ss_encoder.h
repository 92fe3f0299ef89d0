// Sparse-structure encoder of SAM 3D Objects Stage 1 (official `SparseStructureEncoder`, the E_S of
// TRELLIS Sec. 3.3): a dense 3-D convolutional encoder from occupancy [B, 1, R, R, R] to a diagonal
// Gaussian posterior over the shape latent [B, 8, R/f, R/f, R/f] (mean and log-variance), the
// counterpart of SparseStructureDecoder (ss_decoder.h), whose blocks it reuses.
//
// Module tree and parameter names follow the official module, so its safetensors load strictly by name:
//   input_layer (Conv3d in_channels->channels[0], k3)
//   blocks.<i> (per level: num_res_blocks ResBlock3d, then a DownsampleBlock3d `conv` to the next level)
//   middle_block.<i> (ResBlock3d at the last level's width)
//   out_layer.0 (norm of norm_type), out_layer.1 (SiLU), out_layer.2 (Conv3d -> 2*latent_channels, k3)
// As in the official constructor, the residual blocks always use ChannelLayerNorm32: norm_type only
// chooses the output head's norm.
#pragma once

#include <torch/torch.h>

#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "common/config.h"
#include "models/ss_decoder.h"

namespace simu::models {

// Encoder hyper-parameters, named as the official constructor arguments (plus the TdfyWrapper's two).
struct SSEncoderConfig {
  int64_t in_channels = 1;
  int64_t latent_channels = 8;
  int64_t num_res_blocks = 2;
  std::vector<int64_t> channels = {32, 128, 512};
  int64_t num_res_blocks_middle = 2;
  std::string norm_type = "layer";  // output head's norm: "layer" (ChannelLayerNorm32) or "group" (GroupNorm32)
  // Official flag: the torso (blocks, middle_block) runs in float16; input/output layers in float32.
  bool use_fp16 = false;
  // SparseStructureEncoderTdfyWrapper's flags: z is a posterior sample (else the mean), and the output
  // carries mean and logvar (else z alone). Defaults: the wrapper's (true, true) when `_target_` names
  // the wrapper, the plain class's forward defaults (false, false) otherwise.
  bool sample_posterior = false;
  bool return_raw = false;

  // Reads the project layout ({"in_channels": .., "channels": [..], ...}) or the official YAML (the
  // same keys plus `_target_: ...SparseStructureEncoder[TdfyWrapper]` and `pretrained_ckpt_path`,
  // which is ignored). Unknown keys are errors naming the file and key.
  static SSEncoderConfig from(simu::config::Reader& r);
  // Loads a YAML/JSON file (with "a.b=v" overrides) and reads it with from().
  static SSEncoderConfig load(const std::string& path, const std::vector<std::string>& overrides = {});
  // Spatial down-sampling factor of the encoder (2^(levels-1)).
  int64_t downsample_factor() const { return int64_t{1} << (channels.size() - 1); }
};

// Official DownsampleBlock3d in "conv" mode: Conv3d(in, out, kernel 2, stride 2).
class DownsampleBlock3dImpl : public torch::nn::Module {
 public:
  DownsampleBlock3dImpl(int64_t in_channels, int64_t out_channels);
  // x: [B, C_in, D, H, W] -> [B, C_out, D/2, H/2, W/2]
  torch::Tensor forward(const torch::Tensor& x);

  torch::nn::Conv3d conv{nullptr};
};
TORCH_MODULE(DownsampleBlock3d);

// The encoder's outputs, as the official forward(x, sample_posterior, return_raw=True) returns them.
struct SSEncoderOutput {
  torch::Tensor z;       // [B, latent, r, r, r]: mean + exp(logvar / 2) * noise, or the mean
  torch::Tensor mean;    // [B, latent, r, r, r]
  torch::Tensor logvar;  // [B, latent, r, r, r]
};

class SparseStructureEncoderImpl : public torch::nn::Module {
 public:
  explicit SparseStructureEncoderImpl(SSEncoderConfig config);
  // The posterior's parameters. x: [B, in_channels, R, R, R] (any dtype; read as float32, as the
  // official x.float()) -> {mean, logvar} each [B, latent_channels, R/f, R/f, R/f] float32.
  std::pair<torch::Tensor, torch::Tensor> posterior(const torch::Tensor& x);
  // The official forward: z = mean + exp(0.5 * logvar) * noise when sample_posterior (noise: a given
  // standard-normal tensor shaped like mean, or a draw from the default generator as randn_like),
  // z = mean otherwise; mean and logvar are always filled (the official return_raw form).
  SSEncoderOutput forward(const torch::Tensor& x, bool sample_posterior = false,
                          const std::optional<torch::Tensor>& noise = std::nullopt);
  // The TdfyWrapper's forward: forward() with the config's sample_posterior; mean and logvar are left
  // undefined unless the config's return_raw.
  SSEncoderOutput encode(const torch::Tensor& x);

  const SSEncoderConfig& config() const { return config_; }

  torch::nn::Conv3d input_layer{nullptr};
  torch::nn::ModuleList blocks{nullptr};
  torch::nn::Sequential middle_block{nullptr};
  torch::nn::Sequential out_layer{nullptr};

 private:
  SSEncoderConfig config_;
  std::vector<std::function<torch::Tensor(const torch::Tensor&)>> block_forward_;  // one per blocks[i]
};
TORCH_MODULE(SparseStructureEncoder);

// Builds an encoder from a config file and loads its safetensors strictly (keys as the official
// module; keys under "io." are ignored so fixture files load too; "" = keep the random init).
SparseStructureEncoder load_ss_encoder(const std::string& config_path, const std::string& weights_path,
                                       torch::Device device = torch::kCPU);

// Samples of a diagonal Gaussian posterior: mean + exp(0.5 * logvar) * noise (all the same shape).
torch::Tensor sample_posterior(const torch::Tensor& mean, const torch::Tensor& logvar, const torch::Tensor& noise);

// KL(N(mean, exp(logvar)) || N(0, 1)) per element, 0.5 * (mean^2 + exp(logvar) - logvar - 1): the
// VAE's regulariser as TRELLIS trains the sparse-structure VAE (it takes the mean over every element).
torch::Tensor kl_to_standard_normal(const torch::Tensor& mean, const torch::Tensor& logvar);

}  // namespace simu::models
