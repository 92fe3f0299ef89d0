// The flow model's layers below the block (flow_model.h): timestep embedder, LayerNorm32, per-head RMS
// norm, feed-forward net, cross attention and the mixture-of-transformers self attention.
#include <ATen/autocast_mode.h>
#include <fmt/ranges.h>

#include <cmath>

#include "common/error.h"
#include "models/flow_model.h"
#include "models/flow_model_internal.h"
#include "models/fused_ops.h"
#include "models/mlp_epilogue.h"

namespace simu::models {

using detail::attention;
using detail::inference_only_ok;
using detail::register_dict;

// ---------------------------------------------------------------------------------------------
// Modules

TimestepEmbedderImpl::TimestepEmbedderImpl(int64_t hidden_size, int64_t freq_size) : frequency_embedding_size(freq_size) {
  mlp = register_module("mlp", torch::nn::Sequential(Linear(freq_size, hidden_size), torch::nn::SiLU(),
                                                     Linear(hidden_size, hidden_size)));
}

torch::Tensor TimestepEmbedderImpl::timestep_embedding(const torch::Tensor& t, int64_t dim, double max_period) {
  const int64_t half = dim / 2;
  // freqs = exp(-ln(max_period) * arange(half) / half), float32 like the official
  // Made on t's device: no host-to-device copy inside the forward (CUDA graph capture forbids it).
  auto freqs = torch::exp(-std::log(max_period) * torch::arange(half, t.options().dtype(torch::kFloat32)) /
                          static_cast<double>(half));
  auto args = t.reshape({-1, 1}).to(torch::kFloat32) * freqs.unsqueeze(0);  // [B, half]
  auto emb = torch::cat({torch::cos(args), torch::sin(args)}, -1);         // [B, 2*half]
  if (dim % 2) emb = torch::cat({emb, torch::zeros_like(emb.narrow(1, 0, 1))}, -1);
  return emb;
}

torch::Tensor TimestepEmbedderImpl::forward(const torch::Tensor& t) {
  auto tt = t.dim() == 0 ? t.unsqueeze(0) : t;
  return mlp->forward(timestep_embedding(tt, frequency_embedding_size));  // [B, C]
}

LayerNorm32Impl::LayerNorm32Impl(int64_t c, bool affine, double e) : channels(c), eps(e) {
  if (affine) {
    weight = register_parameter("weight", torch::ones({c}));
    bias = register_parameter("bias", torch::zeros({c}));
  }
}

torch::Tensor LayerNorm32Impl::forward(const torch::Tensor& x) {
  auto y = at::layer_norm(x.to(torch::kFloat32), {channels}, weight, bias, eps);
  return y.to(x.scalar_type());
}

MultiHeadRMSNormImpl::MultiHeadRMSNormImpl(int64_t dim, int64_t heads) : scale(std::sqrt(static_cast<double>(dim))) {
  gamma = register_parameter("gamma", torch::ones({heads, dim}));
}

torch::Tensor MultiHeadRMSNormImpl::forward(const torch::Tensor& x) {
  // Official: (F.normalize(x, dim=-1) * gamma * scale).to(x.dtype), i.e. x / max(|x|, 1e-12) in
  // float32 (under autocast the norm runs in fp32): x * (1 / max(|x|, eps)) then * (gamma * scale).
  return fused::multi_head_rms_norm_reference(x, gamma, scale);  // [B, L, H, D]
}

FeedForwardNetImpl::FeedForwardNetImpl(int64_t channels, double mlp_ratio) {
  const auto hidden = static_cast<int64_t>(channels * mlp_ratio);
  fc1 = Linear(channels, hidden);
  fc2 = Linear(hidden, channels);
  register_module("mlp", torch::nn::Sequential(fc1, torch::nn::GELU(torch::nn::GELUOptions().approximate("tanh")), fc2));
}

torch::Tensor FeedForwardNetImpl::forward(const torch::Tensor& x) {
  const bool fused = fused_kernels && fused_path(x) && !(fc1->adapter() && fc1->adapter_enabled());
  // Inference: GELU in fc1's epilogue (not with an adapter on fc1: its delta must be added first).
  if (fused && inference_only_ok(inference_kernels) && fused::supports_linear_gelu(x)) {
    const auto [w1, b1] = fc1->product_weights(x);  // fc1's compute copy where it applies (linear.h)
    return fc2->forward(fused::linear_gelu_tanh_bf16(x, w1, b1));
  }
  // Training kernels or a graph, frozen base: GELU and its gradient in cuBLASLt epilogues, the same products
  // with and without a graph (mlp_epilogue.h); undefined where it does not apply.
  if (fused) {
    auto y = mlp_epilogue::frozen_mlp(x, *fc1, *fc2);  // [..., C]
    if (y.defined()) return y;
  }
  return fc2->forward(torch::gelu(fc1->forward(x), "tanh"));
}

CrossAttentionImpl::CrossAttentionImpl(int64_t channels, int64_t ctx_channels, int64_t heads, bool qk_rms_norm)
    : num_heads(heads) {
  to_q = register_module("to_q", Linear(channels, channels));
  to_kv = register_module("to_kv", Linear(ctx_channels, 2 * channels));
  if (qk_rms_norm) {
    q_rms_norm = register_module("q_rms_norm", MultiHeadRMSNorm(channels / heads, heads));
    k_rms_norm = register_module("k_rms_norm", MultiHeadRMSNorm(channels / heads, heads));
  }
  to_out = register_module("to_out", Linear(channels, channels));
}

std::pair<torch::Tensor, torch::Tensor> CrossAttentionImpl::context_kv(const torch::Tensor& context) {
  const int64_t B = context.size(0), Lc = context.size(1);
  auto kv = to_kv->forward(context).reshape({B, Lc, 2, num_heads, -1});  // [B, Lc, 2, H, D]
  // Strided views as select gives them (no copy for the attention kernel); their backward is one stack
  // writing both halves of kv's gradient, where two selects zero-fill two [B, Lc, 2, H, D] buffers,
  // copy into each and add them.
  auto kvs = kv.unbind(2);
  auto k = kvs[0], v = kvs[1];  // [B, Lc, H, D]
  if (k_rms_norm) k = k_rms_norm->forward(k);
  return {k, v};
}

torch::Tensor CrossAttentionImpl::zero_condition_output(const torch::Tensor& like) {
  // An all-zero condition row: every key is to_kv's bias (through k_rms_norm), the same for all condition
  // tokens, so the softmax is uniform and the attention output is the value bias itself, whatever L_c.
  auto v0 = context_kv(torch::zeros({1, 1, to_kv->in_features}, like.options().dtype(torch::kFloat32))).second;  // [1, 1, H, D]
  return to_out->forward(v0.reshape({1, 1, -1}));  // [1, 1, C]
}

torch::Tensor CrossAttentionImpl::attended(const torch::Tensor& x, const torch::Tensor& k, const torch::Tensor& v) {
  const int64_t B = x.size(0), L = x.size(1), Bk = k.size(0);
  auto q = to_q->forward(Bk < B ? x.narrow(0, 0, Bk) : x).reshape({Bk, L, num_heads, -1});  // [Bk, L, H, D]
  if (q_rms_norm) q = q_rms_norm->forward(q);
  return attention(q, k, v, inference_kernels).reshape({Bk, L, -1});  // [Bk, L, C]
}

bool CrossAttentionImpl::project_plain_into(const torch::Tensor& h, torch::Tensor& out) {
  if ((to_out->adapter() && to_out->adapter_enabled()) || to_out->fp8_weight()) return false;
  const auto [w, b] = to_out->product_weights(h);
  if (w.scalar_type() != h.scalar_type() || (b.defined() && b.scalar_type() != h.scalar_type()) || h.requires_grad() ||
      w.requires_grad())
    return false;
  // The product torch::linear makes of a contiguous [Bk, L, C] input, written into out's rows.
  const int64_t rows = h.size(0) * h.size(1);
  auto o = out.view({rows, -1});
  auto h2 = h.reshape({rows, -1});
  if (b.defined()) at::addmm_out(o, b, h2, w.t());
  else at::mm_out(o, h2, w.t());
  return true;
}

torch::Tensor CrossAttentionImpl::attend(const torch::Tensor& x, const torch::Tensor& k, const torch::Tensor& v,
                                         const torch::Tensor& zero_out) {
  const int64_t B = x.size(0), L = x.size(1), Bk = k.size(0);
  auto h = attended(x, k, v);  // [Bk, L, C]
  if (Bk == B) return to_out->forward(h);
  // Rows Bk.. of x have an all-zero condition (ConditionCache::zero_from): to_out(v(0)) for every query.
  auto tail = zero_out.defined() ? zero_out : zero_condition_output(x);  // [1, 1, C]
  // The attended rows' projection straight into the output, the zero rows filled: no concatenation copy.
  auto out = torch::empty({B, L, to_out->out_features}, h.options());  // [B, L, C]
  auto head = out.narrow(0, 0, Bk);
  if (project_plain_into(h, head)) {
    out.narrow(0, Bk, B - Bk).copy_(tail.expand({B - Bk, L, tail.size(2)}));
    return out;
  }
  auto projected = to_out->forward(h);  // [Bk, L, C]
  return torch::cat({projected, tail.to(projected.scalar_type()).expand({B - Bk, L, tail.size(2)})}, 0);  // [B, L, C]
}

std::pair<torch::Tensor, torch::Tensor> CrossAttentionImpl::attend_parts(const torch::Tensor& x, const torch::Tensor& k,
                                                                         const torch::Tensor& v, const torch::Tensor& zero_out) {
  const int64_t B = x.size(0), L = x.size(1), Bk = k.size(0);
  auto h = attended(x, k, v);  // [Bk, L, C]
  if (Bk == B) return {to_out->forward(h), torch::Tensor()};
  auto head = torch::empty({Bk, L, to_out->out_features}, h.options());  // [Bk, L, C]
  if (!project_plain_into(h, head)) head = to_out->forward(h);
  auto tail = zero_out.defined() ? zero_out : zero_condition_output(x);  // [1, 1, C]
  return {head, tail.to(head.scalar_type())};
}

torch::Tensor CrossAttentionImpl::attend_shared(const torch::Tensor& x, const torch::Tensor& k, const torch::Tensor& v) {
  const int64_t B = x.size(0), L = x.size(1), Bc = k.size(0);
  SIMU_CHECK(Bc > 0 && B % Bc == 0, "cross attention: {} token rows cannot share {} condition rows (need a multiple)", B,
             Bc);
  const int64_t G = B / Bc;
  auto q = to_q->forward(x).reshape({B, L, num_heads, -1});  // [Bc*G, L, H, D]
  if (q_rms_norm) q = q_rms_norm->forward(q);
  // Rows b*G .. b*G + G-1 attend over condition b: consecutive rows, so their G query sets form one
  // sequence by a view (and the output goes back by a view), no transposed copies either way.
  auto h = attention(q.reshape({Bc, G * L, num_heads, -1}), k, v, inference_kernels);  // [Bc, G*L, H, D]
  return to_out->forward(h.reshape({B, L, -1}));                                      // [B, L, C]
}

torch::Tensor CrossAttentionImpl::forward(const torch::Tensor& x, const torch::Tensor& context) {
  const auto [k, v] = context_kv(context);
  if (context.size(0) != x.size(0)) return attend_shared(x, k, v);
  return attend(x, k, v);
}

MOTSelfAttentionImpl::MOTSelfAttentionImpl(int64_t channels, int64_t heads, const std::vector<std::string>& streams,
                                           const std::vector<std::string>& protected_modalities)
    : names(streams), num_heads(heads) {
  for (const auto& n : names) {
    to_qkv.push_back(Linear(channels, 3 * channels));
    to_out.push_back(Linear(channels, channels));
    q_rms_norm.push_back(MultiHeadRMSNorm(channels / heads, heads));
    k_rms_norm.push_back(MultiHeadRMSNorm(channels / heads, heads));
    is_protected.push_back(std::find(protected_modalities.begin(), protected_modalities.end(), n) !=
                           protected_modalities.end());
  }
  register_dict(*this, "to_qkv", names, to_qkv);
  register_dict(*this, "q_rms_norm", names, q_rms_norm);
  register_dict(*this, "k_rms_norm", names, k_rms_norm);
  register_dict(*this, "to_out", names, to_out);
}

namespace {
thread_local bool t_few_query_flash_off = false;
}  // namespace

detail::FewQueryFlashOff::FewQueryFlashOff(bool off) : previous_(t_few_query_flash_off) { t_few_query_flash_off = off; }
detail::FewQueryFlashOff::~FewQueryFlashOff() { t_few_query_flash_off = previous_; }

bool few_query_flash(const torch::Tensor& q, const torch::Tensor& k) {
  if (t_few_query_flash_off) return false;
  const auto dt = q.scalar_type();
  const int64_t D = q.size(3);
  return q.is_cuda() && !at::GradMode::is_enabled() && (dt == at::kHalf || dt == at::kBFloat16) &&
         k.scalar_type() == dt && q.size(1) <= 16 && k.size(1) >= 256 && D <= 256 && D % 8 == 0;
}

torch::Tensor sdpa_blhd(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v, bool few_query_ok) {
  auto qh = q.permute({0, 2, 1, 3}), kh = k.permute({0, 2, 1, 3}), vh = v.permute({0, 2, 1, 3});  // [B, H, L, D]
  // The flash kernel wants each head's rows contiguous in D (views of a projection are).
  if (few_query_ok && few_query_flash(q, k) && v.scalar_type() == q.scalar_type() && q.stride(3) == 1 && k.stride(3) == 1 &&
      v.stride(3) == 1)
    return std::get<0>(at::_scaled_dot_product_flash_attention(qh, kh, vh)).permute({0, 2, 1, 3});
  return at::scaled_dot_product_attention(qh, kh, vh).permute({0, 2, 1, 3});  // [B, L, H, D]
}

bool fused_path(const torch::Tensor& x) {
  return fused::compiled() && x.is_cuda() && at::autocast::is_autocast_enabled(at::kCUDA) &&
         fused::is_low_precision(at::autocast::get_autocast_dtype(at::kCUDA));
}

void MOTSelfAttentionImpl::project_qkv_fused(size_t i, const torch::Tensor& x, torch::Tensor& q, torch::Tensor k,
                                             torch::Tensor v) {
  const int64_t B = x.size(0), L = x.size(1);
  auto qkv = to_qkv[i]->forward(x);  // [B, L, 3C] bf16 under autocast
  qkv = qkv.reshape({B, L, 3, num_heads, -1}).contiguous();
  q = torch::empty({B, L, num_heads, qkv.size(4)}, qkv.options());
  fused::split_qkv_rms_norm(qkv, q_rms_norm[i]->gamma, k_rms_norm[i]->gamma, q_rms_norm[i]->scale, q, k, v);
}

std::vector<torch::Tensor> MOTSelfAttentionImpl::forward_fused(const std::vector<torch::Tensor>& x) {
  const size_t S = x.size();
  const int64_t B = x[0].size(0);
  // Key/value buffer [B, L_others + L_protected, H, D]: the other streams' keys first, then the
  // protected ones (the order of the reference's concatenation); each stream writes its slice.
  int64_t L_others = 0, L_total = 0;
  for (size_t i = 0; i < S; ++i) {
    L_total += x[i].size(1);
    if (!is_protected[i]) L_others += x[i].size(1);
  }
  std::vector<torch::Tensor> q(S), k(S), v(S), h(S);
  const int64_t D = x[0].size(2) / num_heads;
  auto k_all = torch::empty({B, L_total, num_heads, D}, x[0].options().dtype(at::autocast::get_autocast_dtype(at::kCUDA)));
  auto v_all = torch::empty_like(k_all);
  int64_t off_other = 0, off_prot = L_others;
  for (size_t i = 0; i < S; ++i) {
    const int64_t L = x[i].size(1);
    int64_t& off = is_protected[i] ? off_prot : off_other;
    k[i] = k_all.narrow(1, off, L);
    v[i] = v_all.narrow(1, off, L);
    off += L;
    project_qkv_fused(i, x[i], q[i], k[i], v[i]);
  }
  // Protected streams attend to themselves; the others to every key (no gradient here to detach).
  std::vector<torch::Tensor> oq;
  std::vector<size_t> others;
  for (size_t i = 0; i < S; ++i) {
    if (is_protected[i]) {
      h[i] = attention(q[i], k[i], v[i], inference_kernels);
    } else {
      others.push_back(i);
      oq.push_back(q[i]);
    }
  }
  if (!others.empty()) {
    auto ho = attention(oq.size() == 1 ? oq[0] : torch::cat(oq, 1), k_all, v_all, inference_kernels);  // [B, L_others, H, D]
    int64_t start = 0;
    for (size_t i : others) {
      h[i] = ho.narrow(1, start, x[i].size(1));
      start += x[i].size(1);
    }
  }
  for (size_t i = 0; i < S; ++i) h[i] = to_out[i]->forward(h[i].reshape({B, x[i].size(1), -1}));
  return h;
}

std::vector<torch::Tensor> MOTSelfAttentionImpl::forward(const std::vector<torch::Tensor>& x) {
  const size_t S = x.size();
  // Fast path: fused q/k RMS norm written straight into the attention's key/value layout.
  const int64_t head_dim = x[0].size(-1) / num_heads;  // every stream has the model's channels
  if (fused_kernels && inference_only_ok(inference_kernels) && fused_path(x[0]) &&
      (head_dim == 64 || head_dim == 128 || head_dim == 256))
    return forward_fused(x);
  // Per-stream q, k, v: [B, L_i, H, D], with RMS norm on q and k (one differentiable fused kernel each
  // way on the fused path).
  std::vector<torch::Tensor> q(S), k(S), v(S), h(S);
  for (size_t i = 0; i < S; ++i) {
    const int64_t B = x[i].size(0), L = x[i].size(1);
    auto qkv = to_qkv[i]->forward(x[i]).reshape({B, L, 3, num_heads, -1});
    if (fused_kernels && fused_path(qkv) && fused::supports_split_qkv(qkv)) {
      std::tie(q[i], k[i], v[i]) = fused::split_qkv_rms_norm_autograd(qkv, q_rms_norm[i]->gamma, k_rms_norm[i]->gamma,
                                                                      q_rms_norm[i]->scale);
      continue;
    }
    q[i] = q_rms_norm[i]->forward(qkv.select(2, 0));
    k[i] = k_rms_norm[i]->forward(qkv.select(2, 1));
    v[i] = qkv.select(2, 2);
  }
  // Protected streams (shape) attend only to themselves.
  std::vector<torch::Tensor> oq, ok, ov, pk, pv;
  std::vector<size_t> others;
  for (size_t i = 0; i < S; ++i) {
    if (is_protected[i]) {
      h[i] = attention(q[i], k[i], v[i], inference_kernels);
      pk.push_back(k[i].detach());
      pv.push_back(v[i].detach());
    } else {
      others.push_back(i);
      oq.push_back(q[i]);
      ok.push_back(k[i]);
      ov.push_back(v[i]);
    }
  }
  // The other streams attend to [others, protected (detached)] keys/values together.
  if (!others.empty()) {
    auto keys = ok, values = ov;
    keys.insert(keys.end(), pk.begin(), pk.end());
    values.insert(values.end(), pv.begin(), pv.end());
    auto ho = attention(torch::cat(oq, 1), torch::cat(keys, 1), torch::cat(values, 1), inference_kernels);  // [B, sum L, H, D]
    int64_t start = 0;
    for (size_t i : others) {
      const int64_t L = x[i].size(1);
      h[i] = ho.narrow(1, start, L);
      start += L;
    }
  }
  // Output projection per stream.
  for (size_t i = 0; i < S; ++i) h[i] = to_out[i]->forward(h[i].reshape({x[i].size(0), x[i].size(1), -1}));
  return h;
}


}  // namespace simu::models
