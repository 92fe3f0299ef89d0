#include "training/optim.h"

#include <cmath>

#include <fmt/ranges.h>

#include "common/error.h"

namespace simu::training {

OptimConfig OptimConfig::from(simu::config::Reader& r) {
  OptimConfig c;
  r.field("lr", c.lr);
  r.field("betas", c.betas);
  r.field("eps", c.eps);
  r.field("weight_decay", c.weight_decay);
  r.field("warmup_steps", c.warmup_steps);
  r.field("schedule", c.schedule);
  r.field("min_lr_ratio", c.min_lr_ratio);
  r.field("clip_grad_norm", c.clip_grad_norm);
  SIMU_CHECK(c.lr > 0, "{}: optim.lr must be > 0, got {}", r.file(), c.lr);
  SIMU_CHECK(c.betas.size() == 2 && c.betas[0] >= 0 && c.betas[0] < 1 && c.betas[1] >= 0 && c.betas[1] < 1,
             "{}: optim.betas must be two numbers in [0, 1)", r.file());
  SIMU_CHECK(c.eps > 0, "{}: optim.eps must be > 0", r.file());
  SIMU_CHECK(c.weight_decay >= 0, "{}: optim.weight_decay must be >= 0", r.file());
  SIMU_CHECK(c.warmup_steps >= 0, "{}: optim.warmup_steps must be >= 0", r.file());
  SIMU_CHECK(c.schedule == "constant" || c.schedule == "cosine",
             "{}: optim.schedule: expected 'constant' or 'cosine', got '{}'", r.file(), c.schedule);
  return c;
}

double learning_rate(const OptimConfig& cfg, int64_t step, int64_t total_steps) {
  // Linear warm-up.
  if (step < cfg.warmup_steps) return cfg.lr * static_cast<double>(step + 1) / static_cast<double>(cfg.warmup_steps);
  if (cfg.schedule == "constant") return cfg.lr;
  // Cosine from lr (first step after warm-up) to lr*min_lr_ratio (last step).
  const double span = std::max<double>(1.0, static_cast<double>(total_steps - 1 - cfg.warmup_steps));
  const double p = std::min(1.0, static_cast<double>(step - cfg.warmup_steps) / span);
  const double floor = cfg.lr * cfg.min_lr_ratio;
  return floor + (cfg.lr - floor) * 0.5 * (1.0 + std::cos(M_PI * p));
}

double global_grad_norm(const std::vector<torch::Tensor>& params) {
  // Sum of squared per-tensor norms, in float64.
  double sq = 0.0;
  for (const auto& p : params) {
    if (!p.grad().defined()) continue;
    const double n = p.grad().detach().to(torch::kFloat64).norm().item<double>();
    sq += n * n;
  }
  return std::sqrt(sq);
}

double clip_grad_norm(const std::vector<torch::Tensor>& params, double max_norm) {
  const double norm = global_grad_norm(params);
  if (max_norm > 0) {
    // PyTorch: clip_coef = max_norm / (total_norm + 1e-6), clamped to 1.
    const double coef = max_norm / (norm + 1e-6);
    if (coef < 1.0) {
      torch::NoGradGuard ng;
      for (const auto& p : params)
        if (p.grad().defined()) p.grad().mul_(coef);
    }
  }
  return norm;
}

AdamW::AdamW(std::vector<std::pair<std::string, torch::Tensor>> params, const OptimConfig& cfg)
    : params_(std::move(params)) {
  SIMU_CHECK(!params_.empty(), "AdamW: no trainable parameters (were the adapters injected?)");
  auto opts = torch::optim::AdamWOptions(cfg.lr)
                  .betas({cfg.betas.at(0), cfg.betas.at(1)})
                  .eps(cfg.eps)
                  .weight_decay(cfg.weight_decay);
  opt_ = std::make_unique<torch::optim::AdamW>(tensors(), opts);
}

std::vector<torch::Tensor> AdamW::tensors() const {
  std::vector<torch::Tensor> out;
  for (const auto& [n, p] : params_) out.push_back(p);
  return out;
}

void AdamW::step(double lr) {
  for (auto& group : opt_->param_groups()) static_cast<torch::optim::AdamWOptions&>(group.options()).lr(lr);
  opt_->step();
}

void AdamW::zero_grad() { opt_->zero_grad(/*set_to_none=*/true); }

std::map<std::string, torch::Tensor> AdamW::state_dict() const {
  std::map<std::string, torch::Tensor> out;
  auto& state = opt_->state();
  for (const auto& [name, p] : params_) {
    auto it = state.find(p.unsafeGetTensorImpl());
    if (it == state.end()) continue;  // no step taken yet
    auto& s = static_cast<torch::optim::AdamWParamState&>(*it->second);
    out[name + ".exp_avg"] = s.exp_avg().detach().to(torch::kCPU).clone();
    out[name + ".exp_avg_sq"] = s.exp_avg_sq().detach().to(torch::kCPU).clone();
    out[name + ".step"] = torch::tensor(s.step(), torch::kInt64);
  }
  return out;
}

void AdamW::load_state_dict(const std::map<std::string, torch::Tensor>& state, const std::string& source) {
  std::vector<std::string> problems;
  auto& st = opt_->state();
  st.clear();
  for (const auto& [name, p] : params_) {
    auto a = state.find(name + ".exp_avg"), b = state.find(name + ".exp_avg_sq"), s = state.find(name + ".step");
    if (a == state.end() && b == state.end() && s == state.end()) continue;  // saved before the first step
    if (a == state.end() || b == state.end() || s == state.end()) {
      problems.push_back(fmt::format("{}: incomplete state (exp_avg, exp_avg_sq, step)", name));
      continue;
    }
    if (a->second.sizes() != p.sizes() || b->second.sizes() != p.sizes()) {
      problems.push_back(fmt::format("{}: state shape {} vs parameter {}", name, fmt::join(a->second.sizes(), "x"),
                                     fmt::join(p.sizes(), "x")));
      continue;
    }
    auto ps = std::make_unique<torch::optim::AdamWParamState>();
    ps->step(s->second.item<int64_t>());
    ps->exp_avg(a->second.to(p.device(), p.scalar_type()).clone());
    ps->exp_avg_sq(b->second.to(p.device(), p.scalar_type()).clone());
    st[p.unsafeGetTensorImpl()] = std::move(ps);
  }
  if (!problems.empty()) fail("{}: optimizer state does not match the adapters:\n  {}", source, fmt::join(problems, "\n  "));
}

}  // namespace simu::training
