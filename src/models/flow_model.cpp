#include "models/flow_model.h"

#include <ATen/autocast_mode.h>
#include <fmt/ranges.h>

#include <cmath>
#include <set>

#include "common/config.h"
#include "common/error.h"
#include "models/official_yaml.h"
#include "models/fused_ops.h"

#ifdef SIMU_HAVE_CUDA_KERNELS
#include <ATen/cuda/CUDAEvent.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#endif

namespace simu::models {

namespace {

// Registers `modules` under one ModuleDict named `name` (keys = stream names) so state-dict keys read
// `<name>.<stream>.<param>` like the official torch.nn.ModuleDict.
template <typename Holder>
void register_dict(torch::nn::Module& owner, const std::string& name, const std::vector<std::string>& keys,
                   const std::vector<Holder>& modules) {
  std::vector<std::pair<std::string, std::shared_ptr<torch::nn::Module>>> items;
  for (size_t i = 0; i < keys.size(); ++i) items.emplace_back(keys[i], modules[i].ptr());
  owner.register_module(name, torch::nn::ModuleDict(items));
}

// The kernels without a backward (GELU epilogue, q/k/v into the key/value buffer, second stream): only
// where allowed (not in training mode) and when no graph is recorded.
bool inference_only_ok(bool inference_kernels) { return inference_kernels && !at::GradMode::is_enabled(); }

// SDPA on [B, L, H, D] tensors (official scaled_dot_product_attention, "sdpa" backend).
torch::Tensor attention(const torch::Tensor& q, const torch::Tensor& k, const torch::Tensor& v) {
  auto out = at::scaled_dot_product_attention(q.permute({0, 2, 1, 3}), k.permute({0, 2, 1, 3}),
                                              v.permute({0, 2, 1, 3}));  // [B, H, L, D]
  return out.permute({0, 2, 1, 3});                                       // [B, L, H, D]
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Config

int64_t LatentSpec::tokens() const {
  if (pos_embedder == "shape") {
    const int64_t side = resolution / patch_size;
    return side * side * side;
  }
  return token_len;
}

std::vector<std::string> FlowModelConfig::stream_names() const {
  std::set<std::string> merged;
  for (const auto& [_, members] : share_groups) merged.insert(members.begin(), members.end());
  std::vector<std::string> out;
  for (const auto& l : latents)
    if (!merged.count(l.name)) out.push_back(l.name);
  for (const auto& [name, _] : share_groups) out.push_back(name);
  return out;
}

const LatentSpec& FlowModelConfig::latent(const std::string& name) const {
  for (const auto& l : latents)
    if (l.name == name) return l;
  fail("flow model config: no latent named '{}'", name);
}

void FlowModelConfig::validate(const std::string& where) const {
  const std::string w = where.empty() ? "flow model config" : where;
  SIMU_CHECK(model_channels > 0 && num_heads > 0 && model_channels % num_heads == 0,
             "{}: model_channels {} must be a positive multiple of num_heads {}", w, model_channels, num_heads);
  SIMU_CHECK(num_blocks > 0, "{}: num_blocks must be positive, got {}", w, num_blocks);
  SIMU_CHECK(cond_channels > 0, "{}: cond_channels must be positive, got {}", w, cond_channels);
  SIMU_CHECK(pe_mode == "ape", "{}: pe_mode '{}' is not supported by the MOT flow model (only 'ape')", w, pe_mode);
  SIMU_CHECK(qk_rms_norm, "{}: the MOT self-attention needs qk_rms_norm: true (the official model raises otherwise)", w);
  SIMU_CHECK(!latents.empty(), "{}: latent_mapping is empty", w);
  std::set<std::string> names;
  for (const auto& l : latents) {
    SIMU_CHECK(names.insert(l.name).second, "{}: latent '{}' listed twice", w, l.name);
    SIMU_CHECK(l.in_channels > 0, "{}: latent '{}' needs in_channels > 0", w, l.name);
    SIMU_CHECK(l.tokens() > 0, "{}: latent '{}' has no tokens (resolution/token_len)", w, l.name);
  }
  std::set<std::string> grouped;
  for (const auto& [g, members] : share_groups) {
    SIMU_CHECK(!members.empty(), "{}: latent_share_transformer group '{}' is empty", w, g);
    for (const auto& m : members) {
      SIMU_CHECK(names.count(m), "{}: latent_share_transformer group '{}' names unknown latent '{}'", w, g, m);
      SIMU_CHECK(grouped.insert(m).second, "{}: latent '{}' is in two latent_share_transformer groups", w, m);
    }
  }
  const auto streams = stream_names();
  for (const auto& p : protected_modalities)
    SIMU_CHECK(std::find(streams.begin(), streams.end(), p) != streams.end(),
               "{}: protected modality '{}' is not a transformer stream (streams: {})", w, p, fmt::join(streams, ", "));
}

FlowModelConfig FlowModelConfig::from_official(const YAML::Node& b, const std::string& file) {
  SIMU_CHECK(b && b.IsMap(), "{}: flow model (reverse_fn.backbone) section missing or not a mapping", file);
  const std::string target = short_target(b);
  SIMU_CHECK(target.empty() || target == "SparseStructureFlowTdfyWrapper",
             "{}: backbone _target_ '{}' is not SparseStructureFlowTdfyWrapper", file, target);
  FlowModelConfig c;
  c.in_channels = get_or<int64_t>(b, "in_channels", c.in_channels, file);
  c.model_channels = get_or<int64_t>(b, "model_channels", c.model_channels, file);
  c.cond_channels = get_or<int64_t>(b, "cond_channels", c.cond_channels, file);
  c.out_channels = get_or<int64_t>(b, "out_channels", c.out_channels, file);
  c.num_blocks = get_or<int64_t>(b, "num_blocks", c.num_blocks, file);
  const int64_t head_channels = get_or<int64_t>(b, "num_head_channels", 64, file);
  c.num_heads = get_or<int64_t>(b, "num_heads", 0, file);
  if (c.num_heads == 0) c.num_heads = c.model_channels / head_channels;
  c.mlp_ratio = get_or<double>(b, "mlp_ratio", 4.0, file);
  c.pe_mode = get_or<std::string>(b, "pe_mode", "ape", file);
  c.share_mod = get_or<bool>(b, "share_mod", false, file);
  c.qk_rms_norm = get_or<bool>(b, "qk_rms_norm", false, file);
  c.qk_rms_norm_cross = get_or<bool>(b, "qk_rms_norm_cross", false, file);
  c.is_shortcut_model = get_or<bool>(b, "is_shortcut_model", false, file);
  c.force_zeros_cond = get_or<bool>(b, "force_zeros_cond", false, file);
  // latent_mapping: name -> {in_channels, pos_embedder: {_target_, ...}}
  const YAML::Node lm = b["latent_mapping"];
  SIMU_CHECK(lm && lm.IsMap(), "{}: backbone.latent_mapping missing or not a mapping", file);
  for (const auto& kv : lm) {
    LatentSpec s;
    s.name = kv.first.as<std::string>();
    const YAML::Node n = kv.second;
    s.in_channels = get_or<int64_t>(n, "in_channels", 0, file);
    const YAML::Node pe = n["pos_embedder"];
    const std::string pt = short_target(pe);
    if (pt == "ShapePositionEmbedder") {
      s.pos_embedder = "shape";
      s.resolution = get_or<int64_t>(pe, "resolution", get_or<int64_t>(b, "resolution", 0, file), file);
      s.patch_size = get_or<int64_t>(pe, "patch_size", get_or<int64_t>(b, "patch_size", 1, file), file);
    } else if (pt == "LearntPositionEmbedder" || pt == "RandomPositionEmbedder") {
      s.pos_embedder = pt == "LearntPositionEmbedder" ? "learnt" : "random";
      s.token_len = get_or<int64_t>(pe, "token_len", 1, file);
    } else {
      fail("{}: latent_mapping.{}.pos_embedder: unknown _target_ '{}' (expected ShapePositionEmbedder, "
           "LearntPositionEmbedder or RandomPositionEmbedder)", file, s.name, pt);
    }
    c.latents.push_back(s);
  }
  // latent_share_transformer: merged name -> [latent names]
  if (const YAML::Node st = b["latent_share_transformer"]; st && st.IsMap()) {
    for (const auto& kv : st) c.share_groups.emplace_back(kv.first.as<std::string>(), kv.second.as<std::vector<std::string>>());
  }
  c.validate(file + ": module.generator.backbone.reverse_fn.backbone");
  return c;
}

FlowModelConfig FlowModelConfig::from(config::Reader& r) {
  FlowModelConfig c;
  r.field("in_channels", c.in_channels);
  r.field("model_channels", c.model_channels);
  r.field("cond_channels", c.cond_channels);
  r.field("out_channels", c.out_channels);
  r.field("num_blocks", c.num_blocks);
  r.field("num_heads", c.num_heads);
  r.field("mlp_ratio", c.mlp_ratio);
  r.field("pe_mode", c.pe_mode);
  r.field("share_mod", c.share_mod);
  r.field("qk_rms_norm", c.qk_rms_norm);
  r.field("qk_rms_norm_cross", c.qk_rms_norm_cross);
  r.field("is_shortcut_model", c.is_shortcut_model);
  r.field("force_zeros_cond", c.force_zeros_cond);
  r.field("protected_modalities", c.protected_modalities);
  // latents: list of {name, in_channels, pos_embedder: shape|learnt|random, resolution, patch_size, token_len}
  const YAML::Node list = r.raw("latents");
  SIMU_CHECK(list && list.IsSequence(), "{}: key '{}': expected a list of latents", r.file(), r.full("latents"));
  for (size_t i = 0; i < list.size(); ++i) {
    config::Reader lr(list[i], r.file(), r.full(fmt::format("latents[{}]", i)));
    LatentSpec s;
    s.name = lr.require<std::string>("name");
    s.in_channels = lr.require<int64_t>("in_channels");
    lr.field("pos_embedder", s.pos_embedder);
    lr.field("resolution", s.resolution);
    lr.field("patch_size", s.patch_size);
    lr.field("token_len", s.token_len);
    lr.finish();
    SIMU_CHECK(s.pos_embedder == "shape" || s.pos_embedder == "learnt" || s.pos_embedder == "random",
               "{}: latents[{}].pos_embedder: expected shape, learnt or random, got '{}'", r.file(), i, s.pos_embedder);
    c.latents.push_back(s);
  }
  // share_groups: mapping merged name -> list of latent names (order kept)
  if (r.has("share_groups")) {
    const YAML::Node g = r.raw("share_groups");
    SIMU_CHECK(g.IsMap(), "{}: key '{}': expected a mapping name -> list of latents", r.file(), r.full("share_groups"));
    for (const auto& kv : g) c.share_groups.emplace_back(kv.first.as<std::string>(), kv.second.as<std::vector<std::string>>());
  }
  c.validate(r.file() + ": " + (r.full("").empty() ? "flow_model" : r.full("")));
  return c;
}

// ---------------------------------------------------------------------------------------------
// Autocast

Bf16Autocast::Bf16Autocast(bool enable) : enabled_(enable) {
  if (!enabled_) return;
  prev_enabled_ = at::autocast::is_autocast_enabled(at::kCUDA);
  prev_dtype_ = at::autocast::get_autocast_dtype(at::kCUDA);
  at::autocast::set_autocast_enabled(at::kCUDA, true);
  at::autocast::set_autocast_dtype(at::kCUDA, at::kBFloat16);
  at::autocast::increment_nesting();
}

Bf16Autocast::~Bf16Autocast() {
  if (!enabled_) return;
  if (at::autocast::decrement_nesting() == 0) at::autocast::clear_cache();
  at::autocast::set_autocast_enabled(at::kCUDA, prev_enabled_);
  at::autocast::set_autocast_dtype(at::kCUDA, prev_dtype_);
}

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
  // Fast path: GELU in fc1's epilogue (not with an adapter on fc1: its delta must be added first).
  if (fused_kernels && inference_only_ok(inference_kernels) && !(fc1->adapter() && fc1->adapter_enabled()) &&
      fused_path(x) && fused::supports_linear_gelu(x))
    return fc2->forward(fused::linear_gelu_tanh_bf16(x, fc1->weight, fc1->bias));
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
  auto k = kv.select(2, 0), v = kv.select(2, 1);                         // [B, Lc, H, D]
  if (k_rms_norm) k = k_rms_norm->forward(k);
  return {k, v};
}

torch::Tensor CrossAttentionImpl::attend(const torch::Tensor& x, const torch::Tensor& k, const torch::Tensor& v) {
  const int64_t B = x.size(0), L = x.size(1);
  if (k.size(0) < B) {
    // Rows k.size(0).. of x have an all-zero condition (ConditionCache::zero_from): every key there is
    // to_kv's bias (through k_rms_norm), the same for all condition tokens, so the softmax is uniform
    // and the attention output is the value bias itself: to_out(v(0)) for every query, whatever L_c.
    const int64_t Bk = k.size(0);
    auto head = attend(x.narrow(0, 0, Bk), k, v);                                        // [Bk, L, C]
    auto v0 = context_kv(torch::zeros({1, 1, to_kv->in_features}, x.options().dtype(torch::kFloat32))).second;  // [1, 1, H, D]
    auto tail = to_out->forward(v0.reshape({1, 1, -1})).to(head.scalar_type());         // [1, 1, C]
    return torch::cat({head, tail.expand({B - Bk, L, tail.size(2)})}, 0);               // [B, L, C]
  }
  auto q = to_q->forward(x).reshape({B, L, num_heads, -1});  // [B, L, H, D]
  if (q_rms_norm) q = q_rms_norm->forward(q);
  auto h = attention(q, k, v).reshape({B, L, -1});  // [B, L, C]
  return to_out->forward(h);
}

torch::Tensor CrossAttentionImpl::forward(const torch::Tensor& x, const torch::Tensor& context) {
  const auto [k, v] = context_kv(context);
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
      h[i] = attention(q[i], k[i], v[i]);
    } else {
      others.push_back(i);
      oq.push_back(q[i]);
    }
  }
  if (!others.empty()) {
    auto ho = attention(oq.size() == 1 ? oq[0] : torch::cat(oq, 1), k_all, v_all);  // [B, L_others, H, D]
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
      h[i] = attention(q[i], k[i], v[i]);
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
    auto ho = attention(torch::cat(oq, 1), torch::cat(keys, 1), torch::cat(values, 1));  // [B, sum L, H, D]
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

std::vector<torch::Tensor> MOTBlockImpl::forward(const std::vector<torch::Tensor>& x_in, const torch::Tensor& mod,
                                                 const torch::Tensor& cond,
                                                 const std::vector<std::pair<torch::Tensor, torch::Tensor>>* kv,
                                                 ResidualCarry* carry) {
  // Modulation: six [B, 1, C] chunks (shift/scale/gate for attention and MLP).
  auto m = share_mod ? mod : ada_linear->forward(torch::silu(mod));
  auto chunks = m.chunk(6, 1);
  auto shift_msa = chunks[0].unsqueeze(1), scale_msa = chunks[1].unsqueeze(1), gate_msa = chunks[2].unsqueeze(1);
  auto shift_mlp = chunks[3].unsqueeze(1), scale_mlp = chunks[4].unsqueeze(1), gate_mlp = chunks[5].unsqueeze(1);
  const size_t S = x_in.size();
  // A pending residual from the previous block: kept for the fused LayerNorm below, else applied now.
  ResidualCarry incoming;
  if (carry) std::swap(incoming, *carry);
  std::vector<torch::Tensor> x = x_in, h(S);
  // norm(x) * (1 + scale) + shift. When the modulation is one row (the same t for the whole batch,
  // as in sampling) it is a LayerNorm with weight 1 + scale and bias shift: one fused fp32 kernel.
  const bool one_row = m.size(0) == 1;
  // Fast path: LayerNorm + modulation (or norm2's affine) in one kernel that stores bf16 for the next
  // projection (fused_ops.h); same fp32 arithmetic, one rounding.
  bool fast = fused_kernels && fused_path(x_in[0]) && (one_row || m.size(0) == x_in[0].size(0));
  for (const auto& xi : x_in) fast = fast && fused::supports_layer_norm_affine(xi);
  // The 16-bit type the fast path stores: the autocast dtype (bf16 in training, fp16 as released).
  const auto low = fast ? at::autocast::get_autocast_dtype(at::kCUDA) : torch::kBFloat16;
  // The streams share the modulation: in the fast path its fp32 affine rows [1 or B, C] (weight
  // 1 + scale, bias shift) are made once per block and passed in as `affine`.
  using Affine = std::pair<torch::Tensor, torch::Tensor>;
  auto affine_of = [&](const torch::Tensor& scale, const torch::Tensor& shift) {
    return fast ? Affine{(1 + scale).squeeze(1).to(torch::kFloat32), shift.squeeze(1).to(torch::kFloat32)} : Affine{};
  };
  const Affine affine_msa = affine_of(scale_msa, shift_msa), affine_mlp = affine_of(scale_mlp, shift_mlp);
  auto modulate = [&](LayerNorm32& norm, const torch::Tensor& xi, const torch::Tensor& scale, const torch::Tensor& shift,
                      const Affine& affine) {
    if (fast) return fused::layer_norm_affine_bf16(xi, affine.first, affine.second, norm->eps, low);
    if (one_row) {
      auto w = (1 + scale).reshape({-1}).to(torch::kFloat32), b = shift.reshape({-1}).to(torch::kFloat32);
      return at::layer_norm(xi.to(torch::kFloat32), {xi.size(-1)}, w, b, norm->eps).to(xi.scalar_type());
    }
    return norm->forward(xi) * (1 + scale) + shift;
  };
  if (fast) {
    // Residual update and the next LayerNorm in one kernel when the sublayer output allows it.
    auto residual_norm = [&](const torch::Tensor& xi, const torch::Tensor& hi, const torch::Tensor& gate,
                             const torch::Tensor& w, const torch::Tensor& b, double eps) {
      if (fused::supports_residual_layer_norm_affine(xi, hi)) return fused::residual_layer_norm_affine_bf16(xi, hi, gate, w, b, eps);
      auto xn = gate.defined() ? torch::addcmul(xi, hi, gate.unsqueeze(1)) : xi + hi;
      return std::make_pair(xn, fused::layer_norm_affine_bf16(xn, w, b, eps, low));
    };
    const auto gate_a = gate_msa.squeeze(1), gate_m = gate_mlp.squeeze(1);  // [1 or B, C]
    std::vector<torch::Tensor> mlp_out(S);
    // Stream i's norm1: with the previous block's pending residual when there is one -> {x, norm1(x)}.
    auto norm1_of = [&](size_t i) {
      if (!incoming.h.empty())
        return residual_norm(x[i], incoming.h[i], incoming.gate, affine_msa.first, affine_msa.second, norm1[i]->eps);
      return std::make_pair(x[i], fused::layer_norm_affine_bf16(x[i], affine_msa.first, affine_msa.second, norm1[i]->eps, low));
    };
    // Stream i after self attention (ha): gated residual + norm2 -> cross attention -> residual +
    // modulated norm3 -> MLP; the MLP's gated residual is left to the carry when there is one.
    auto rest_of = [&](size_t i, const torch::Tensor& xi, const torch::Tensor& ha) {
      auto [xa, n2] = residual_norm(xi, ha, gate_a, norm2[i]->weight.unsqueeze(0), norm2[i]->bias.unsqueeze(0), norm2[i]->eps);
      auto c = kv ? cross_attn[i]->attend(n2, (*kv)[i].first, (*kv)[i].second) : cross_attn[i]->forward(n2, cond);
      auto [xb, n3] = residual_norm(xa, c, torch::Tensor(), affine_mlp.first, affine_mlp.second, norm3[i]->eps);
      mlp_out[i] = mlp[i]->forward(n3);
      return carry ? xb : torch::addcmul(xb, mlp_out[i], gate_m.unsqueeze(1));
    };
    const int64_t head_dim = x[0].size(2) / self_attn->num_heads;
    const bool qkv_fused = self_attn->fused_kernels && (head_dim == 64 || head_dim == 128 || head_dim == 256);
#ifdef SIMU_HAVE_CUDA_KERNELS
    // Only without a condition cache: with cached keys/values (sampling) the forward has less GPU work
    // per launch and the second stream measured slower (H100, 25 CFG steps at 2,800 condition tokens:
    // 752 ms with it, 713 ms without), while the uncached forward gains (30.4 vs 32.8 ms).
    if (stream_overlap && inference_only_ok(inference_kernels) && !kv && qkv_fused && S == 2 &&
        self_attn->is_protected[0] != self_attn->is_protected[1]) {
      // p: the protected stream (shape), on the current stream; o: the other (pose), on a side stream.
      const size_t p = self_attn->is_protected[0] ? 0 : 1, o = 1 - p;
      const int64_t B = x[p].size(0), Lp = x[p].size(1), Lo = x[o].size(1), H = self_attn->num_heads;
      const auto dev = x[p].device().index();
      const auto main = c10::cuda::getCurrentCUDAStream(dev);
      const auto side = c10::cuda::getStreamFromPool(false, dev);
      // The side stream starts after everything issued so far (inputs, modulation).
      at::cuda::CUDAEvent inputs_ready, shape_kv_ready, other_done;
      inputs_ready.record(main);
      inputs_ready.block(side);
      // Keys/values of both streams, the other's first (the reference's concatenation order).
      auto k_all = torch::empty({B, Lo + Lp, H, head_dim}, x[p].options().dtype(low));
      auto v_all = torch::empty_like(k_all);
      // Protected stream: norm1, q/k/v (its keys into k_all), then the other stream may attend.
      auto [xp, n1p] = norm1_of(p);
      torch::Tensor qp;
      self_attn->project_qkv_fused(p, n1p, qp, k_all.narrow(1, Lo, Lp), v_all.narrow(1, Lo, Lp));
      shape_kv_ready.record(main);
      torch::Tensor xo_out;
      {
        // Other stream on the side stream: attends to every key once the protected ones are written.
        const c10::cuda::CUDAStreamGuard on_side(side);
        auto [xo, n1o] = norm1_of(o);
        torch::Tensor qo;
        self_attn->project_qkv_fused(o, n1o, qo, k_all.narrow(1, 0, Lo), v_all.narrow(1, 0, Lo));
        shape_kv_ready.block(side);
        auto ho = self_attn->to_out[o]->forward(attention(qo, k_all, v_all).reshape({B, Lo, -1}));
        xo_out = rest_of(o, xo, ho);
        other_done.record(side);
      }
      // Protected stream attends to itself only.
      auto hp = self_attn->to_out[p]->forward(attention(qp, k_all.narrow(1, Lo, Lp), v_all.narrow(1, Lo, Lp)).reshape({B, Lp, -1}));
      x[p] = rest_of(p, xp, hp);
      x[o] = xo_out;
      // Join. Tensors the side stream used stay referenced until here, so their memory is not reused
      // by work that could run before the side stream is done.
      other_done.block(main);
      if (carry) *carry = ResidualCarry{mlp_out, gate_m};
      return x;
    }
#endif
    // Self attention on the modulated norm1 (all streams together).
    for (size_t i = 0; i < S; ++i) std::tie(x[i], h[i]) = norm1_of(i);
    h = self_attn->forward(h);
    for (size_t i = 0; i < S; ++i) x[i] = rest_of(i, x[i], h[i]);
    if (carry) *carry = ResidualCarry{mlp_out, gate_m};
    return x;
  }
  // Off the fused path: a pending residual is applied first.
  x = incoming.apply(x);
  // Self attention on the modulated norm1; gated residual x + h * gate.
  for (size_t i = 0; i < S; ++i) h[i] = modulate(norm1[i], x[i], scale_msa, shift_msa, affine_msa);
  h = self_attn->forward(h);
  for (size_t i = 0; i < S; ++i) x[i] = torch::addcmul(x[i], h[i], gate_msa);
  // Cross attention over the condition on the affine norm2 (no modulation).
  for (size_t i = 0; i < S; ++i) {
    auto hi = fast ? fused::layer_norm_affine_bf16(x[i], norm2[i]->weight.unsqueeze(0), norm2[i]->bias.unsqueeze(0), norm2[i]->eps, low)
                   : norm2[i]->forward(x[i]);
    x[i] = x[i] + (kv ? cross_attn[i]->attend(hi, (*kv)[i].first, (*kv)[i].second) : cross_attn[i]->forward(hi, cond));
  }
  // MLP on the modulated norm3; gated residual.
  for (size_t i = 0; i < S; ++i) x[i] = torch::addcmul(x[i], mlp[i]->forward(modulate(norm3[i], x[i], scale_mlp, shift_mlp, affine_mlp)), gate_mlp);
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
    for (auto& m : block->mlp) m->inference_kernels = !on;
  }
}

void SparseStructureFlowTdfyWrapperImpl::set_stream_overlap(bool on) {
  for (auto& block : block_list_) block->stream_overlap = on;
}

ConditionCache SparseStructureFlowTdfyWrapperImpl::condition_cache(const torch::Tensor& cond, int64_t zero_from) {
  SIMU_CHECK(zero_from < 0 || (zero_from > 0 && zero_from <= cond.size(0)),
             "condition_cache: zero_from {} must be in [1, {}] (or negative: none)", zero_from, cond.size(0));
  ConditionCache cache;
  cache.cond = cond;
  cache.zero_from = zero_from;
  auto cond32 = (zero_from >= 0 ? cond.narrow(0, 0, zero_from) : cond).to(torch::kFloat32);
  for (auto& block : block_list_) {
    std::vector<std::pair<torch::Tensor, torch::Tensor>> per_stream;
    for (auto& ca : block->cross_attn) per_stream.push_back(ca->context_kv(cond32));
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
      auto [k, v] = block_list_[b]->cross_attn[i]->context_kv(cond32);
      SIMU_CHECK(k.sizes() == per_stream[i].first.sizes() && v.sizes() == per_stream[i].second.sizes(),
                 "condition_cache_into: keys [{}] do not fit the cache's [{}]", fmt::join(k.sizes(), ", "),
                 fmt::join(per_stream[i].first.sizes(), ", "));
      per_stream[i].first.copy_(k);
      per_stream[i].second.copy_(v);
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
  // Timestep embedding (+ shortcut step embedding), then the shared modulation when share_mod.
  auto t_emb = t_embedder->forward(t);  // [B, C]
  if (d.has_value()) {
    SIMU_CHECK(d_embedder, "flow model: a shortcut step d was given but the model has no d_embedder "
                           "(is_shortcut_model: false)");
    t_emb = t_emb + d_embedder->forward(*d);
  }
  if (c.share_mod) t_emb = adaLN_modulation->forward(t_emb);  // [B, 6C]
  t_emb = t_emb.to(torch::kFloat32);

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
  const auto input_dtype = h.front().scalar_type();
  for (auto& hi : h) hi = hi.to(torch::kFloat32);
  // The condition once in the dtype its projections use: bf16 / fp16 under CUDA autocast in that dtype
  // (the cast every to_kv would otherwise repeat, same values), else fp32.
  const bool low_autocast = cond.is_cuda() && at::autocast::is_autocast_enabled(at::kCUDA) &&
                            fused::is_low_precision(at::autocast::get_autocast_dtype(at::kCUDA));
  auto cond32 = cond.to(low_autocast ? at::autocast::get_autocast_dtype(at::kCUDA) : torch::kFloat32);

  // Transformer blocks; each leaves its last residual to the next one's first LayerNorm (fused path).
  ResidualCarry carry;
  for (size_t b = 0; b < block_list_.size(); ++b) {
    if (!block_wrapper_) {
      h = block_list_[b]->forward(h, t_emb, cond32, cache ? &cache->kv[b] : nullptr, &carry);
      continue;
    }
    // Wrapped: inputs = streams + [modulation, condition]; fn owns the block and the cached keys/values.
    std::vector<torch::Tensor> inputs = h;
    inputs.push_back(t_emb);
    inputs.push_back(cond32);
    const size_t S = h.size();
    auto kv = cache ? std::make_shared<const std::vector<std::pair<torch::Tensor, torch::Tensor>>>(cache->kv[b]) : nullptr;
    BlockFn fn = [block = block_list_[b].ptr(), S, kv](const std::vector<torch::Tensor>& v) {
      return block->forward(std::vector<torch::Tensor>(v.begin(), v.begin() + S), v[S], v[S + 1], kv.get());
    };
    h = block_wrapper_(static_cast<int64_t>(b), *block_list_[b], inputs, fn);
  }
  h = carry.apply(h);
  for (auto& hi : h) hi = hi.to(input_dtype);

  // Split streams back into latents and project out.
  std::map<std::string, torch::Tensor> split;
  for (size_t i = 0; i < streams_.size(); ++i) {
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
  for (const auto& s : c.latents) out[s.name] = latent_mapping.at(s.name)->to_output(split.at(s.name));
  return out;
}

double flow_forward_flops(const FlowModelConfig& c, int64_t batch, int64_t cond_len) {
  const double C = static_cast<double>(c.model_channels), Cc = static_cast<double>(c.cond_channels);
  const double Lc = static_cast<double>(cond_len), hidden = std::floor(C * c.mlp_ratio);
  // Tokens per stream and keys each stream attends to.
  const auto streams = c.stream_names();
  double total_tokens = 0, protected_tokens = 0;
  std::map<std::string, double> tokens;
  for (const auto& s : streams) {
    double t = 0;
    const auto g = std::find_if(c.share_groups.begin(), c.share_groups.end(), [&](const auto& p) { return p.first == s; });
    if (g == c.share_groups.end()) t = static_cast<double>(c.latent(s).tokens());
    else
      for (const auto& m : g->second) t += static_cast<double>(c.latent(m).tokens());
    tokens[s] = t;
    total_tokens += t;
    if (std::find(c.protected_modalities.begin(), c.protected_modalities.end(), s) != c.protected_modalities.end())
      protected_tokens += t;
  }
  double block = 0;
  for (const auto& s : streams) {
    const double T = tokens[s];
    const bool prot = std::find(c.protected_modalities.begin(), c.protected_modalities.end(), s) != c.protected_modalities.end();
    const double keys = prot ? T : total_tokens;  // protected: itself; others: everything
    block += 2 * T * C * 3 * C + 2 * T * C * C;                 // self qkv + out
    block += 2 * 2 * T * keys * C;                              // self QK^T + PV
    block += 2 * T * C * C + 2 * Lc * Cc * 2 * C + 2 * T * C * C;  // cross q, kv, out
    block += 2 * 2 * T * Lc * C;                                // cross QK^T + PV
    block += 2 * 2 * T * C * hidden;                            // MLP
  }
  (void)protected_tokens;
  double io = 0;
  for (const auto& l : c.latents) io += 2 * 2 * static_cast<double>(l.tokens()) * C * l.in_channels;
  const double ada = (c.share_mod ? 1.0 : static_cast<double>(c.num_blocks)) * 2 * C * 6 * C;
  return batch * (c.num_blocks * block + io + ada);
}

double flow_condition_kv_flops(const FlowModelConfig& c, int64_t batch, int64_t cond_len) {
  const double streams = static_cast<double>(c.stream_names().size());
  return batch * c.num_blocks * streams * 2.0 * cond_len * c.cond_channels * 2.0 * c.model_channels;
}

}  // namespace simu::models
