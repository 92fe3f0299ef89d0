// Sparse-structure decoder of SAM 3D Objects Stage 1 (official `SparseStructureDecoder`, TRELLIS
// "ss_dec_conv3d"): a dense 3-D convolutional decoder from the [B, 8, 16, 16, 16] shape latent to
// [B, 1, 64, 64, 64] occupancy logits, plus the occupancy step of the official pipeline
// (tokens -> cube -> logits -> occupied voxel coordinates where logit > 0).
//
// Module tree and parameter names follow the official module, so the official safetensors load
// strictly by name:
//   input_layer (Conv3d latent->channels[0], k3)
//   middle_block.<i> (ResBlock3d: norm1, conv1, norm2, conv2[, skip_connection])
//   blocks.<i> (per level: num_res_blocks ResBlock3d, then an UpsampleBlock3d `conv` to the next level)
//   out_layer.0 (norm of norm_type), out_layer.1 (SiLU), out_layer.2 (Conv3d -> out_channels, k3)
#pragma once

#include <torch/torch.h>

#include <functional>
#include <string>
#include <vector>

#include "common/config.h"

namespace simu::models {

// Decoder hyper-parameters, named as the official constructor arguments.
struct SSDecoderConfig {
  int64_t out_channels = 1;
  int64_t latent_channels = 8;
  int64_t num_res_blocks = 2;
  std::vector<int64_t> channels = {512, 128, 32};
  int64_t num_res_blocks_middle = 2;
  // The output head's norm: "layer" (ChannelLayerNorm32) or "group" (GroupNorm32, 32 groups). The residual
  // blocks use layer norm either way, as the official constructor builds them.
  std::string norm_type = "layer";
  // Official flag: forward() first turns [B, T, C] tokens into a cube with `flat_to_cube`.
  bool reshape_input_to_cube = false;
  // Official flag: the torso (middle_block, blocks) runs in float16; input/output layers in float32.
  bool use_fp16 = false;

  // Reads the project layout ({"out_channels": .., "channels": [..], ...}) or the official YAML
  // (the same keys plus `_target_: ...SparseStructureDecoder[TdfyWrapper]` and
  // `pretrained_ckpt_path`, which is ignored). Unknown keys are errors.
  static SSDecoderConfig from(simu::config::Reader& r);
  // Loads a YAML/JSON file (with "a.b=v" overrides) and reads it with from().
  static SSDecoderConfig load(const std::string& path, const std::vector<std::string>& overrides = {});
  // Spatial upsampling factor of the decoder (2^(levels-1)).
  int64_t upsample_factor() const { return int64_t{1} << (channels.size() - 1); }
};

// Official ChannelLayerNorm32: LayerNorm over the channel dimension of [B, C, *spatial], computed in
// float32 and cast back to the input dtype. Parameters `weight`, `bias` [C]; eps 1e-5.
// With group = true it is GroupNorm32 (32 groups, float32) instead.
class ChannelNorm32Impl : public torch::nn::Module {
 public:
  ChannelNorm32Impl(int64_t channels, bool group = false);
  // x: [B, C, D, H, W] -> same shape and dtype
  torch::Tensor forward(const torch::Tensor& x);

  int64_t channels;
  bool group;
  torch::Tensor weight, bias;  // [C]
};
TORCH_MODULE(ChannelNorm32);

// Official ResBlock3d: norm1 -> SiLU -> conv1 -> norm2 -> SiLU -> conv2, plus skip (1x1 conv when the
// channel count changes, identity otherwise).
class ResBlock3dImpl : public torch::nn::Module {
 public:
  ResBlock3dImpl(int64_t channels, int64_t out_channels, const std::string& norm_type);
  // x: [B, C, D, H, W] -> [B, C_out, D, H, W]
  torch::Tensor forward(const torch::Tensor& x);

  ChannelNorm32 norm1{nullptr}, norm2{nullptr};
  torch::nn::Conv3d conv1{nullptr}, conv2{nullptr}, skip_connection{nullptr};
};
TORCH_MODULE(ResBlock3d);

// Official UpsampleBlock3d in "conv" mode: Conv3d(in, out*8, k3) followed by 3-D pixel shuffle x2.
class UpsampleBlock3dImpl : public torch::nn::Module {
 public:
  UpsampleBlock3dImpl(int64_t in_channels, int64_t out_channels);
  // x: [B, C_in, D, H, W] -> [B, C_out, 2D, 2H, 2W]
  torch::Tensor forward(const torch::Tensor& x);

  torch::nn::Conv3d conv{nullptr};
};
TORCH_MODULE(UpsampleBlock3d);

// 3-D pixel shuffle as the official `pixel_shuffle_3d`: channel c*f^3 + (i*f + j)*f + k goes to
// spatial offset (i, j, k) of output channel c. x: [B, C*f^3, H, W, D] -> [B, C, fH, fW, fD].
torch::Tensor pixel_shuffle_3d(const torch::Tensor& x, int64_t factor);

class SparseStructureDecoderImpl : public torch::nn::Module {
 public:
  explicit SparseStructureDecoderImpl(SSDecoderConfig config);
  // x: [B, latent_channels, R, R, R] (or [B, R^3, latent_channels] when reshape_input_to_cube)
  // -> logits [B, out_channels, R*f, R*f, R*f] with f = config.upsample_factor(), in x's dtype.
  torch::Tensor forward(const torch::Tensor& x);

  const SSDecoderConfig& config() const { return config_; }

  torch::nn::Conv3d input_layer{nullptr};
  torch::nn::Sequential middle_block{nullptr};
  torch::nn::ModuleList blocks{nullptr};
  torch::nn::Sequential out_layer{nullptr};

 private:
  SSDecoderConfig config_;
  std::vector<std::function<torch::Tensor(const torch::Tensor&)>> block_forward_;  // one per blocks[i]
};
TORCH_MODULE(SparseStructureDecoder);

// Builds a decoder from a config file and loads its safetensors strictly (keys as the official module;
// keys under "io." are ignored so fixture files load too; "" = keep the random init, as load_generator).
// device/dtype: where the parameters live.
SparseStructureDecoder load_ss_decoder(const std::string& config_path, const std::string& weights_path,
                                       torch::Device device = torch::kCPU);

// Official `flat_to_cube`: tokens [B, k^3, C] -> [B, C, k, k, k] by view(B, k, k, k, C).permute(0,4,1,2,3).
torch::Tensor flat_to_cube(const torch::Tensor& tokens);

// The official pipeline's reshape of the generator's shape latent before decoding
// (`shape_latent.permute(0, 2, 1).contiguous().view(B, C, k, k, k)`): token index t = (x*k + y)*k + z
// lands at grid [x, y, z]. tokens [B, k^3, C] -> [B, C, k, k, k]. (Same result as flat_to_cube.)
torch::Tensor shape_tokens_to_grid(const torch::Tensor& tokens);

// Official occupancy step: `argwhere(logits > 0)[:, [0, 2, 3, 4]]`. logits [B, 1, R, R, R] ->
// int32 [N, 4] rows (batch, x, y, z), sorted by batch then x, y, z (row-major order). On logits' device.
torch::Tensor occupied_coords(const torch::Tensor& logits);

}  // namespace simu::models
