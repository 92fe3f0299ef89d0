#include "models/ss_encoder.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "common/error.h"
#include "models/weights.h"

namespace simu::models {

namespace {
bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}
torch::nn::Conv3d conv3d(int64_t in, int64_t out, int64_t kernel) {
  return torch::nn::Conv3d(torch::nn::Conv3dOptions(in, out, kernel).padding(kernel / 2));
}
}  // namespace

SSEncoderConfig SSEncoderConfig::from(simu::config::Reader& r) {
  SSEncoderConfig c;
  // Official YAML extras: the class path (checked; the wrapper changes the forward defaults) and the
  // checkpoint path (the loader takes the weights separately).
  if (r.has("_target_")) {
    const auto target = r.require<std::string>("_target_");
    SIMU_CHECK(ends_with(target, "SparseStructureEncoder") || ends_with(target, "SparseStructureEncoderTdfyWrapper"),
               "{}: _target_ '{}' is not a SparseStructureEncoder", r.file(), target);
    if (ends_with(target, "TdfyWrapper")) c.sample_posterior = c.return_raw = true;
  }
  if (r.has("pretrained_ckpt_path")) r.raw("pretrained_ckpt_path");
  r.field("in_channels", c.in_channels);
  r.field("latent_channels", c.latent_channels);
  r.field("num_res_blocks", c.num_res_blocks);
  r.field("channels", c.channels);
  r.field("num_res_blocks_middle", c.num_res_blocks_middle);
  r.field("norm_type", c.norm_type);
  r.field("use_fp16", c.use_fp16);
  r.field("sample_posterior", c.sample_posterior);
  r.field("return_raw", c.return_raw);
  r.finish();
  // Sanity of the values, each error naming the file and key.
  SIMU_CHECK(!c.channels.empty(), "{}: 'channels' must list at least one level", r.file());
  for (auto ch : c.channels) SIMU_CHECK(ch > 0, "{}: 'channels' entries must be positive, got {}", r.file(), ch);
  SIMU_CHECK(c.norm_type == "layer" || c.norm_type == "group", "{}: norm_type must be 'layer' or 'group', got '{}'",
             r.file(), c.norm_type);
  SIMU_CHECK(c.norm_type != "group" || c.channels.back() % 32 == 0,
             "{}: norm_type 'group' (GroupNorm32, 32 groups) needs the last 'channels' entry divisible by 32, got {}",
             r.file(), c.channels.back());
  SIMU_CHECK(c.in_channels > 0 && c.latent_channels > 0 && c.num_res_blocks >= 0 && c.num_res_blocks_middle >= 0,
             "{}: channel counts must be positive and block counts non-negative", r.file());
  return c;
}

SSEncoderConfig SSEncoderConfig::load(const std::string& path, const std::vector<std::string>& overrides) {
  simu::config::Reader r(simu::config::load_file(path, overrides), path);
  return from(r);
}

// ---------------------------------------------------------------------------------------------
DownsampleBlock3dImpl::DownsampleBlock3dImpl(int64_t in_channels, int64_t out_channels) {
  conv = register_module("conv", torch::nn::Conv3d(torch::nn::Conv3dOptions(in_channels, out_channels, 2).stride(2)));
}

torch::Tensor DownsampleBlock3dImpl::forward(const torch::Tensor& x) { return conv(x); }

// ---------------------------------------------------------------------------------------------
SparseStructureEncoderImpl::SparseStructureEncoderImpl(SSEncoderConfig config) : config_(std::move(config)) {
  const auto& ch = config_.channels;
  input_layer = register_module("input_layer", conv3d(config_.in_channels, ch[0], 3));

  // Per level: residual blocks (layer norm, as the official ResBlock3d default), then a /2 down-sampling
  // to the next level's width.
  blocks = torch::nn::ModuleList();
  for (size_t level = 0; level < ch.size(); ++level) {
    for (int64_t i = 0; i < config_.num_res_blocks; ++i) {
      ResBlock3d block(ch[level], ch[level], "layer");
      blocks->push_back(block);
      block_forward_.push_back([block](const torch::Tensor& h) mutable { return block->forward(h); });
    }
    if (level + 1 < ch.size()) {
      DownsampleBlock3d down(ch[level], ch[level + 1]);
      blocks->push_back(down);
      block_forward_.push_back([down](const torch::Tensor& h) mutable { return down->forward(h); });
    }
  }
  register_module("blocks", blocks);

  // Middle: residual blocks at the latent resolution.
  middle_block = torch::nn::Sequential();
  for (int64_t i = 0; i < config_.num_res_blocks_middle; ++i) middle_block->push_back(ResBlock3d(ch.back(), ch.back(), "layer"));
  register_module("middle_block", middle_block);

  // Output head: norm of norm_type, SiLU, conv to mean and logvar channels.
  out_layer = torch::nn::Sequential(ChannelNorm32(ch.back(), config_.norm_type == "group"), torch::nn::SiLU(),
                                    conv3d(ch.back(), 2 * config_.latent_channels, 3));
  register_module("out_layer", out_layer);

  // Official use_fp16: the torso's parameters are float16.
  if (config_.use_fp16) {
    blocks->to(torch::kFloat16);
    middle_block->to(torch::kFloat16);
  }
}

std::pair<torch::Tensor, torch::Tensor> SparseStructureEncoderImpl::posterior(const torch::Tensor& input) {
  SIMU_CHECK(input.dim() == 5 && input.size(1) == config_.in_channels,
             "SparseStructureEncoder: expected input [B, {}, R, R, R], got {}", config_.in_channels, input.sizes());
  const int64_t f = config_.downsample_factor();
  for (int64_t d = 2; d < 5; ++d)
    SIMU_CHECK(input.size(d) % f == 0, "SparseStructureEncoder: grid size {} is not divisible by the down-sampling factor {}",
               input.size(d), f);
  // Input projection in float32, then the torso in its own dtype (float16 when use_fp16).
  const auto x = input.to(torch::kFloat32);
  auto h = input_layer(x);
  if (config_.use_fp16) h = h.to(torch::kFloat16);
  for (auto& block : block_forward_) h = block(h);
  h = middle_block->forward(h);
  // Output head in float32; mean and logvar are the two halves of its channels.
  h = out_layer->forward(h.to(torch::kFloat32));
  auto halves = h.to(torch::kFloat32).chunk(2, 1);  // 2 x [B, latent, r, r, r]
  return {halves[0], halves[1]};
}

SSEncoderOutput SparseStructureEncoderImpl::forward(const torch::Tensor& x, bool sample,
                                                    const std::optional<torch::Tensor>& noise) {
  SSEncoderOutput out;
  std::tie(out.mean, out.logvar) = posterior(x);
  if (!sample) {
    out.z = out.mean;
    return out;
  }
  // The reparameterised sample; without a given noise, a draw as the official randn_like(std).
  if (noise) {
    SIMU_CHECK(noise->sizes() == out.mean.sizes(), "SparseStructureEncoder: noise {} does not match the latent {}",
               noise->sizes(), out.mean.sizes());
    out.z = sample_posterior(out.mean, out.logvar, noise->to(out.mean.device(), out.mean.scalar_type()));
  } else {
    out.z = sample_posterior(out.mean, out.logvar, torch::randn_like(out.mean));
  }
  return out;
}

SSEncoderOutput SparseStructureEncoderImpl::encode(const torch::Tensor& x) {
  auto out = forward(x, config_.sample_posterior);
  if (!config_.return_raw) out.mean = out.logvar = torch::Tensor();
  return out;
}

// ---------------------------------------------------------------------------------------------
SparseStructureEncoder load_ss_encoder(const std::string& config_path, const std::string& weights_path,
                                       torch::Device device) {
  SparseStructureEncoder encoder(SSEncoderConfig::load(config_path));
  if (!weights_path.empty()) {
    LoadOptions options;
    options.ignore_prefixes = {"io."};
    options.source = weights_path;
    load_safetensors_into(*encoder, weights_path, options);
  }
  encoder->to(device);
  encoder->eval();
  return encoder;
}

torch::Tensor sample_posterior(const torch::Tensor& mean, const torch::Tensor& logvar, const torch::Tensor& noise) {
  return mean + torch::exp(0.5 * logvar) * noise;
}

torch::Tensor kl_to_standard_normal(const torch::Tensor& mean, const torch::Tensor& logvar) {
  return 0.5 * (mean.pow(2) + logvar.exp() - logvar - 1);
}

}  // namespace simu::models
