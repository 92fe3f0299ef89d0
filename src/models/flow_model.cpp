// SparseStructureFlowTdfyWrapper (flow_model.h): the MOT block, the latent mappings and the wrapper's
// forward and condition cache. Configuration and FLOP counts: flow_config.cpp; layers: flow_layers.cpp.
#include "models/flow_model.h"

#include <ATen/autocast_mode.h>
#include <fmt/ranges.h>

#include <cmath>

#include "common/error.h"
#include "models/flow_model_internal.h"
#include "models/fused_ops.h"

#ifdef SIMU_HAVE_CUDA_KERNELS
#include <ATen/cuda/CUDAEvent.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#endif

namespace simu::models {

using detail::attention;
using detail::inference_only_ok;
using detail::register_dict;

MOTBlockImpl::MOTBlockImpl(const FlowModelConfig& c) : share_mod(c.share_mod) {
  const auto names = c.stream_names();
  const int64_t C = c.model_channels;
  for (size_t i = 0; i < names.size(); ++i) {
    norm1.push_back(LayerNorm32(C, false, 1e-6));
    norm2.push_back(LayerNorm32(C, true, 1e-6));
    norm3.push_back(LayerNorm32(C, false, 1e-6));
    cross_attn.push_back(CrossAttention(C, c.cond_channels, c.num_heads, c.qk_rms_norm_cross));
    mlp.push_back(FeedForwardNet(C, c.mlp_ratio));
  }
  register_dict(*this, "norm1", names, norm1);
  register_dict(*this, "norm2", names, norm2);
  register_dict(*this, "norm3", names, norm3);
  self_attn = register_module("self_attn", MOTSelfAttention(C, c.num_heads, names, c.protected_modalities));
  register_dict(*this, "cross_attn", names, cross_attn);
  register_dict(*this, "mlp", names, mlp);
  if (!share_mod) {
    ada_linear = Linear(C, 6 * C);
    adaLN_modulation = register_module("adaLN_modulation", torch::nn::Sequential(torch::nn::SiLU(), ada_linear));
  }
}

std::vector<torch::Tensor> ResidualCarry::apply(const std::vector<torch::Tensor>& x) {
  if (h.empty()) return x;
  std::vector<torch::Tensor> out(x.size());
  for (size_t i = 0; i < x.size(); ++i) out[i] = torch::addcmul(x[i], h[i], gate.unsqueeze(1));
  h.clear();
  gate = torch::Tensor();
  return out;
}

// The lagged two-stream schedule of one wrapper forward: one side stream for every block's other
// stream, and the main-stream tensors the side stream reads, kept alive (so the caching allocator
// cannot hand their memory to later main-stream work) until join().
struct StreamLag {
#ifdef SIMU_HAVE_CUDA_KERNELS
  c10::optional<c10::cuda::CUDAStream> side;
#endif
  std::vector<torch::Tensor> keep;
  bool pending = false;
  // The current (main) stream waits for everything issued on the side stream so far.
  void join() {
#ifdef SIMU_HAVE_CUDA_KERNELS
    if (pending) {
      at::cuda::CUDAEvent done;
      done.record(*side);
      done.block(c10::cuda::getCurrentCUDAStream(side->device_index()));
    }
#endif
    pending = false;
    keep.clear();
  }
};

namespace {

using BlockKV = std::vector<CrossKV>;
using Affine = std::pair<torch::Tensor, torch::Tensor>;  // fp32 LayerNorm weight and bias rows [1 or B, C]

// The reference path of one block: x (a pending residual already applied) -> x after self attention on
// the modulated norm1, cross attention on the affine norm2 and the MLP on the modulated norm3, each
// with its (gated) residual. mod: the six [1 or B, 1, C] modulation chunks.
std::vector<torch::Tensor> block_reference(MOTBlockImpl& b, std::vector<torch::Tensor> x, const std::vector<torch::Tensor>& mod,
                                           const torch::Tensor& cond, const BlockKV* kv) {
  const auto &shift_msa = mod[0], &scale_msa = mod[1], &gate_msa = mod[2];
  const auto &shift_mlp = mod[3], &scale_mlp = mod[4], &gate_mlp = mod[5];
  const size_t S = x.size();
  // norm(x) * (1 + scale) + shift. When the modulation is one row (the same t for the whole batch,
  // as in sampling) it is a LayerNorm with weight 1 + scale and bias shift: one fused fp32 kernel.
  const bool one_row = shift_msa.size(0) == 1;
  auto modulate = [&](LayerNorm32& norm, const torch::Tensor& xi, const torch::Tensor& scale, const torch::Tensor& shift) {
    if (one_row) {
      auto w = (1 + scale).reshape({-1}).to(torch::kFloat32), bias = shift.reshape({-1}).to(torch::kFloat32);
      return at::layer_norm(xi.to(torch::kFloat32), {xi.size(-1)}, w, bias, norm->eps).to(xi.scalar_type());
    }
    return norm->forward(xi) * (1 + scale) + shift;
  };
  // Self attention on the modulated norm1; gated residual x + h * gate.
  std::vector<torch::Tensor> h(S);
  for (size_t i = 0; i < S; ++i) h[i] = modulate(b.norm1[i], x[i], scale_msa, shift_msa);
  h = b.self_attn->forward(h);
  for (size_t i = 0; i < S; ++i) x[i] = torch::addcmul(x[i], h[i], gate_msa);
  // Cross attention over the condition on the affine norm2 (no modulation).
  for (size_t i = 0; i < S; ++i) {
    auto hi = b.norm2[i]->forward(x[i]);
    auto& ca = b.cross_attn[i];
    x[i] = x[i] + (kv ? ca->attend(hi, (*kv)[i].k, (*kv)[i].v, (*kv)[i].zero_out) : ca->forward(hi, cond));
  }
  // MLP on the modulated norm3; gated residual.
  for (size_t i = 0; i < S; ++i)
    x[i] = torch::addcmul(x[i], b.mlp[i]->forward(modulate(b.norm3[i], x[i], scale_mlp, shift_mlp)), gate_mlp);
  return x;
}

// The fused path's per-stream steps of one block (fused_ops.h kernels that store the autocast dtype):
// they share the block's modulation (as LayerNorm affine rows), the previous block's pending residual
// and, when `leave_residual`, leave the MLP's gated residual in mlp_out for the caller's carry.
struct FusedBlock {
  MOTBlockImpl& b;
  const torch::Tensor& cond;
  const BlockKV* kv;
  const ResidualCarry& incoming;
  bool leave_residual;
  Affine msa, mlp;               // norm1 / norm3: weight 1 + scale, bias shift
  torch::Tensor gate_a, gate_m;  // [1 or B, C]
  at::ScalarType low;            // the 16-bit type stored (bf16 in training, fp16 as released)
  std::vector<torch::Tensor> mlp_out;

  // Residual update and the next LayerNorm in one kernel when the sublayer output allows it:
  // {x + h * gate (or x + h), LayerNorm(that) with w, b}.
  std::pair<torch::Tensor, torch::Tensor> residual_norm(const torch::Tensor& xi, const torch::Tensor& hi,
                                                        const torch::Tensor& gate, const torch::Tensor& w,
                                                        const torch::Tensor& bias, double eps) const {
    if (fused::supports_residual_layer_norm_affine(xi, hi)) return fused::residual_layer_norm_affine_bf16(xi, hi, gate, w, bias, eps);
    auto xn = gate.defined() ? torch::addcmul(xi, hi, gate.unsqueeze(1)) : xi + hi;
    return std::make_pair(xn, fused::layer_norm_affine_bf16(xn, w, bias, eps, low));
  }
  // Stream i's norm1, with the previous block's pending residual when there is one: {x, norm1(x)}.
  std::pair<torch::Tensor, torch::Tensor> norm1_of(size_t i, const torch::Tensor& xi) const {
    if (!incoming.h.empty()) return residual_norm(xi, incoming.h[i], incoming.gate, msa.first, msa.second, b.norm1[i]->eps);
    return std::make_pair(xi, fused::layer_norm_affine_bf16(xi, msa.first, msa.second, b.norm1[i]->eps, low));
  }
  // Stream i after self attention (ha): gated residual + norm2 -> cross attention -> residual +
  // modulated norm3 -> MLP; the MLP's gated residual is left to the carry when leave_residual.
  torch::Tensor rest_of(size_t i, const torch::Tensor& xi, const torch::Tensor& ha) {
    const auto& n2w = b.norm2[i];
    auto [xa, n2] = residual_norm(xi, ha, gate_a, n2w->weight.unsqueeze(0), n2w->bias.unsqueeze(0), n2w->eps);
    auto& ca = b.cross_attn[i];
    // CFG's zero-condition rows (cached keys/values for fewer rows, sampling): their output is one row,
    // read by the residual kernel as a broadcast instead of being copied into every row.
    if (kv && (*kv)[i].k.size(0) < n2.size(0) && !at::GradMode::is_enabled()) {
      auto [head, tail] = ca->attend_parts(n2, (*kv)[i].k, (*kv)[i].v, (*kv)[i].zero_out);
      if (fused::supports_residual_layer_norm_affine_tail(xa, head, tail)) {
        auto [xb, n3] = fused::residual_layer_norm_affine_tail_bf16(xa, head, tail, torch::Tensor(), mlp.first, mlp.second,
                                                                     b.norm3[i]->eps);
        return mlp_rest(i, xb, n3);
      }
      const int64_t rest = n2.size(0) - head.size(0);
      auto c = torch::cat({head, tail.expand({rest, head.size(1), tail.size(2)})}, 0);  // [B, L, C]
      auto [xb, n3] = residual_norm(xa, c, torch::Tensor(), mlp.first, mlp.second, b.norm3[i]->eps);
      return mlp_rest(i, xb, n3);
    }
    auto c = kv ? ca->attend(n2, (*kv)[i].k, (*kv)[i].v, (*kv)[i].zero_out) : ca->forward(n2, cond);
    auto [xb, n3] = residual_norm(xa, c, torch::Tensor(), mlp.first, mlp.second, b.norm3[i]->eps);
    return mlp_rest(i, xb, n3);
  }
  // Stream i's MLP on n3 after the cross attention's residual (xb); its gated residual left to the carry
  // when leave_residual.
  torch::Tensor mlp_rest(size_t i, const torch::Tensor& xb, const torch::Tensor& n3) {
    mlp_out[i] = b.mlp[i]->forward(n3);
    return leave_residual ? xb : torch::addcmul(xb, mlp_out[i], gate_m.unsqueeze(1));
  }
};

#ifdef SIMU_HAVE_CUDA_KERNELS
// The fused path with one protected stream (shape, on the current CUDA stream) and one other (pose, on
// a side stream), joined at the end of the block; with `lag`, on lag's side stream and not joined
// (StreamLag). x: the block's input streams.
std::vector<torch::Tensor> block_two_streams(FusedBlock& fb, std::vector<torch::Tensor> x, int64_t head_dim,
                                             StreamLag* lag) {
  auto& sa = fb.b.self_attn;
  const size_t p = sa->is_protected[0] ? 0 : 1, o = 1 - p;
  const int64_t B = x[p].size(0), Lp = x[p].size(1), Lo = x[o].size(1), H = sa->num_heads;
  const auto dev = x[p].device().index();
  const auto main = c10::cuda::getCurrentCUDAStream(dev);
  if (lag && !lag->side) lag->side = c10::cuda::getStreamFromPool(false, dev);
  const auto side = lag ? *lag->side : c10::cuda::getStreamFromPool(false, dev);
  const auto x_other_in = x[o];
  // The side stream starts after everything issued so far (inputs, modulation).
  at::cuda::CUDAEvent inputs_ready, shape_kv_ready, other_done;
  inputs_ready.record(main);
  inputs_ready.block(side);
  // Keys/values of both streams, the other's first (the reference's concatenation order).
  auto k_all = torch::empty({B, Lo + Lp, H, head_dim}, x[p].options().dtype(fb.low));
  auto v_all = torch::empty_like(k_all);
  // Protected stream: norm1, q/k/v (its keys into k_all), then the other stream may attend.
  auto [xp, n1p] = fb.norm1_of(p, x[p]);
  torch::Tensor qp;
  sa->project_qkv_fused(p, n1p, qp, k_all.narrow(1, Lo, Lp), v_all.narrow(1, Lo, Lp));
  shape_kv_ready.record(main);
  torch::Tensor xo_out;
  {
    // Other stream on the side stream: attends to every key once the protected ones are written.
    const c10::cuda::CUDAStreamGuard on_side(side);
    const detail::FewQueryFlashOff few_query(!fb.b.side_few_query_flash);
    auto [xo, n1o] = fb.norm1_of(o, x[o]);
    torch::Tensor qo;
    sa->project_qkv_fused(o, n1o, qo, k_all.narrow(1, 0, Lo), v_all.narrow(1, 0, Lo));
    shape_kv_ready.block(side);
    auto ho = sa->to_out[o]->forward(attention(qo, k_all, v_all, true).reshape({B, Lo, -1}));
    xo_out = fb.rest_of(o, xo, ho);
    other_done.record(side);
  }
  // Protected stream attends to itself only.
  auto hp = sa->to_out[p]->forward(attention(qp, k_all.narrow(1, Lo, Lp), v_all.narrow(1, Lo, Lp), true).reshape({B, Lp, -1}));
  x[p] = fb.rest_of(p, xp, hp);
  x[o] = xo_out;
  if (lag) {
    // No join: what the side stream reads stays referenced until the wrapper's join (the side
    // stream's own tensors are reused only by its later work, in its order).
    for (const auto& t : {k_all, v_all, x_other_in, fb.msa.first, fb.msa.second, fb.mlp.first, fb.mlp.second, fb.gate_a,
                          fb.gate_m, fb.incoming.gate})
      if (t.defined()) lag->keep.push_back(t);
    if (!fb.incoming.h.empty()) lag->keep.push_back(fb.incoming.h[o]);
    lag->pending = true;
    return x;
  }
  // Join. Tensors the side stream used stay referenced until here, so their memory is not reused
  // by work that could run before the side stream is done.
  other_done.block(main);
  return x;
}
#endif

}  // namespace

std::vector<torch::Tensor> MOTBlockImpl::forward(const std::vector<torch::Tensor>& x_in, const torch::Tensor& mod,
                                                 const torch::Tensor& cond, const BlockKV* kv, ResidualCarry* carry,
                                                 StreamLag* lag) {
  // Modulation [B or 1, 6C]: shift/scale/gate for attention and MLP (mod is already the SiLU of the t
  // embedding, the first half of adaLN_modulation).
  auto m = share_mod ? mod : ada_linear->forward(mod);
  const size_t S = x_in.size();
  // A pending residual from the previous block: kept for the fused LayerNorm below, else applied now.
  ResidualCarry incoming;
  if (carry) std::swap(incoming, *carry);
  // Fast path: LayerNorm + modulation (or norm2's affine) in one kernel that stores bf16 for the next
  // projection (fused_ops.h); same fp32 arithmetic, one rounding.
  bool fast = fused_kernels && fused_path(x_in[0]) && (m.size(0) == 1 || m.size(0) == x_in[0].size(0));
  for (const auto& xi : x_in) fast = fast && fused::supports_layer_norm_affine(xi);
  if (!fast) {
    // Six [B or 1, 1, C] chunks.
    std::vector<torch::Tensor> chunks;
    for (const auto& c : m.chunk(6, 1)) chunks.push_back(c.unsqueeze(1));
    if (lag) lag->join();
    return block_reference(*this, incoming.apply(x_in), chunks, cond, kv);
  }
  // The streams share the modulation: its fp32 rows [6, 1 or B, C] (norm1/norm3 weight 1 + scale and
  // bias shift, the gates) made once per block, in one kernel (fused_ops.h modulation_rows; the same
  // values as (1 + scale).to(float32) and shift.to(float32) on the chunks).
  const auto rows = fused::modulation_rows(m);
  FusedBlock fb{*this, cond, kv, incoming, carry != nullptr, Affine{rows[1], rows[0]}, Affine{rows[4], rows[3]},
                rows[2], rows[5], at::autocast::get_autocast_dtype(at::kCUDA), std::vector<torch::Tensor>(S)};
  std::vector<torch::Tensor> x = x_in, h(S);
  const int64_t head_dim = x[0].size(2) / self_attn->num_heads;
  const bool qkv_fused = self_attn->fused_kernels && (head_dim == 64 || head_dim == 128 || head_dim == 256);
#ifdef SIMU_HAVE_CUDA_KERNELS
  // With cached keys/values (sampling) only when stream_overlap_cached (default on; an earlier H100
  // measurement had one stream faster there, 713 vs 752 ms at 2,800 tokens; this tree measures the
  // overlap faster on an H200: flow_model.h).
  if (stream_overlap && inference_only_ok(inference_kernels) && (!kv || stream_overlap_cached) && qkv_fused && S == 2 &&
      self_attn->is_protected[0] != self_attn->is_protected[1]) {
    x = block_two_streams(fb, x, head_dim, lag);
    if (carry) *carry = ResidualCarry{fb.mlp_out, fb.gate_m};
    return x;
  }
#endif
  if (lag) lag->join();
  // Self attention on the modulated norm1 (all streams together).
  for (size_t i = 0; i < S; ++i) std::tie(x[i], h[i]) = fb.norm1_of(i, x[i]);
  h = self_attn->forward(h);
  for (size_t i = 0; i < S; ++i) x[i] = fb.rest_of(i, x[i], h[i]);
  if (carry) *carry = ResidualCarry{fb.mlp_out, fb.gate_m};
  return x;
}

torch::Tensor shape_position_embedding(int64_t channels, int64_t resolution, int64_t patch_size) {
  const int64_t side = resolution / patch_size;
  const int64_t freq_dim = channels / 3 / 2;
  // freqs = 1 / 10000^(arange(freq_dim)/freq_dim)
  auto freqs = 1.0 / torch::pow(10000.0, torch::arange(freq_dim, torch::kFloat32) / static_cast<double>(freq_dim));
  auto r = torch::arange(side, torch::kFloat32);
  auto grids = torch::meshgrid({r, r, r}, "ij");
  auto coords = torch::stack({grids[0], grids[1], grids[2]}, -1).reshape({-1, 3});  // [N, 3]
  const int64_t N = coords.size(0);
  auto out = torch::outer(coords.reshape({-1}), freqs);               // [N*3, freq_dim]
  auto emb = torch::cat({torch::sin(out), torch::cos(out)}, -1).reshape({N, -1});  // [N, 6*freq_dim]
  if (emb.size(1) < channels) emb = torch::cat({emb, torch::zeros({N, channels - emb.size(1)})}, -1);
  return emb;
}

LatentMappingImpl::LatentMappingImpl(const LatentSpec& s, int64_t C) {
  input_layer = register_module("input_layer", Linear(s.in_channels, C));
  out_layer = register_module("out_layer", Linear(C, s.in_channels));
  if (s.pos_embedder == "shape")
    pos_emb = register_buffer("pos_emb", shape_position_embedding(C, s.resolution, s.patch_size));
  else if (s.pos_embedder == "learnt")
    pos_emb = register_parameter("pos_emb", torch::randn({s.token_len, C}));
  else
    pos_emb = register_buffer("pos_emb", torch::randn({s.token_len, C}));
}

torch::Tensor LatentMappingImpl::to_input(const torch::Tensor& x) { return input_layer->forward(x) + pos_emb.unsqueeze(0); }

torch::Tensor LatentMappingImpl::to_output(const torch::Tensor& h) {
  auto n = at::layer_norm(h, {h.size(-1)});  // no affine, eps 1e-5 (F.layer_norm default)
  return out_layer->forward(n);
}

SparseStructureFlowTdfyWrapperImpl::SparseStructureFlowTdfyWrapperImpl(FlowModelConfig c) : config_(std::move(c)) {
  config_.validate();
  streams_ = config_.stream_names();
  streams_run_ = streams_.size();
  const int64_t C = config_.model_channels;
  if (config_.is_shortcut_model) d_embedder = register_module("d_embedder", TimestepEmbedder(C));
  t_embedder = register_module("t_embedder", TimestepEmbedder(C));
  if (config_.share_mod)
    adaLN_modulation = register_module("adaLN_modulation", torch::nn::Sequential(torch::nn::SiLU(), Linear(C, 6 * C)));
  blocks = register_module("blocks", torch::nn::ModuleList());
  for (int64_t i = 0; i < config_.num_blocks; ++i) {
    block_list_.push_back(MOTBlock(config_));
    blocks->push_back(block_list_.back());
  }
  std::vector<std::string> names;
  std::vector<LatentMapping> maps;
  for (const auto& s : config_.latents) {
    names.push_back(s.name);
    maps.push_back(LatentMapping(s, C));
    latent_mapping.emplace(s.name, maps.back());
  }
  register_dict(*this, "latent_mapping", names, maps);
}

void SparseStructureFlowTdfyWrapperImpl::set_fused_kernels(bool on) {
  fused_kernels_ = on;
  for (auto& block : block_list_) {
    block->fused_kernels = on;
    block->self_attn->fused_kernels = on;
    for (auto& m : block->mlp) m->fused_kernels = on;
  }
}

void SparseStructureFlowTdfyWrapperImpl::set_training_kernels(bool on) {
  training_kernels_ = on;
  for (auto& block : block_list_) {
    block->inference_kernels = !on;
    block->self_attn->inference_kernels = !on;
    for (auto& ca : block->cross_attn) ca->inference_kernels = !on;
    for (auto& m : block->mlp) m->inference_kernels = !on;
  }
}

void SparseStructureFlowTdfyWrapperImpl::set_stream_overlap(bool on) {
  for (auto& block : block_list_) block->stream_overlap = on;
}

void SparseStructureFlowTdfyWrapperImpl::set_side_few_query_flash(bool on) {
  for (auto& block : block_list_) block->side_few_query_flash = on;
}

void SparseStructureFlowTdfyWrapperImpl::set_stream_overlap_cached(bool on) {
  for (auto& block : block_list_) block->stream_overlap_cached = on;
}

void SparseStructureFlowTdfyWrapperImpl::set_output_latents(const std::vector<std::string>& names) {
  // The stream holding each named latent (its own, or the share group it is merged into).
  size_t last = 0;
  for (const auto& n : names) {
    const auto it = std::find(streams_.begin(), streams_.end(), config_.stream_of(n));  // throws for unknown n
    last = std::max(last, static_cast<size_t>(it - streams_.begin()) + 1);
  }
  // Only leading protected streams may run alone (they attend to themselves only).
  bool alone = !names.empty();
  for (size_t i = 0; i < last; ++i) alone = alone && config_.is_protected(streams_[i]);
  output_latents_ = names;
  streams_run_ = alone ? last : streams_.size();
}

ConditionCache SparseStructureFlowTdfyWrapperImpl::condition_cache(const torch::Tensor& cond, int64_t zero_from) {
  SIMU_CHECK(zero_from < 0 || (zero_from > 0 && zero_from <= cond.size(0)),
             "condition_cache: zero_from {} must be in [1, {}] (or negative: none)", zero_from, cond.size(0));
  ConditionCache cache;
  cache.cond = cond;
  cache.zero_from = zero_from;
  auto cond32 = (zero_from >= 0 ? cond.narrow(0, 0, zero_from) : cond).to(torch::kFloat32);
  for (auto& block : block_list_) {
    std::vector<CrossKV> per_stream;
    for (auto& ca : block->cross_attn) {
      auto [k, v] = ca->context_kv(cond32);
      per_stream.push_back(CrossKV{k, v, zero_from >= 0 ? ca->zero_condition_output(cond32) : torch::Tensor()});
    }
    cache.kv.push_back(std::move(per_stream));
  }
  return cache;
}

void SparseStructureFlowTdfyWrapperImpl::condition_cache_into(const torch::Tensor& cond, ConditionCache& dst) {
  SIMU_CHECK(dst.kv.size() == block_list_.size(), "condition_cache_into: the cache has {} blocks, the model {}", dst.kv.size(),
             block_list_.size());
  auto cond32 = (dst.zero_from >= 0 ? cond.narrow(0, 0, dst.zero_from) : cond).to(torch::kFloat32);
  for (size_t b = 0; b < block_list_.size(); ++b) {
    auto& per_stream = dst.kv[b];
    SIMU_CHECK(per_stream.size() == block_list_[b]->cross_attn.size(), "condition_cache_into: stream count differs");
    for (size_t i = 0; i < per_stream.size(); ++i) {
      auto& ca = block_list_[b]->cross_attn[i];
      auto [k, v] = ca->context_kv(cond32);
      SIMU_CHECK(k.sizes() == per_stream[i].k.sizes() && v.sizes() == per_stream[i].v.sizes(),
                 "condition_cache_into: keys [{}] do not fit the cache's [{}]", fmt::join(k.sizes(), ", "),
                 fmt::join(per_stream[i].k.sizes(), ", "));
      per_stream[i].k.copy_(k);
      per_stream[i].v.copy_(v);
      // The zero rows' output depends on the weights only; made again, as the weights may have changed.
      if (per_stream[i].zero_out.defined()) per_stream[i].zero_out.copy_(ca->zero_condition_output(cond32));
    }
  }
}

Latents SparseStructureFlowTdfyWrapperImpl::forward(const Latents& x, const torch::Tensor& t, const torch::Tensor& cond,
                                                    const c10::optional<torch::Tensor>& d, const ConditionCache* cache) {
  SIMU_CHECK(!cache || (cache->cond.is_same(cond) && cache->kv.size() == block_list_.size()),
             "flow model: the condition cache was computed for another condition tensor");
  const auto& c = config_;
  SIMU_CHECK(cond.dim() == 3 && cond.size(2) == c.cond_channels, "flow model: cond must be [B, L, {}], got [{}]",
             c.cond_channels, fmt::join(cond.sizes(), ", "));
  const int64_t B = x.empty() ? 0 : x.begin()->second.size(0);
  SIMU_CHECK(cond.size(0) > 0 && B % cond.size(0) == 0 && (!cache || cond.size(0) == B),
             "flow model: cond has {} rows for {} latent rows (need the same, or a divisor shared by the rows "
             "b*G + g, without a condition cache)", cond.size(0), B);
  // Timestep embedding (+ shortcut step embedding), then the shared modulation when share_mod.
  auto t_emb = t_embedder->forward(t);  // [B, C]
  if (d.has_value()) {
    SIMU_CHECK(d_embedder, "flow model: a shortcut step d was given but the model has no d_embedder "
                           "(is_shortcut_model: false)");
    t_emb = t_emb + d_embedder->forward(*d);
  }
  if (c.share_mod) t_emb = adaLN_modulation->forward(t_emb);  // [B, 6C]
  t_emb = t_emb.to(torch::kFloat32);
  const bool low_autocast = cond.is_cuda() && at::autocast::is_autocast_enabled(at::kCUDA) &&
                            fused::is_low_precision(at::autocast::get_autocast_dtype(at::kCUDA));
  // The blocks' modulation input, once for all of them: the shared modulation, or the SiLU that starts
  // every block's adaLN_modulation, in the 16-bit dtype its Linear computes in under CUDA autocast (the
  // cast each block's Linear would otherwise repeat; same values).
  auto mod = t_emb;  // [B or 1, 6C] or [B or 1, C]
  if (!c.share_mod) {
    mod = torch::silu(t_emb);
    if (low_autocast) mod = mod.to(at::autocast::get_autocast_dtype(at::kCUDA));
  }

  // Input projection per latent, merged into the transformer streams (float32).
  at::ScalarType input_dtype;
  auto h = input_streams(x, input_dtype);
  h.resize(streams_run_);  // set_output_latents: only the leading protected streams
  // The condition once in the dtype its projections use: bf16 / fp16 under CUDA autocast in that dtype
  // (the cast every to_kv would otherwise repeat, same values), else fp32.
  auto cond32 = cond.to(low_autocast ? at::autocast::get_autocast_dtype(at::kCUDA) : torch::kFloat32);

  // Transformer blocks; each leaves its last residual to the next one's first LayerNorm (fused path).
  ResidualCarry carry;
  // Lagged two-stream schedule (set_stream_lag): joined after the last block.
  StreamLag lag;
  StreamLag* lag_ptr = stream_lag_ && cond.is_cuda() && !block_wrapper_ ? &lag : nullptr;
  for (size_t b = 0; b < block_list_.size(); ++b) {
    if (!block_wrapper_) {
      h = block_list_[b]->forward(h, mod, cond32, cache ? &cache->kv[b] : nullptr, &carry, lag_ptr);
      continue;
    }
    // Wrapped: inputs = streams + [modulation, condition]; fn owns the block and the cached keys/values.
    std::vector<torch::Tensor> inputs = h;
    inputs.push_back(mod);
    inputs.push_back(cond32);
    const size_t S = h.size();
    auto kv = cache ? std::make_shared<const BlockKV>(cache->kv[b]) : nullptr;
    BlockFn fn = [block = block_list_[b].ptr(), S, kv](const std::vector<torch::Tensor>& v) {
      return block->forward(std::vector<torch::Tensor>(v.begin(), v.begin() + S), v[S], v[S + 1], kv.get());
    };
    h = block_wrapper_(static_cast<int64_t>(b), *block_list_[b], inputs, fn);
  }
  lag.join();
  h = carry.apply(h);
  for (auto& hi : h) hi = hi.to(input_dtype);

  return output_latents(h);
}

std::vector<torch::Tensor> SparseStructureFlowTdfyWrapperImpl::input_streams(const Latents& x, at::ScalarType& dtype) {
  const auto& c = config_;
  // Input projection per latent, then merge shared groups into streams.
  std::map<std::string, torch::Tensor> projected;
  for (const auto& s : c.latents) {
    const auto it = x.find(s.name);
    SIMU_CHECK(it != x.end(), "flow model: latent '{}' missing from the input", s.name);
    const auto& xi = it->second;
    SIMU_CHECK(xi.dim() == 3 && xi.size(1) == s.tokens() && xi.size(2) == s.in_channels,
               "flow model: latent '{}' must be [B, {}, {}], got [{}]", s.name, s.tokens(), s.in_channels,
               fmt::join(xi.sizes(), ", "));
    projected[s.name] = latent_mapping.at(s.name)->to_input(xi);  // [B, T, C]
  }
  std::vector<torch::Tensor> h;
  for (const auto& name : streams_) {
    const auto g = std::find_if(c.share_groups.begin(), c.share_groups.end(), [&](const auto& p) { return p.first == name; });
    if (g == c.share_groups.end()) {
      h.push_back(projected.at(name));
    } else {
      std::vector<torch::Tensor> parts;
      for (const auto& m : g->second) parts.push_back(projected.at(m));
      h.push_back(torch::cat(parts, 1));
    }
  }
  dtype = h.front().scalar_type();
  for (auto& hi : h) hi = hi.to(torch::kFloat32);
  return h;
}

Latents SparseStructureFlowTdfyWrapperImpl::output_latents(const std::vector<torch::Tensor>& h) {
  const auto& c = config_;
  // Split streams back into latents and project out.
  std::map<std::string, torch::Tensor> split;
  for (size_t i = 0; i < h.size(); ++i) {
    const auto g = std::find_if(c.share_groups.begin(), c.share_groups.end(), [&](const auto& p) { return p.first == streams_[i]; });
    if (g == c.share_groups.end()) {
      split[streams_[i]] = h[i];
    } else {
      int64_t start = 0;
      for (const auto& m : g->second) {
        const int64_t len = c.latent(m).tokens();
        split[m] = h[i].narrow(1, start, len);
        start += len;
      }
    }
  }
  Latents out;
  for (const auto& s : c.latents) {
    if (!output_latents_.empty() && std::find(output_latents_.begin(), output_latents_.end(), s.name) == output_latents_.end())
      continue;
    out[s.name] = latent_mapping.at(s.name)->to_output(split.at(s.name));
  }
  return out;
}

}  // namespace simu::models
