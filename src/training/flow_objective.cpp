// Stage-1 flow matching: staging, the loss and its backward, metrics, EMA, export (flow_objective.h).
#include "training/flow_objective.h"

#include <cmath>
#include <filesystem>

#include <fmt/ranges.h>

#include "common/error.h"
#include "models/precision.h"
#include "training/fmdpo.h"
#include "training/staging.h"
#include "training/trainer.h"

namespace simu::training {

namespace stdfs = std::filesystem;

namespace {

// One micro-batch: gathered rows and the samples' draws, on the device.
struct FlowGroup {
  std::map<std::string, torch::Tensor> inputs;  // stored dtypes [m, ch, s, s]
  torch::Tensor occupancy;                      // [m, R, R, R] uint8
  std::map<std::string, torch::Tensor> pose;    // [m, k] float32
  torch::Tensor t, drop, d, cfg_target;         // [m] float32 (drop, cfg_target: 0 / 1)
  std::vector<torch::Tensor> eps;               // per latent [m, T, C]
  std::vector<int64_t> shortcut_rows;           // rows with d > 0 (known on the host: no device sync)
  std::vector<int64_t> shortcut_cfg;            // positions among shortcut_rows whose target uses CFG
  Uploads uploads;
  std::vector<torch::Tensor*> device_tensors() {
    std::vector<torch::Tensor*> out{&occupancy, &t, &drop, &d, &cfg_target};
    for (auto& [k, v] : inputs) out.push_back(&v);
    for (auto& [k, v] : pose) out.push_back(&v);
    for (auto& v : eps) out.push_back(&v);
    return out;
  }
};

struct FlowBatch : StagedBatch {
  std::vector<FlowGroup> groups;
};

// Rows `idx` of every tensor of a list.
std::vector<torch::Tensor> rows_of(const std::vector<torch::Tensor>& xs, const torch::Tensor& idx) {
  std::vector<torch::Tensor> out;
  for (const auto& x : xs) out.push_back(x.index_select(0, idx));
  return out;
}

}  // namespace

SampleDraws draw_sample(uint64_t seed, int64_t step, int64_t sample_id, const std::vector<std::vector<int64_t>>& shapes,
                        const FlowObjectiveConfig& c) {
  auto gen = sample_generator(seed, step, sample_id);
  const auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  SampleDraws s;
  // t = sigmoid(N(mean, std)): the official logit-normal training sampler.
  s.t = torch::sigmoid(at::randn(std::vector<int64_t>{}, gen, f32) * c.t_std + c.t_mean);
  for (const auto& shape : shapes) s.eps.push_back(at::randn(shape, gen, f32));
  const auto u = at::rand({4}, gen, f32);
  const auto a = u.accessor<float, 1>();
  s.drop_condition = a[0] < c.p_unconditional;
  if (a[1] < c.shortcut_fraction) s.d = 1.0f / static_cast<float>(1 << std::min(7, static_cast<int>(a[2] * 8)));
  s.cfg_target = a[3] < c.shortcut_cfg_ratio;
  return s;
}

FlowObjective::FlowObjective(Stage1Config cfg, Stage1Model model, std::shared_ptr<const Stage1Samples> samples,
                             ShapeTargetFn targets, torch::Device device)
    : cfg_(std::move(cfg)), model_(std::move(model)), samples_(std::move(samples)), targets_(std::move(targets)),
      device_(device) {
  const auto& gc = model_->generator->config();
  const auto& fc = gc.backbone;
  shortcut_model_ = fc.is_shortcut_model;
  for (const auto& spec : fc.latents) {
    latents_.push_back(spec.name);
    shapes_.push_back({spec.tokens(), spec.in_channels});
    if (spec.name == "shape") continue;
    const auto it = samples_->pose.find(spec.name);
    if (it == samples_->pose.end() || it->second.size(1) != spec.tokens() * spec.in_channels)
      fail("{}: the flow model's latent '{}' ([{}, {}]) has no matching pose latent in the samples", cfg_.file,
           spec.name, spec.tokens(), spec.in_channels);
  }
  SIMU_CHECK(std::find(latents_.begin(), latents_.end(), "shape") != latents_.end(),
             "{}: the flow model has no 'shape' latent", cfg_.model.generator);
  for (const auto& [name, w] : cfg_.objective.latent_weights)
    if (std::find(latents_.begin(), latents_.end(), name) == latents_.end())
      fail("{}: key 'objective.latent_weights.{}': the flow model has no such latent ({})", cfg_.file, name,
           fmt::join(latents_, ", "));
  if (cfg_.objective.shortcut_fraction > 0 && !shortcut_model_)
    fail_hint("set objective.shortcut_fraction: 0, or train a shortcut model (is_shortcut_model: true)",
              "{}: shortcut targets need a shortcut model (d embedder); {} has none", cfg_.file, cfg_.model.generator);
  if (cfg_.objective.p_unconditional > 0 && gc.unconditional_handling == "add_flag" && !fc.force_zeros_cond)
    fail_hint("set force_zeros_cond: true in the flow model, or unconditional_handling: zeros",
              "{}: condition dropout would change nothing: with add_flag and force_zeros_cond false the model's "
              "unconditional branch is the conditional one", cfg_.model.generator);
  // Per-block activation checkpointing over each block's (trained) parameters.
  if (cfg_.train.activation_checkpointing)
    model_->backbone()->set_block_wrapper([](int64_t, torch::nn::Module& block, const std::vector<torch::Tensor>& inputs,
                                             const models::BlockFn& fn) {
      std::vector<torch::Tensor> params;
      for (auto& p : block.parameters())
        if (p.requires_grad()) params.push_back(p);
      return checkpointed_segment(fn, inputs, params);
    });
  torch::NoGradGuard no_grad;
  for (const auto& [name, p] : model_->named_weights()) ema_.emplace_back(name, p.detach().clone());
}

void FlowObjective::open_data(int rank, int world, int64_t global_batch, uint64_t seed, DataPosition position) {
  order_ = std::make_unique<EpochOrder>(samples_->size(), rank, world, global_batch, seed, position);
}

std::unique_ptr<StagedBatch> FlowObjective::read_batch(int64_t step, const UploadStream& stream) {
  auto b = std::make_unique<FlowBatch>();
  b->position = order_->position();
  b->step = step;
  const auto rows = order_->next();
  const int64_t n = static_cast<int64_t>(rows.size());
  b->samples = n;
  for (int64_t m0 = 0; m0 < n; m0 += cfg_.data.micro_batch) {
    FlowGroup g;
    const std::vector<int64_t> idx(rows.begin() + m0, rows.begin() + std::min(n, m0 + cfg_.data.micro_batch));
    const auto sel = torch::tensor(idx, torch::kInt64);
    auto gather = [&](const torch::Tensor& src) { return gather_to(src, sel, device_, stream, g.uploads.host); };
    for (const auto& [name, v] : samples_->inputs) g.inputs[name] = gather(v);
    g.occupancy = gather(samples_->occupancy);
    for (const auto& [name, v] : samples_->pose) g.pose[name] = gather(v);
    // Each sample's draws (by its record index: independent of rank, micro-batch and read-ahead).
    std::vector<torch::Tensor> ts, drop, d, cfgt;
    std::vector<std::vector<torch::Tensor>> eps(latents_.size());
    for (int64_t i : idx) {
      auto s = draw_sample(cfg_.train.seed, step, samples_->ids[i], shapes_, cfg_.objective);
      ts.push_back(s.t);
      drop.push_back(torch::tensor(s.drop_condition ? 1.0f : 0.0f));
      d.push_back(torch::tensor(s.d));
      cfgt.push_back(torch::tensor(s.cfg_target ? 1.0f : 0.0f));
      if (s.d > 0) {
        if (s.cfg_target) g.shortcut_cfg.push_back(static_cast<int64_t>(g.shortcut_rows.size()));
        g.shortcut_rows.push_back(static_cast<int64_t>(ts.size()) - 1);
      }
      for (size_t l = 0; l < eps.size(); ++l) eps[l].push_back(s.eps[l]);
    }
    auto up = [&](const std::vector<torch::Tensor>& parts) { return stack_to(parts, device_, stream, g.uploads.host); };
    g.t = up(ts);
    g.drop = up(drop);
    g.d = up(d);
    g.cfg_target = up(cfgt);
    for (auto& e : eps) g.eps.push_back(up(e));
    g.uploads.record(stream);
    b->groups.push_back(std::move(g));
  }
  return b;
}

std::vector<torch::Tensor> FlowObjective::velocity(const std::vector<torch::Tensor>& x, const torch::Tensor& t,
                                                   const torch::Tensor& cond, const torch::Tensor& d) {
  const auto& gc = model_->generator->config();
  const bool bf16 = cfg_.train.precision == "bf16" && device_.is_cuda();
  models::Latents in;
  for (size_t l = 0; l < latents_.size(); ++l) in[latents_[l]] = x[l];
  models::Latents out;
  {
    models::Autocast ac(models::Precision::kBf16, bf16);
    const c10::optional<torch::Tensor> dd = shortcut_model_ ? c10::optional<torch::Tensor>(d * gc.time_scale) : c10::nullopt;
    out = model_->backbone()->forward(in, t * gc.time_scale, cond, dd);
  }
  std::vector<torch::Tensor> v;
  for (const auto& name : latents_) v.push_back(out.at(name).to(torch::kFloat32));
  return v;
}

std::vector<torch::Tensor> FlowObjective::shortcut_targets(const std::vector<torch::Tensor>& x_t, const torch::Tensor& t,
                                                           const torch::Tensor& d, const torch::Tensor& cond,
                                                           const torch::Tensor& cfg_idx) {
  torch::NoGradGuard no_grad;
  const double g = cfg_.objective.shortcut_cfg_strength;
  const bool zeros = model_->generator->config().unconditional_handling == "zeros";
  const auto shape = std::find(latents_.begin(), latents_.end(), "shape") - latents_.begin();
  // The model's step-d velocity, with CFG on the shape latent of the cfg rows (official cfg_modalities).
  auto v = [&](const std::vector<torch::Tensor>& x, const torch::Tensor& tt) {
    auto vc = velocity(x, tt, cond, d);
    if (cfg_idx.numel() > 0 && g > 0) {
      const auto dc = d.index_select(0, cfg_idx);
      auto vu = velocity(rows_of(x, cfg_idx), tt.index_select(0, cfg_idx), cond.index_select(0, cfg_idx) * 0,
                         zeros ? dc * 0 : dc);
      auto guided = (1 + g) * vc[shape].index_select(0, cfg_idx) - g * vu[shape];
      vc[shape] = vc[shape].index_copy(0, cfg_idx, guided);
    }
    return vc;
  };
  const auto s_t = v(x_t, t);
  std::vector<torch::Tensor> x_td;
  for (size_t l = 0; l < x_t.size(); ++l) x_td.push_back(x_t[l] + s_t[l] * d.view({-1, 1, 1}));
  const auto s_td = v(x_td, t + d);
  std::vector<torch::Tensor> out;
  for (size_t l = 0; l < s_t.size(); ++l) out.push_back((s_t[l] + s_td[l]) / 2);
  return out;
}

torch::Tensor FlowObjective::forward_backward(StagedBatch& staged) {
  auto& batch = static_cast<FlowBatch&>(staged);
  const auto& gc = model_->generator->config();
  const double sigma = gc.sigma_min;
  const bool bf16 = cfg_.train.precision == "bf16" && device_.is_cuda();
  const double f = cfg_.objective.shortcut_fraction;
  const auto shape = std::find(latents_.begin(), latents_.end(), "shape") - latents_.begin();
  std::vector<torch::Tensor> metric_terms;
  for (auto& g : batch.groups) {
    g.uploads.wait(g.device_tensors(), device_);
    const int64_t m = g.t.size(0);
    // Targets x1 (no gradient): the shape latent of the occupancy (fp32), the pose latents as stored.
    std::vector<torch::Tensor> x1(latents_.size());
    {
      torch::NoGradGuard no_grad;
      models::Autocast fp32(models::Precision::kFp32, device_.is_cuda());
      x1[shape] = targets_(g.occupancy);  // [m, T, C]
    }
    const auto pose = pose_latents(g.pose);
    for (size_t l = 0; l < latents_.size(); ++l)
      if (static_cast<int64_t>(l) != shape) x1[l] = pose.at(latents_[l]);  // [m, 1, k]
    // Noised latents and velocity targets.
    const auto t = g.t.view({m, 1, 1});
    std::vector<torch::Tensor> x_t, target;
    for (size_t l = 0; l < latents_.size(); ++l) {
      x_t.push_back((1 - (1 - sigma) * t) * g.eps[l] + t * x1[l]);
      target.push_back(x1[l] - (1 - sigma) * g.eps[l]);
    }
    // The condition, with gradient into the embedder; dropped rows times 0.
    torch::Tensor cond;
    {
      models::Autocast ac(models::Precision::kBf16, bf16);
      cond = model_->embedder->forward(decode_inputs(g.inputs));  // [m, L, Cc]
    }
    const auto keep = 1 - g.drop;  // [m]
    const auto cond_used = cond * keep.view({m, 1, 1}).to(cond.scalar_type());
    // Shortcut rows: targets from two d-steps of the model (conditional, no gradient); asked for 2d.
    const auto sc = g.d > 0;  // [m] bool
    torch::Tensor d_model;
    if (shortcut_model_) {
      d_model = 2 * g.d;
      if (gc.unconditional_handling == "zeros") d_model = d_model * keep;
    }
    if (!g.shortcut_rows.empty()) {
      const auto idx = torch::tensor(g.shortcut_rows, torch::kInt64).to(device_);
      const auto cfg_idx = torch::tensor(g.shortcut_cfg, torch::kInt64).to(device_);
      const auto st = shortcut_targets(rows_of(x_t, idx), g.t.index_select(0, idx), g.d.index_select(0, idx),
                                       cond.detach().index_select(0, idx), cfg_idx);
      for (size_t l = 0; l < target.size(); ++l) target[l] = target[l].index_copy(0, idx, st[l]);
    }
    const auto pred = velocity(x_t, g.t, cond_used, d_model);
    // Per-sample loss: latent-weighted mean squared errors; shortcut and flow samples reweighted.
    std::vector<torch::Tensor> mse;
    auto loss = torch::zeros({m}, g.t.options());
    for (size_t l = 0; l < latents_.size(); ++l) {
      mse.push_back(flow_mse(pred[l], target[l]));  // [m]
      loss = loss + cfg_.objective.weight_of(latents_[l]) * mse.back();
    }
    auto w = torch::ones({m}, g.t.options());
    if (f > 0) w = torch::where(sc, torch::full_like(w, cfg_.objective.shortcut_weight / f), torch::full_like(w, 1 / (1 - f)));
    const auto weighted = w * loss;  // [m]
    // Rank-local mean over its share; the all-reduce averages the ranks -> global mean.
    (weighted.sum() / static_cast<double>(batch.samples)).backward();
    std::vector<torch::Tensor> rows{weighted};
    rows.insert(rows.end(), mse.begin(), mse.end());
    rows.push_back(g.drop);
    rows.push_back(sc.to(torch::kFloat32));
    rows.push_back(x1[shape].pow(2).flatten(1).mean(1));
    metric_terms.push_back(torch::stack(rows).detach().to(torch::kFloat32));  // [4 + L, m]
  }
  return torch::cat(metric_terms, 1);  // [4 + L, samples]
}

std::vector<double> FlowObjective::metric_sums(const torch::Tensor& terms, const StagedBatch&) const {
  std::vector<double> sums(latents_.size() + 4, 0.0);
  if (!terms.defined()) return sums;
  const auto host = terms.to(torch::kCPU, torch::kFloat64).contiguous();
  const auto a = host.accessor<double, 2>();
  // Column by column (micro-batch order), every row.
  for (int64_t b = 0; b < host.size(1); ++b)
    for (int64_t r = 0; r < host.size(0); ++r) sums[r] += a[r][b];
  return sums;
}

void FlowObjective::set_metrics(const std::vector<double>& sums, double n, StepMetrics& m) const {
  const size_t L = latents_.size();
  SIMU_CHECK(sums.size() == L + 4, "flow matching: {} metric sums, {} expected", sums.size(), L + 4);
  m.loss = sums[0] / n;
  for (size_t l = 0; l < L; ++l) m.per_kind["loss/" + latents_[l]] = sums[1 + l] / n;
  m.per_kind["condition_dropped"] = sums[L + 1] / n;
  if (cfg_.objective.shortcut_fraction > 0) m.per_kind["shortcut_share"] = sums[L + 2] / n;
  m.per_kind["target/shape_rms"] = std::sqrt(sums[L + 3] / n);
}

void FlowObjective::after_update(int64_t steps_done) {
  const double s = static_cast<double>(steps_done);
  const double decay = std::min(cfg_.ema.decay, (1 + s) / (10 + s));
  torch::NoGradGuard no_grad;
  std::vector<torch::Tensor> ema, params;
  for (const auto& [name, e] : ema_) ema.push_back(e);
  for (const auto& [name, p] : model_->named_weights()) params.push_back(p.detach());
  // ema + (1 - decay) (p - ema) = decay ema + (1 - decay) p
  at::_foreach_lerp_(ema, params, 1 - decay);
}

std::map<std::string, torch::Tensor> FlowObjective::extra_state() const {
  std::map<std::string, torch::Tensor> out;
  for (const auto& [name, e] : ema_) out["ema." + name] = e.detach().to(torch::kCPU).clone();
  return out;
}

void FlowObjective::load_extra_state(const std::map<std::string, torch::Tensor>& state, const std::string& source) {
  std::vector<std::string> problems;
  for (const auto& [name, e] : ema_) {
    const auto it = state.find("ema." + name);
    if (it == state.end()) problems.push_back("missing ema." + name);
    else if (it->second.sizes() != e.sizes())
      problems.push_back(fmt::format("ema.{}: shape {} vs {}", name, fmt::join(it->second.sizes(), "x"), fmt::join(e.sizes(), "x")));
  }
  if (state.size() != ema_.size())
    problems.push_back(fmt::format("{} tensors in extra.safetensors, {} EMA weights in the model", state.size(), ema_.size()));
  if (!problems.empty())
    fail("{}: the checkpoint's EMA weights do not match the model:\n  {}", source, fmt::join(problems, "\n  "));
  torch::NoGradGuard no_grad;
  for (auto& [name, e] : ema_) e.copy_(state.at("ema." + name));
}

std::string FlowObjective::export_result(const std::string& out_dir) {
  const std::string dir = out_dir + "/model";
  stdfs::create_directories(dir);
  auto tensors = cfg_.export_.weights == "ema" ? ema_ : model_->named_weights();
  for (const auto& kv : model_->named_fixed()) tensors.push_back(kv);
  const auto dtype = cfg_.export_.dtype == "float16" ? torch::kFloat16 : torch::kFloat32;
  save_stage1_weights(dir + "/ss_generator.safetensors", tensors, dtype);
  // The configs beside the weights, so the folder is complete.
  for (const auto& [src, stem] : {std::pair{cfg_.model.generator, "generator"}, std::pair{cfg_.model.embedder, "embedder"}})
    stdfs::copy_file(src, dir + "/" + stem + stdfs::path(src).extension().string(), stdfs::copy_options::overwrite_existing);
  return fmt::format("model ({} weights, {}) in {}/ss_generator.safetensors", cfg_.export_.weights, cfg_.export_.dtype, dir);
}

}  // namespace simu::training
