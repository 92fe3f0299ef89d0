#include "models/ss_decoder.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <cmath>

#include "common/error.h"
#include "models/weights.h"

namespace simu::models {

namespace {
torch::nn::Conv3d conv3d(int64_t in, int64_t out, int64_t kernel) {
  return torch::nn::Conv3d(torch::nn::Conv3dOptions(in, out, kernel).padding(kernel / 2));
}
bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}
}  // namespace

SSDecoderConfig SSDecoderConfig::from(simu::config::Reader& r) {
  SSDecoderConfig c;
  // Official YAML extras: the class path (checked) and the checkpoint path (the loader takes it apart).
  if (r.has("_target_")) {
    const auto target = r.require<std::string>("_target_");
    SIMU_CHECK(ends_with(target, "SparseStructureDecoder") || ends_with(target, "SparseStructureDecoderTdfyWrapper"),
               "{}: _target_ '{}' is not a SparseStructureDecoder", r.file(), target);
  }
  if (r.has("pretrained_ckpt_path")) r.raw("pretrained_ckpt_path");
  r.field("out_channels", c.out_channels);
  r.field("latent_channels", c.latent_channels);
  r.field("num_res_blocks", c.num_res_blocks);
  r.field("channels", c.channels);
  r.field("num_res_blocks_middle", c.num_res_blocks_middle);
  r.field("norm_type", c.norm_type);
  r.field("reshape_input_to_cube", c.reshape_input_to_cube);
  r.field("use_fp16", c.use_fp16);
  r.finish();
  // Sanity of the values, each error naming the file and key.
  SIMU_CHECK(!c.channels.empty(), "{}: 'channels' must list at least one level", r.file());
  for (auto ch : c.channels) SIMU_CHECK(ch > 0, "{}: 'channels' entries must be positive, got {}", r.file(), ch);
  SIMU_CHECK(c.norm_type == "layer" || c.norm_type == "group", "{}: norm_type must be 'layer' or 'group', got '{}'",
             r.file(), c.norm_type);
  SIMU_CHECK(c.out_channels > 0 && c.latent_channels > 0 && c.num_res_blocks >= 0 && c.num_res_blocks_middle >= 0,
             "{}: channel and block counts must be positive", r.file());
  return c;
}

SSDecoderConfig SSDecoderConfig::load(const std::string& path, const std::vector<std::string>& overrides) {
  simu::config::Reader r(simu::config::load_file(path, overrides), path);
  return from(r);
}

// ---------------------------------------------------------------------------------------------
ChannelNorm32Impl::ChannelNorm32Impl(int64_t channels_, bool group_) : channels(channels_), group(group_) {
  weight = register_parameter("weight", torch::ones({channels}));
  bias = register_parameter("bias", torch::zeros({channels}));
}

torch::Tensor ChannelNorm32Impl::forward(const torch::Tensor& x) {
  const auto dtype = x.scalar_type();
  const auto w = weight.to(torch::kFloat32), b = bias.to(torch::kFloat32);
  if (group) {
    // GroupNorm32: 32 groups over [B, C, ...] in float32.
    return torch::group_norm(x.to(torch::kFloat32), 32, w, b, 1e-5).to(dtype);
  }
  // ChannelLayerNorm32: channels last, LayerNorm over C in float32, channels back to dim 1.
  const int64_t dims = x.dim();
  std::vector<int64_t> to_last{0}, to_first{0, dims - 1};
  for (int64_t d = 2; d < dims; ++d) to_last.push_back(d);
  to_last.push_back(1);
  for (int64_t d = 1; d < dims - 1; ++d) to_first.push_back(d);
  auto h = x.permute(to_last).contiguous().to(torch::kFloat32);  // [B, *spatial, C]
  h = torch::layer_norm(h, {channels}, w, b, 1e-5).to(dtype);
  return h.permute(to_first).contiguous();  // [B, C, *spatial]
}

// ---------------------------------------------------------------------------------------------
ResBlock3dImpl::ResBlock3dImpl(int64_t channels, int64_t out_channels, const std::string& norm_type) {
  const bool group = norm_type == "group";
  norm1 = register_module("norm1", ChannelNorm32(channels, group));
  norm2 = register_module("norm2", ChannelNorm32(out_channels, group));
  conv1 = register_module("conv1", conv3d(channels, out_channels, 3));
  conv2 = register_module("conv2", conv3d(out_channels, out_channels, 3));
  if (channels != out_channels) skip_connection = register_module("skip_connection", conv3d(channels, out_channels, 1));
}

torch::Tensor ResBlock3dImpl::forward(const torch::Tensor& x) {
  // Pre-norm residual branch.
  auto h = conv1(torch::silu(norm1(x)));
  h = conv2(torch::silu(norm2(h)));
  // Skip path (identity when the width is unchanged).
  return h + (skip_connection ? skip_connection(x) : x);
}

// ---------------------------------------------------------------------------------------------
UpsampleBlock3dImpl::UpsampleBlock3dImpl(int64_t in_channels, int64_t out_channels) {
  conv = register_module("conv", conv3d(in_channels, out_channels * 8, 3));
}

torch::Tensor UpsampleBlock3dImpl::forward(const torch::Tensor& x) { return pixel_shuffle_3d(conv(x), 2); }

torch::Tensor pixel_shuffle_3d(const torch::Tensor& x, int64_t f) {
  SIMU_CHECK(x.dim() == 5, "pixel_shuffle_3d: expected [B, C, H, W, D], got {}", x.dim());
  const int64_t B = x.size(0), C = x.size(1), H = x.size(2), W = x.size(3), D = x.size(4);
  SIMU_CHECK(C % (f * f * f) == 0, "pixel_shuffle_3d: channels {} not divisible by {}^3", C, f);
  const int64_t Co = C / (f * f * f);
  // [B, Co, f, f, f, H, W, D] -> [B, Co, H, f, W, f, D, f] -> [B, Co, fH, fW, fD]
  return x.reshape({B, Co, f, f, f, H, W, D})
      .permute({0, 1, 5, 2, 6, 3, 7, 4})
      .reshape({B, Co, H * f, W * f, D * f});
}

// ---------------------------------------------------------------------------------------------
SparseStructureDecoderImpl::SparseStructureDecoderImpl(SSDecoderConfig config) : config_(std::move(config)) {
  const auto& ch = config_.channels;
  input_layer = register_module("input_layer", conv3d(config_.latent_channels, ch[0], 3));

  // Middle: residual blocks at the latent resolution. Residual blocks always use layer norm: the
  // official constructor builds ResBlock3d(ch, ch) without norm_type, which only reaches out_layer.
  middle_block = torch::nn::Sequential();
  for (int64_t i = 0; i < config_.num_res_blocks_middle; ++i) middle_block->push_back(ResBlock3d(ch[0], ch[0], "layer"));
  register_module("middle_block", middle_block);

  // Per level: residual blocks, then a x2 upsampling to the next level's width.
  blocks = torch::nn::ModuleList();
  for (size_t level = 0; level < ch.size(); ++level) {
    for (int64_t i = 0; i < config_.num_res_blocks; ++i) {
      ResBlock3d block(ch[level], ch[level], "layer");
      blocks->push_back(block);
      block_forward_.push_back([block](const torch::Tensor& h) mutable { return block->forward(h); });
    }
    if (level + 1 < ch.size()) {
      UpsampleBlock3d up(ch[level], ch[level + 1]);
      blocks->push_back(up);
      block_forward_.push_back([up](const torch::Tensor& h) mutable { return up->forward(h); });
    }
  }
  register_module("blocks", blocks);

  // Output head: norm, SiLU, conv to the output channels.
  out_layer = torch::nn::Sequential(ChannelNorm32(ch.back(), config_.norm_type == "group"), torch::nn::SiLU(),
                                    conv3d(ch.back(), config_.out_channels, 3));
  register_module("out_layer", out_layer);

  // Official use_fp16: the torso's parameters are float16.
  if (config_.use_fp16) {
    middle_block->to(torch::kFloat16);
    blocks->to(torch::kFloat16);
  }
}

torch::Tensor SparseStructureDecoderImpl::forward(const torch::Tensor& input) {
  auto x = config_.reshape_input_to_cube ? flat_to_cube(input) : input;
  SIMU_CHECK(x.dim() == 5 && x.size(1) == config_.latent_channels,
             "SparseStructureDecoder: expected input [B, {}, R, R, R], got {}", config_.latent_channels, x.sizes());
  // Input projection, then the torso in its own dtype (float16 when use_fp16).
  auto h = input_layer(x);
  if (config_.use_fp16) h = h.to(torch::kFloat16);
  h = middle_block->forward(h);
  for (auto& block : block_forward_) h = block(h);
  // Output head in the input's dtype.
  h = h.to(x.scalar_type());
  return out_layer->forward(h);
}

// ---------------------------------------------------------------------------------------------
SparseStructureDecoder load_ss_decoder(const std::string& config_path, const std::string& weights_path,
                                       torch::Device device) {
  SparseStructureDecoder decoder(SSDecoderConfig::load(config_path));
  if (!weights_path.empty()) {
    LoadOptions options;
    options.ignore_prefixes = {"io."};
    options.source = weights_path;
    load_safetensors_into(*decoder, weights_path, options);
  }
  decoder->to(device);
  decoder->eval();
  return decoder;
}

torch::Tensor flat_to_cube(const torch::Tensor& tokens) {
  SIMU_CHECK(tokens.dim() == 3, "flat_to_cube: expected tokens [B, T, C], got {}", tokens.sizes());
  const int64_t T = tokens.size(1);
  const auto k = static_cast<int64_t>(std::llround(std::cbrt(static_cast<double>(T))));
  SIMU_CHECK(k * k * k == T, "flat_to_cube: token count {} is not a cube", T);
  return tokens.reshape({tokens.size(0), k, k, k, tokens.size(2)}).permute({0, 4, 1, 2, 3});
}

torch::Tensor shape_tokens_to_grid(const torch::Tensor& tokens) {
  SIMU_CHECK(tokens.dim() == 3, "shape_tokens_to_grid: expected the shape latent [B, T, C], got {}", tokens.sizes());
  const int64_t B = tokens.size(0), T = tokens.size(1), C = tokens.size(2);
  const auto k = static_cast<int64_t>(std::llround(std::cbrt(static_cast<double>(T))));
  SIMU_CHECK(k * k * k == T, "shape_tokens_to_grid: token count {} is not a cube (expected e.g. 4096 = 16^3)", T);
  // [B, T, C] -> [B, C, T] -> [B, C, k, k, k]
  return tokens.permute({0, 2, 1}).contiguous().view({B, C, k, k, k});
}

torch::Tensor occupied_coords(const torch::Tensor& logits) {
  SIMU_CHECK(logits.dim() == 5 && logits.size(1) == 1, "occupied_coords: expected logits [B, 1, R, R, R], got {}",
             logits.sizes());
  // argwhere(logits > 0) -> [N, 5] (b, 0, x, y, z); keep columns 0, 2, 3, 4.
  auto idx = torch::nonzero(logits > 0);
  return idx.index_select(1, torch::tensor({0, 2, 3, 4}, torch::dtype(torch::kLong).device(idx.device())))
      .to(torch::kInt32);
}

}  // namespace simu::models
