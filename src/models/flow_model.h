// SAM 3D Objects Stage-1 flow model: the mixture-of-transformers DiT `SparseStructureFlowTdfyWrapper`.
//
// Port of sam3d_objects/model/backbone/tdfy_dit/models/mot_sparse_structure_flow.py and the modules it
// uses (TimestepEmbedder, MOTModulatedTransformerCrossBlock, MOTMultiHeadSelfAttention,
// MultiHeadAttention, MultiHeadRMSNorm, FeedForwardNet, LayerNorm32, mm_latent.Latent).
//
// Data flow (B = batch, C = model_channels):
//   latents {name: [B, tokens, in_ch]} --Latent.input_layer + pos_emb--> {name: [B, tokens, C]}
//   --latent_share_transformer merge (cat along tokens)--> transformer streams (e.g. "shape" and the
//   merged pose stream "6drotation_normalized") --num_blocks x MOT block--> split back per latent
//   --layer_norm + Latent.out_layer--> {name: [B, tokens, in_ch]} (the predicted velocity).
// Each block has per-stream weights (norms, qkv/out projections, cross attention, MLP) and one shared
// adaLN modulation from the timestep embedding. Self-attention: the protected stream ("shape")
// attends only to itself; every other stream attends to all streams, with the shape keys/values
// detached (no gradient into shape through pose).
//
// Module names reproduce the official state-dict keys after stripping "_base_models.generator." and
// "reverse_fn.backbone." (e.g. `blocks.0.self_attn.to_qkv.shape.weight`). Every linear projection is a
// simu::models::Linear (LoRA attaches there).
//
// Numerics: written so that the same ops run in fp32 on CPU (reference) and under CUDA bf16 autocast
// (see models::Autocast in precision.h): LayerNorms in fp32, the residual stream in fp32, projections in bf16,
// attention through at::scaled_dot_product_attention.
#pragma once

#include <torch/torch.h>
#include <yaml-cpp/yaml.h>

#include <functional>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "models/linear.h"

namespace simu::config {
class Reader;
}

namespace simu::models {

// Modality name -> tensor [B, tokens, channels].
using Latents = std::map<std::string, torch::Tensor>;

// One entry of `latent_mapping`: a latent modality with its input channels and position embedding.
struct LatentSpec {
  std::string name;
  int64_t in_channels = 0;
  // "shape": fixed 3-D sin/cos (ShapePositionEmbedder, a buffer); "learnt": a parameter
  // (LearntPositionEmbedder); "random": a fixed random buffer (RandomPositionEmbedder).
  std::string pos_embedder = "learnt";
  int64_t resolution = 0;  // shape only: grid side
  int64_t patch_size = 1;  // shape only
  int64_t token_len = 1;   // learnt / random only
  // Number of tokens of this latent: (resolution/patch_size)^3 or token_len.
  int64_t tokens() const;
};

struct FlowModelConfig {
  int64_t in_channels = 8;
  int64_t model_channels = 1024;
  int64_t cond_channels = 1024;
  int64_t out_channels = 8;
  int64_t num_blocks = 24;
  int64_t num_heads = 16;
  double mlp_ratio = 4.0;
  std::string pe_mode = "ape";  // only "ape" (the MOT model raises on rope)
  bool share_mod = false;
  bool qk_rms_norm = true;  // the MOT self-attention requires it (official raises otherwise)
  bool qk_rms_norm_cross = false;
  bool is_shortcut_model = false;  // has d_embedder (shortcut step size)
  bool force_zeros_cond = true;    // unconditional branch ("add_flag") multiplies the condition by 0
  std::vector<LatentSpec> latents;  // latent_mapping, in file order
  // latent_share_transformer: merged stream name -> the latents concatenated into it, in order.
  std::vector<std::pair<std::string, std::vector<std::string>>> share_groups;
  std::vector<std::string> protected_modalities = {"shape"};

  // Transformer stream names (official `latent_names`): latents not merged, then merged stream names.
  std::vector<std::string> stream_names() const;
  const LatentSpec& latent(const std::string& name) const;
  // The transformer stream a latent runs in: its own, or the share group it is merged into (throws for
  // an unknown latent).
  std::string stream_of(const std::string& latent_name) const;
  // Whether a stream is protected (attends only to itself, so never reads the other streams).
  bool is_protected(const std::string& stream) const;
  int64_t head_dim() const { return model_channels / num_heads; }
  // Throws simu::Error on an inconsistent config (heads not dividing channels, unknown merged names...).
  void validate(const std::string& where = "") const;

  // From the official YAML/JSON node `module.generator.backbone.reverse_fn.backbone` (the
  // SparseStructureFlowTdfyWrapper kwargs). Unknown training-only keys are ignored.
  static FlowModelConfig from_official(const YAML::Node& backbone, const std::string& file = "");
  // From the project layout (configs/*.yaml `flow_model:` section); strict keys.
  static FlowModelConfig from(config::Reader& r);
};

// Sinusoidal embedding of scalar times, then Linear-SiLU-Linear. t: [B] -> [B, C].
class TimestepEmbedderImpl : public torch::nn::Module {
 public:
  TimestepEmbedderImpl(int64_t hidden_size, int64_t frequency_embedding_size = 256);
  torch::Tensor forward(const torch::Tensor& t);
  // cos/sin features of t: [B] -> [B, dim] (first half cos, second half sin, max_period 10000).
  static torch::Tensor timestep_embedding(const torch::Tensor& t, int64_t dim, double max_period = 10000.0);
  torch::nn::Sequential mlp{nullptr};
  int64_t frequency_embedding_size;
};
TORCH_MODULE(TimestepEmbedder);

// LayerNorm computed in float32, output cast back to the input dtype (official LayerNorm32).
class LayerNorm32Impl : public torch::nn::Module {
 public:
  LayerNorm32Impl(int64_t channels, bool affine, double eps);
  torch::Tensor forward(const torch::Tensor& x);
  torch::Tensor weight, bias;  // [C] when affine
  int64_t channels;
  double eps;
};
TORCH_MODULE(LayerNorm32);

// Per-head RMS norm on q/k: normalize(x, dim=-1) * gamma * sqrt(dim). x: [B, L, H, D]; gamma [H, D].
class MultiHeadRMSNormImpl : public torch::nn::Module {
 public:
  MultiHeadRMSNormImpl(int64_t dim, int64_t heads);
  torch::Tensor forward(const torch::Tensor& x);
  torch::Tensor gamma;
  double scale;
};
TORCH_MODULE(MultiHeadRMSNorm);

// Linear - GELU(tanh) - Linear, hidden = channels * mlp_ratio. Keys mlp.0.*, mlp.2.*.
class FeedForwardNetImpl : public torch::nn::Module {
 public:
  FeedForwardNetImpl(int64_t channels, double mlp_ratio);
  torch::Tensor forward(const torch::Tensor& x);
  Linear fc1{nullptr}, fc2{nullptr};
  // fc1 + GELU in one matrix product: inference GELU_BIAS (fused_ops.h); with a graph or training kernels,
  // a frozen base's GELU_AUX_BIAS forward and DGELU backward (mlp_epilogue.h)
  bool fused_kernels = true;
  bool inference_kernels = true;  // false: never the inference-only GELU_BIAS epilogue, see set_training_kernels
};
TORCH_MODULE(FeedForwardNet);

// Cross attention of tokens over the condition tokens (official MultiHeadAttention, type "cross").
class CrossAttentionImpl : public torch::nn::Module {
 public:
  CrossAttentionImpl(int64_t channels, int64_t ctx_channels, int64_t num_heads, bool qk_rms_norm);
  // x: [B, L, C], context: [B, Lc, Cc] -> [B, L, C]. A context of fewer rows Bc (B = Bc * G) is shared:
  // row b*G + g attends over context row b (attend_shared; each context row's G token rows consecutive).
  torch::Tensor forward(const torch::Tensor& x, const torch::Tensor& context);
  // Keys (RMS-normed when enabled) and values of the context: [B, Lc, H, D] each; v (and k without the
  // norm) are strided views of to_kv's output (split with unbind: one stack in backward).
  std::pair<torch::Tensor, torch::Tensor> context_kv(const torch::Tensor& context);
  // Attention of x over precomputed keys/values, then to_out: [B, L, C].
  // k, v may hold fewer batch rows than x: the rows past them have an all-zero condition
  // (ConditionCache::zero_from) and get to_out(value bias), what attention over identical keys gives:
  // zero_out when given (CrossKV::zero_out, made once per sampling), else zero_condition_output. Where
  // to_out is a plain product in x's compute dtype (no adapter, no FP8), the attended rows' projection
  // writes straight into the output and only the zero rows are filled (no concatenation copy).
  torch::Tensor attend(const torch::Tensor& x, const torch::Tensor& k, const torch::Tensor& v,
                       const torch::Tensor& zero_out = {});
  // attend() in two parts, without building the [B, L, C] output: {the attended rows' output
  // [Bk, L, C] (the same product as attend's), the zero rows' output [1, 1, C] in its dtype, or
  // undefined when k, v cover every row}. The fused block feeds both to one residual kernel
  // (fused_ops.h residual_layer_norm_affine_tail_bf16).
  std::pair<torch::Tensor, torch::Tensor> attend_parts(const torch::Tensor& x, const torch::Tensor& k,
                                                       const torch::Tensor& v, const torch::Tensor& zero_out = {});
  // The cross-attention output of a token row whose condition is all zero, to_out(v(0)): [1, 1, C]
  // (computed on like's device, under the caller's autocast).
  torch::Tensor zero_condition_output(const torch::Tensor& like);
  // Attention of x ([Bc*G, L, C]) over keys/values of Bc condition rows ([Bc, Lc, H, D]), row b*G + g over
  // row b (pair-major: FM-DPO stacks x+_0, x-_0, x+_1, x-_1, ...): the G query sets of a condition run as
  // one [Bc, G*L] query sequence, a view of the queries (and the output a view back), so the condition's
  // projection (to_kv) runs once per condition row, not once per token row (FM-DPO's x+ and x- share
  // their pair's condition). Same values as attend() over the keys/values repeated G times per row
  // (repeat_interleave), up to the attention kernel's rounding. -> [Bc*G, L, C]
  torch::Tensor attend_shared(const torch::Tensor& x, const torch::Tensor& k, const torch::Tensor& v);
  Linear to_q{nullptr}, to_kv{nullptr}, to_out{nullptr};
  MultiHeadRMSNorm q_rms_norm{nullptr}, k_rms_norm{nullptr};
  int64_t num_heads;
  bool inference_kernels = true;  // the few-query flash kernel allowed (sdpa_blhd); see set_training_kernels

 private:
  // The attention of x's first k.size(0) rows over k, v, before to_out: [Bk, L, C].
  torch::Tensor attended(const torch::Tensor& x, const torch::Tensor& k, const torch::Tensor& v);
  // to_out of attended rows h [Bk, L, C] written into out ([Bk, L, C] rows, contiguous), when to_out is a
  // plain product in h's dtype (no adapter, no FP8, no gradient); false (nothing written) otherwise.
  bool project_plain_into(const torch::Tensor& h, torch::Tensor& out);
};
TORCH_MODULE(CrossAttention);

// Mixture-of-transformers self attention (official MOTMultiHeadSelfAttention, qk RMS norm on).
class MOTSelfAttentionImpl : public torch::nn::Module {
 public:
  MOTSelfAttentionImpl(int64_t channels, int64_t num_heads, const std::vector<std::string>& stream_names,
                       const std::vector<std::string>& protected_modalities);
  // x[i]: [B, L_i, C] for stream_names[i] -> same shapes.
  std::vector<torch::Tensor> forward(const std::vector<torch::Tensor>& x);
  // Fast path piece: stream i's qkv projection of x ([B, L, C], bf16 under autocast), split with the
  // q/k RMS norms into q ([B, L, H, D]) and the given key/value views (fused_ops.h split_qkv_rms_norm).
  void project_qkv_fused(size_t i, const torch::Tensor& x, torch::Tensor& q, torch::Tensor k, torch::Tensor v);
  std::vector<Linear> to_qkv, to_out;                      // per stream
  std::vector<MultiHeadRMSNorm> q_rms_norm, k_rms_norm;    // per stream
  std::vector<std::string> names;
  std::vector<bool> is_protected;
  int64_t num_heads;
  // Fused CUDA kernels for q/k RMS norm (fused_ops.h) when fused_path holds; the wrapper's
  // set_fused_kernels switches them. Without a graph and with inference_kernels, q/k/v are also written
  // straight into the attention's key/value layout (no backward); otherwise the differentiable split.
  bool fused_kernels = true;
  bool inference_kernels = true;

 private:
  std::vector<torch::Tensor> forward_fused(const std::vector<torch::Tensor>& x);
};
TORCH_MODULE(MOTSelfAttention);

// One block and stream's cached cross-attention inputs: the condition's keys and values [Bk, Lc, H, D]
// (rows [0, zero_from) of the condition), and with zero_from >= 0 the output every all-zero-condition
// row gets, zero_out = to_out(value bias) [1, 1, C] (CrossAttentionImpl::zero_condition_output).
struct CrossKV {
  torch::Tensor k, v, zero_out;
};

// Cross-attention keys/values of the condition for every block and stream, computed once and reused
// over the sampling steps (the condition is the same at every step). kv[block][stream].
struct ConditionCache {
  torch::Tensor cond;  // the condition they were computed from
  std::vector<std::vector<CrossKV>> kv;
  // >= 0: rows [zero_from, B) of cond are all zero (CFG's unconditional half with force_zeros_cond):
  // kv holds rows [0, zero_from) only, and cross attention gives those rows the value bias directly
  // (CrossAttentionImpl::attend: identical keys, uniform softmax), not an attention over L_c tokens.
  int64_t zero_from = -1;
};

// The wrapper's lagged two-stream schedule (SparseStructureFlowTdfyWrapperImpl::set_stream_lag); defined
// in flow_model.cpp.
struct StreamLag;

// One MOT block: adaLN-modulated self attention, cross attention, MLP; per-stream weights.
// The fused path's deferred residual between blocks: a block leaves its last gated residual
// (x + h * gate, the MLP's) to the next block, whose first LayerNorm kernel applies it on the way
// (fused_ops.h residual_layer_norm_affine_bf16); the wrapper applies what the last block leaves.
struct ResidualCarry {
  std::vector<torch::Tensor> h;  // per stream [B, L_i, C] (bf16); empty: nothing pending
  torch::Tensor gate;            // [1 or B, C]
  // x[i] + h[i] * gate for every stream (the plain addcmul), then empty.
  std::vector<torch::Tensor> apply(const std::vector<torch::Tensor>& x);
};

class MOTBlockImpl : public torch::nn::Module {
 public:
  explicit MOTBlockImpl(const FlowModelConfig& c);
  // x[i]: [B, L_i, C]; mod: [B or 1, C] the SiLU of the t embedding (adaLN_modulation's first step: the
  // wrapper applies it once for all blocks, this forward applies its Linear), or [B or 1, 6C] the shared
  // modulation when share_mod; cond: [B, Lc, Cc].
  // On the fused path the modulation's fp32 rows come from one kernel (fused_ops.h modulation_rows);
  // the reference path (block_reference) takes the same chunks through ATen.
  // kv: this block's precomputed condition keys/values per stream (ConditionCache), or null.
  // carry (optional): a pending residual from the previous block is applied first; on the fused path
  // this block's own last residual is left in it instead of applied (so the result is x minus that
  // residual; the caller applies carry at the end). Off the fused path the result is complete and
  // carry comes back empty.
  // lag (optional, the wrapper's): on the two-stream path the other stream's part runs on lag's side
  // stream and the main stream does not wait for it (the wrapper joins once after the last block); on
  // any other path a pending lag is joined first.
  std::vector<torch::Tensor> forward(const std::vector<torch::Tensor>& x, const torch::Tensor& mod,
                                     const torch::Tensor& cond,
                                     const std::vector<CrossKV>* kv = nullptr,
                                     ResidualCarry* carry = nullptr, StreamLag* lag = nullptr);
  std::vector<LayerNorm32> norm1, norm2, norm3;
  MOTSelfAttention self_attn{nullptr};
  std::vector<CrossAttention> cross_attn;
  std::vector<FeedForwardNet> mlp;
  torch::nn::Sequential adaLN_modulation{nullptr};  // SiLU, Linear(C, 6C); absent when share_mod (forward: see mod)
  Linear ada_linear{nullptr};
  bool share_mod;
  bool fused_kernels = true;  // fused LayerNorm + modulation (+ residual) -> bf16 (fused_ops.h) on the fused path
  bool inference_kernels = true;  // stream_overlap allowed (without a graph); see set_training_kernels
  // Fused path with one protected stream and one other: the other (the small pose stream) runs on a
  // second CUDA stream, concurrently with the protected one, joining at the end of the block (or once
  // per forward: the wrapper's set_stream_lag).
  // stream_overlap_cached: also with the condition's cached keys/values (sampling). Measured (H200,
  // bench_stage1 --precision fp16, 25 CFG steps, persistent graphs): 7,528 tokens 744.6 -> 723.1 ms,
  // 2,800 tokens 617.9 -> 596.3 ms; eager 751.4 -> 732.3 and 628.1 -> 607.0 ms.
  bool stream_overlap = true;
  bool stream_overlap_cached = true;
  // The other stream's few-query attention on the side stream: the flash kernel (true), which splits the
  // keys over thread blocks across the whole GPU, or PyTorch's choice (false, the default: cuDNN, one
  // thread block per head), which leaves the SMs to the protected stream's kernels running beside it.
  bool side_few_query_flash = false;
};
TORCH_MODULE(MOTBlock);

// One latent modality's input/output mapping (official mm_latent.Latent).
class LatentMappingImpl : public torch::nn::Module {
 public:
  LatentMappingImpl(const LatentSpec& spec, int64_t model_channels);
  // [B, T, in] -> [B, T, C]: input_layer(x) + pos_emb
  torch::Tensor to_input(const torch::Tensor& x);
  // [B, T, C] -> [B, T, in]: out_layer(layer_norm(h))
  torch::Tensor to_output(const torch::Tensor& h);
  Linear input_layer{nullptr}, out_layer{nullptr};
  torch::Tensor pos_emb;  // [T, C]
};
TORCH_MODULE(LatentMapping);

// 3-D sin/cos position embedding of a res^3 grid (official AbsolutePositionEmbedder over ij-meshgrid
// coordinates, zero padded to `channels`): [res^3, channels].
torch::Tensor shape_position_embedding(int64_t channels, int64_t resolution, int64_t patch_size);

// A transformer block as a function of its tensor inputs (the streams, then the modulation, then
// the condition) returning the streams. It keeps alive what it refers to, so it may be called again
// later (e.g. during backward).
using BlockFn = std::function<std::vector<torch::Tensor>(const std::vector<torch::Tensor>&)>;
// Runs block `index` (module `block`) on `inputs` through `fn`; must return what fn(inputs) returns.
// Lets callers wrap every block (e.g. activation checkpointing) without the model knowing why.
using BlockWrapper = std::function<std::vector<torch::Tensor>(int64_t index, torch::nn::Module& block,
                                                              const std::vector<torch::Tensor>& inputs,
                                                              const BlockFn& fn)>;

class SparseStructureFlowTdfyWrapperImpl : public torch::nn::Module {
 public:
  explicit SparseStructureFlowTdfyWrapperImpl(FlowModelConfig config);

  // x: one tensor per latent of the config [B, tokens, in_ch]; t: [B] (or [1]) in time_scale units
  // (t*1000); cond: [B, L, cond_channels], or [Bc, L, cond_channels] with B = Bc * G, condition row b
  // shared by the rows b*G + g (CrossAttentionImpl::attend_shared; without a cache); d: [B] shortcut
  // step in time_scale units, only for shortcut models (when given, its embedding is added, also for
  // d = 0). Returns the velocity per latent.
  // cache: condition keys/values from condition_cache(cond) for this same cond (skips the to_kv
  // projections); null computes them.
  Latents forward(const Latents& x, const torch::Tensor& t, const torch::Tensor& cond,
                  const c10::optional<torch::Tensor>& d = c10::nullopt, const ConditionCache* cache = nullptr);
  // Cross-attention keys/values of cond for every block (run under the same autocast as forward).
  // zero_from >= 0: the caller guarantees rows [zero_from, B) of cond are all zero (see ConditionCache).
  ConditionCache condition_cache(const torch::Tensor& cond, int64_t zero_from = -1);
  // The same keys/values written into an existing cache's tensors (same shapes; dst.cond is left as it
  // is): the buffers a CUDA graph reads stay where they are. One block's keys/values exist at a time.
  // (dst.zero_from applies as in condition_cache.)
  void condition_cache_into(const torch::Tensor& cond, ConditionCache& dst);

  const FlowModelConfig& config() const { return config_; }
  // Every transformer block of forward runs through wrapper (empty: blocks run directly).
  void set_block_wrapper(BlockWrapper wrapper) { block_wrapper_ = std::move(wrapper); }

  // Fused CUDA kernels (fused_ops.h) replace the plain ATen ops for the norms, modulation, residuals and
  // q/k RMS norm when fused_path() holds: CUDA and bf16 or fp16 autocast. On by default; the same results up to
  // 16-bit rounding order. With a graph (grad mode) only the kernels that have a backward run; without
  // one, also the inference-only ones (GELU epilogue, q/k/v into the key/value buffer, second stream).
  void set_fused_kernels(bool on);
  bool fused_kernels() const { return fused_kernels_; }
  // Training: only the differentiable fused kernels, with or without grad mode, so that a no-grad
  // forward (FM-DPO's reference pass) computes exactly what the graph forward (the policy) computes.
  void set_training_kernels(bool on);
  bool training_kernels() const { return training_kernels_; }
  // On the fused path, run the non-protected stream on a second CUDA stream (MOTBlockImpl::stream_overlap).
  void set_stream_overlap(bool on);
  // Overlap the two streams also when the condition's keys/values are cached (sampling); on by default.
  void set_stream_overlap_cached(bool on);
  // Lagged overlap: with the two streams overlapped, the other (pose) stream's part of every block runs
  // on one side CUDA stream that waits only for the protected (shape) stream's keys/values of that
  // block, and the main stream waits for the side stream once, after the last block, instead of at
  // the end of every block. The protected stream never reads the other, so the main stream runs the
  // whole shape stack without stopping. Same kernels on the same inputs: the same numbers
  // (tests/models/fused_ops_gpu.cpp). Costs the blocks' key/value buffers alive until the join.
  // On by default: with the side stream's few-query attention on PyTorch's kernel
  // (set_side_few_query_flash) and the zero rows broadcast, H100, 25 fp16 CFG steps with graphs,
  // 7,528 / 2,800 tokens 702-709 / 577-580 -> 695-696 / 571-574 ms (docs/lift.md; bench_stage1 --stream-lag).
  void set_stream_lag(bool on) { stream_lag_ = on; }
  bool stream_lag() const { return stream_lag_; }
  // The few-query attention kernel of the stream on the side stream (MOTBlockImpl::side_few_query_flash).
  void set_side_few_query_flash(bool on);
  // Latents later forwards must return (empty: all, the default). When they all live in leading
  // protected streams (shape: protected streams attend only to themselves, so they never read the
  // others), forward runs only those streams and returns only their latents; FM-DPO scores the shape
  // latent alone and so skips the pose stream (its blocks and its condition projections). Otherwise
  // every stream runs and forward returns the named latents. Unknown names throw.
  void set_output_latents(const std::vector<std::string>& names);

  TimestepEmbedder t_embedder{nullptr}, d_embedder{nullptr};
  torch::nn::Sequential adaLN_modulation{nullptr};  // share_mod only
  torch::nn::ModuleList blocks{nullptr};
  std::map<std::string, LatentMapping> latent_mapping;

 private:
  // Input projection per latent (+ position embedding), merged into the transformer streams, float32:
  // [B, L_i, C] per stream name; `dtype` gets the projections' own dtype (the output's).
  std::vector<torch::Tensor> input_streams(const Latents& x, at::ScalarType& dtype);
  // The streams split back into their latents and projected out: the velocity per latent.
  Latents output_latents(const std::vector<torch::Tensor>& h);
  FlowModelConfig config_;
  std::vector<std::string> streams_;
  std::vector<std::string> output_latents_;  // set_output_latents (empty: all)
  size_t streams_run_ = 0;                   // leading streams forward runs (set_output_latents)
  std::vector<MOTBlock> block_list_;
  BlockWrapper block_wrapper_;
  bool fused_kernels_ = true;
  bool training_kernels_ = false;
  bool stream_lag_ = true;
};
TORCH_MODULE(SparseStructureFlowTdfyWrapper);

// True when the fused kernels may replace the reference ops for activations like x: they were compiled
// in, x is on CUDA and CUDA autocast runs in bf16 or fp16. (The inference-only ones also need grad mode off.)
bool fused_path(const torch::Tensor& x);

// Scaled dot-product attention on [B, L, H, D] tensors (the official "sdpa" backend) -> [B, L, H, D].
// Few queries over many keys without a graph (few_query_flash: the pose stream's 4 tokens over the
// condition or all shape tokens, in sampling) run FlashAttention's kernel, which splits the keys over
// thread blocks; PyTorch's first choice there (cuDNN) runs one thread block per head (H100, fp16,
// 4 queries over 7,528 keys, 16 heads: 77 us cuDNN, 18 us flash; bench/few_query_attention.py).
// Everything else takes PyTorch's choice. Same attention, another kernel's rounding.
// few_query_ok = false (training mode, see set_training_kernels) always takes PyTorch's choice.
torch::Tensor sdpa_blhd(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v, bool few_query_ok = true);
// Whether sdpa_blhd takes the flash kernel for these inputs: CUDA, fp16 or bf16, no grad mode, at most
// 16 queries over at least 256 keys, head dim <= 256 and a multiple of 8.
bool few_query_flash(const torch::Tensor& q, const torch::Tensor& k);

// Matrix-product FLOPs of one forward (2 per multiply-add), counted analytically for the benchmark:
// per block and per stream of T tokens: self qkv 2*T*C*3C + out 2*T*C*C; self attention QK^T and PV
// 2*2*T*Tk*C (Tk = keys seen); cross q 2*T*C*C + kv 2*Lc*Cc*2C + out 2*T*C*C; cross attention
// 2*2*T*Lc*C; MLP 2*2*T*C*(C*mlp_ratio); plus adaLN and latent in/out layers. Times batch.
double flow_forward_flops(const FlowModelConfig& c, int64_t batch, int64_t cond_len);
// The part of flow_forward_flops spent on the condition key/value projections (2*Lc*Cc*2C per block
// and stream, times batch): what a ConditionCache saves per reuse.
double flow_condition_kv_flops(const FlowModelConfig& c, int64_t batch, int64_t cond_len);

}  // namespace simu::models
