#include "training/fmdpo.h"

#include <cmath>

#include <ATen/CPUGeneratorImpl.h>
#include <ATen/autocast_mode.h>

#include <mutex>

#include "common/config_check.h"
#include "common/error.h"
#include "common/random.h"
#include "training/staging.h"

namespace simu::training {

ObjectiveConfig ObjectiveConfig::from(simu::config::Reader& r) {
  ObjectiveConfig c;
  r.field("beta", c.beta);
  r.field("weight_completion", c.weight_completion);
  r.field("weight_preservation", c.weight_preservation);
  r.field("t_mean", c.t_mean);
  r.field("t_std", c.t_std);
  // Domains: finite values only; beta is the DPO temperature (the paper's range is 10^2..10^4).
  simu::config::check_in(r, "beta", c.beta, 0, 1e6, true, "(0, 1e6]");
  simu::config::check_in(r, "weight_completion", c.weight_completion, 0, 1e6, false, "[0, 1e6]");
  simu::config::check_in(r, "weight_preservation", c.weight_preservation, 0, 1e6, false, "[0, 1e6]");
  simu::config::check_in(r, "t_mean", c.t_mean, -100, 100, false, "[-100, 100]");
  simu::config::check_in(r, "t_std", c.t_std, 0, 100, true, "(0, 100]");
  return c;
}

double ObjectiveConfig::weight_of(data::PairKind kind) const {
  if (kind == data::PairKind::OcclusionCompletion) return weight_completion;
  if (kind == data::PairKind::CleanPreservation) return weight_preservation;
  fail("pair kind {} unknown (0 = occlusion completion, 1 = clean preservation)", static_cast<int>(kind));
}

torch::Tensor flow_mse(const torch::Tensor& pred, const torch::Tensor& target) {
  // [B, ...] -> [B]
  auto diff = pred.to(torch::kFloat32) - target.to(torch::kFloat32);
  return diff.pow(2).flatten(1).mean(1);
}

namespace {

// Keeps the closure of a checkpointed segment and the RNG states it started from alive in the
// autograd context.
struct SegmentHolder : torch::CustomClassHolder {
  SegmentFn fn;
  torch::Tensor cpu_rng;                 // CPU default generator state at the segment's forward
  std::vector<std::pair<torch::Device, torch::Tensor>> cuda_rng;  // per CUDA device of the inputs
};

// Autocast state to replay in the backward recompute (the engine thread has its own).
struct AutocastState {
  bool cuda = false, cpu = false;
  at::ScalarType cuda_dtype = at::kBFloat16, cpu_dtype = at::kBFloat16;
  static AutocastState capture() {
    AutocastState s;
    s.cuda = at::autocast::is_autocast_enabled(at::kCUDA);
    s.cpu = at::autocast::is_autocast_enabled(at::kCPU);
    s.cuda_dtype = at::autocast::get_autocast_dtype(at::kCUDA);
    s.cpu_dtype = at::autocast::get_autocast_dtype(at::kCPU);
    return s;
  }
  void apply() const {
    at::autocast::set_autocast_enabled(at::kCUDA, cuda);
    at::autocast::set_autocast_enabled(at::kCPU, cpu);
    at::autocast::set_autocast_dtype(at::kCUDA, cuda_dtype);
    at::autocast::set_autocast_dtype(at::kCPU, cpu_dtype);
  }
};

// Autocast's weight cache off for a scope (restored at exit).
struct AutocastCacheOff {
  bool before = at::autocast::is_autocast_cache_enabled();
  AutocastCacheOff() { at::autocast::set_autocast_cache_enabled(false); }
  ~AutocastCacheOff() { at::autocast::set_autocast_cache_enabled(before); }
};

// State of a default generator (under its lock).
torch::Tensor rng_get(at::Generator g) {
  std::lock_guard<std::mutex> lock(g.mutex());
  return g.get_state();
}
void rng_set(at::Generator g, const torch::Tensor& state) {
  std::lock_guard<std::mutex> lock(g.mutex());
  g.set_state(state);
}

// Sets the default generators to the states saved at the segment's forward; restores the current
// ones at scope exit (so a recompute draws the same dropout masks and leaves the stream untouched).
struct RngReplay {
  const SegmentHolder& h;
  torch::Tensor cpu_now;
  std::vector<torch::Tensor> cuda_now;
  explicit RngReplay(const SegmentHolder& holder) : h(holder) {
    cpu_now = rng_get(at::detail::getDefaultCPUGenerator());
    rng_set(at::detail::getDefaultCPUGenerator(), h.cpu_rng);
    for (const auto& [dev, state] : h.cuda_rng) {
      auto g = at::globalContext().defaultGenerator(dev);
      cuda_now.push_back(rng_get(g));
      rng_set(g, state);
    }
  }
  ~RngReplay() {
    rng_set(at::detail::getDefaultCPUGenerator(), cpu_now);
    for (size_t i = 0; i < h.cuda_rng.size(); ++i) rng_set(at::globalContext().defaultGenerator(h.cuda_rng[i].first), cuda_now[i]);
  }
};

struct CheckpointFunction : public torch::autograd::Function<CheckpointFunction> {
  // all = inputs (first n_inputs) + params; returns fn(inputs), computed without a graph.
  static torch::autograd::variable_list forward(torch::autograd::AutogradContext* ctx,
                                                at::TensorList all_list, int64_t n_inputs,
                                                c10::intrusive_ptr<SegmentHolder> holder) {
    const torch::autograd::variable_list all(all_list.begin(), all_list.end());
    const auto ac = AutocastState::capture();
    // RNG states this forward starts from (CPU, and every CUDA device among the inputs).
    holder->cpu_rng = rng_get(at::detail::getDefaultCPUGenerator());
    holder->cuda_rng.clear();
    for (int64_t i = 0; i < n_inputs; ++i) {
      const auto dev = all[i].device();
      if (!dev.is_cuda()) continue;
      bool seen = false;
      for (const auto& [d, st] : holder->cuda_rng) seen = seen || d == dev;
      if (!seen) holder->cuda_rng.emplace_back(dev, rng_get(at::globalContext().defaultGenerator(dev)));
    }
    ctx->saved_data["n_inputs"] = n_inputs;
    ctx->saved_data["fn"] = c10::IValue::make_capsule(c10::intrusive_ptr<torch::CustomClassHolder>(holder));
    ctx->saved_data["ac_cuda"] = ac.cuda;
    ctx->saved_data["ac_cpu"] = ac.cpu;
    ctx->saved_data["ac_cuda_dtype"] = static_cast<int64_t>(ac.cuda_dtype);
    ctx->saved_data["ac_cpu_dtype"] = static_cast<int64_t>(ac.cpu_dtype);
    ctx->save_for_backward(all);
    std::vector<torch::Tensor> ins(all.begin(), all.begin() + n_inputs);
    // No graph kept (custom functions already run forward with grad mode off), and no graph-less bf16
    // copies of the adapter weights left in the autocast cache for a later forward of this scope.
    torch::NoGradGuard no_grad;
    AutocastCacheOff no_cache;
    return holder->fn(ins);
  }

  static torch::autograd::variable_list backward(torch::autograd::AutogradContext* ctx,
                                                 torch::autograd::variable_list grad_out) {
    auto saved = ctx->get_saved_variables();
    const int64_t n_inputs = ctx->saved_data["n_inputs"].toInt();
    auto holder = c10::static_intrusive_pointer_cast<SegmentHolder>(ctx->saved_data["fn"].toCapsule());
    AutocastState ac;
    ac.cuda = ctx->saved_data["ac_cuda"].toBool();
    ac.cpu = ctx->saved_data["ac_cpu"].toBool();
    ac.cuda_dtype = static_cast<at::ScalarType>(ctx->saved_data["ac_cuda_dtype"].toInt());
    ac.cpu_dtype = static_cast<at::ScalarType>(ctx->saved_data["ac_cpu_dtype"].toInt());
    // Recompute with a graph: inputs detached (fresh leaves), parameters as they are; same autocast
    // and RNG states as the forward.
    std::vector<torch::Tensor> ins;
    std::vector<torch::Tensor> targets;
    std::vector<int64_t> target_index;
    for (int64_t i = 0; i < static_cast<int64_t>(saved.size()); ++i) {
      torch::Tensor v = saved[i];
      if (i < n_inputs) {
        v = v.detach().requires_grad_(saved[i].requires_grad());
        ins.push_back(v);
      }
      if (v.requires_grad()) {
        targets.push_back(v);
        target_index.push_back(i);
      }
    }
    std::vector<torch::Tensor> outs;
    {
      const auto before = AutocastState::capture();
      // No autocast weight cache here: this thread's cache is never cleared (it would hand later
      // recomputes stale bf16 copies of the adapter weights) and the forward's copies have no graph.
      AutocastCacheOff no_cache;
      RngReplay rng(*holder);
      torch::AutoGradMode grad_on(true);
      ac.apply();
      try {
        outs = holder->fn(ins);
      } catch (...) {
        before.apply();
        throw;
      }
      before.apply();
    }
    SIMU_CHECK(outs.size() == grad_out.size(), "checkpointed segment: recompute gave {} outputs, forward {}",
               outs.size(), grad_out.size());
    // Gradients of the outputs that carry a graph and an incoming gradient, w.r.t. every target.
    std::vector<torch::Tensor> o, go;
    for (size_t k = 0; k < outs.size(); ++k)
      if (outs[k].requires_grad() && grad_out[k].defined()) {
        o.push_back(outs[k]);
        go.push_back(grad_out[k]);
      }
    torch::autograd::variable_list grads(saved.size() + 2);
    if (!targets.empty() && !o.empty()) {
      auto g = torch::autograd::grad(o, targets, go, /*retain_graph=*/false, /*create_graph=*/false,
                                     /*allow_unused=*/true);
      for (size_t k = 0; k < g.size(); ++k) grads[target_index[k]] = g[k];
    }
    return grads;
  }
};

// Switches the adapters off for the reference pass and back on at scope exit.
struct AdaptersOff {
  PolicyModel& m;
  explicit AdaptersOff(PolicyModel& model) : m(model) { m.set_adapters_enabled(false); }
  ~AdaptersOff() { m.set_adapters_enabled(true); }
};

}  // namespace

std::vector<torch::Tensor> checkpointed_segment(const SegmentFn& fn, const std::vector<torch::Tensor>& inputs,
                                                const std::vector<torch::Tensor>& params) {
  // Outside a graph (no grad mode, or nothing requires grad) there is nothing to save.
  if (!torch::GradMode::is_enabled()) return fn(inputs);
  auto holder = c10::make_intrusive<SegmentHolder>();
  holder->fn = fn;
  torch::autograd::variable_list all(inputs.begin(), inputs.end());
  all.insert(all.end(), params.begin(), params.end());
  // Passed as a TensorList so that autograd sees every tensor as an input (a std::vector is not).
  return CheckpointFunction::apply(at::TensorList(all), static_cast<int64_t>(inputs.size()), holder);
}

torch::Tensor checkpointed(const std::function<torch::Tensor(const std::vector<torch::Tensor>&)>& fn,
                           const std::vector<torch::Tensor>& inputs, const std::vector<torch::Tensor>& params) {
  return checkpointed_segment([fn](const std::vector<torch::Tensor>& v) { return std::vector<torch::Tensor>{fn(v)}; },
                              inputs, params)[0];
}

PairNoise draw_pair_noise(uint64_t seed, int64_t step, int64_t pair_id, at::IntArrayRef latent_shape, double t_mean,
                          double t_std) {
  auto gen = sample_generator(seed, step, pair_id);
  PairNoise n;
  const auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  // t = sigmoid(N(mean, std)): the official logit-normal training sampler.
  n.t = torch::sigmoid(at::randn(std::vector<int64_t>{}, gen, f32) * t_std + t_mean);
  n.eps_pos = at::randn(latent_shape, gen, f32);
  n.eps_neg = at::randn(latent_shape, gen, f32);
  return n;
}

FmdpoTerms fmdpo_terms(PolicyModel& model, const FmdpoInputs& in, double beta, bool checkpoint) {
  const int64_t B = in.x_pos.size(0);
  SIMU_CHECK(in.x_neg.sizes() == in.x_pos.sizes() && in.eps_pos.sizes() == in.x_pos.sizes() &&
                 in.eps_neg.sizes() == in.x_pos.sizes(),
             "fmdpo: x_pos, x_neg, eps_pos, eps_neg must share one shape");
  SIMU_CHECK(in.t.dim() == 1 && in.t.size(0) == B && in.w.size(0) == B && in.cond.size(0) == B,
             "fmdpo: t, w and cond must have one entry per pair ({})", B);
  // Noised latents and velocity targets, both members stacked pair-major: row 2b = x+ of pair b, row
  // 2b + 1 = its x- ([2B, T, C]), so a pair's two rows are adjacent (shared-condition attention by views).
  auto t = in.t.to(torch::kFloat32).view({B, 1, 1});
  auto members = [](const torch::Tensor& pos, const torch::Tensor& neg) {
    return torch::stack({pos, neg}, 1).flatten(0, 1);  // [B, 2, ...] -> [2B, ...]
  };
  auto xt = members((1 - t) * in.eps_pos + t * in.x_pos, (1 - t) * in.eps_neg + t * in.x_neg);
  auto target = members(in.x_pos - in.eps_pos, in.x_neg - in.eps_neg);
  auto t_scaled = members(in.t, in.t).to(torch::kFloat32) * 1000.0;  // [2B]
  // Both members share the pair's condition: [B, L, Cc] once where the model accepts it, else [2B, L, Cc]
  // (each row repeated for its two members).
  auto cond = model.shares_condition() ? in.cond : members(in.cond, in.cond);
  auto d = torch::zeros({2 * B}, t_scaled.options());  // no shortcut

  FmdpoTerms out;
  // Policy: adapters on, with graph.
  torch::Tensor pred;
  if (checkpoint && model.set_block_checkpointing(true)) {
    // Per transformer block: each block recomputes in backward; switched off again for the reference.
    struct BlocksOff {
      PolicyModel& m;
      ~BlocksOff() { m.set_block_checkpointing(false); }
    } off{model};
    pred = model.predict_shape(xt, t_scaled, cond, d);
  } else if (checkpoint) {
    // A model without blocks: the whole forward is one segment.
    std::vector<torch::Tensor> params;
    for (auto& [n, p] : model.adapter_parameters()) params.push_back(p);
    pred = checkpointed(
        [&model](const std::vector<torch::Tensor>& v) { return model.predict_shape(v[0], v[1], v[2], v[3]); },
        {xt, t_scaled, cond, d}, params);
  } else {
    pred = model.predict_shape(xt, t_scaled, cond, d);
  }
  auto l_pol = flow_mse(pred, target).view({B, 2});  // [B, (x+, x-)]
  out.loss_pos_policy = l_pol.select(1, 0);
  out.loss_neg_policy = l_pol.select(1, 1);
  // Reference: adapters off, no graph, same inputs.
  {
    torch::NoGradGuard no_grad;
    AdaptersOff off(model);
    auto l_ref = flow_mse(model.predict_shape(xt, t_scaled, cond, d), target).view({B, 2});
    out.loss_pos_ref = l_ref.select(1, 0);
    out.loss_neg_ref = l_ref.select(1, 1);
  }
  out.d_theta = out.loss_pos_policy - out.loss_neg_policy;
  out.d_ref = out.loss_pos_ref - out.loss_neg_ref;
  out.per_pair = -torch::log_sigmoid(-beta / 2.0 * (out.d_theta - out.d_ref));
  out.loss = (in.w.to(torch::kFloat32) * out.per_pair).mean();
  return out;
}

}  // namespace simu::training
