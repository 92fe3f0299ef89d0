#include "training/optim.h"

#include <cmath>

#include <fmt/ranges.h>

#include "common/config_check.h"
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
  // Domains: finite values only; lr above 1 (or eps above 1e-2) never trains an adapter, it diverges.
  simu::config::check_in(r, "lr", c.lr, 0, 1, true, "(0, 1]");
  SIMU_CHECK(c.betas.size() == 2, "{}: key 'optim.betas': expected two numbers in [0, 1), got {} numbers", r.file(),
             c.betas.size());
  simu::config::check_in(r, "betas", c.betas[0], 0, 0.999999, false, "[0, 1)");
  simu::config::check_in(r, "betas", c.betas[1], 0, 0.999999999, false, "[0, 1)");
  simu::config::check_in(r, "eps", c.eps, 0, 1e-2, true, "(0, 0.01]");
  simu::config::check_in(r, "weight_decay", c.weight_decay, 0, 10, false, "[0, 10]");
  SIMU_CHECK(c.warmup_steps >= 0, "{}: key 'optim.warmup_steps': expected an integer >= 0, got {}", r.file(),
             c.warmup_steps);
  SIMU_CHECK(c.schedule == "constant" || c.schedule == "cosine",
             "{}: key 'optim.schedule': expected 'constant' or 'cosine', got '{}'", r.file(), c.schedule);
  simu::config::check_in(r, "min_lr_ratio", c.min_lr_ratio, 0, 1, false, "[0, 1]");
  SIMU_CHECK(std::isfinite(c.clip_grad_norm), "{}: key 'optim.clip_grad_norm': expected a finite number (<= 0: no "
             "clipping), got {}", r.file(), c.clip_grad_norm);
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

namespace {
// The defined gradients of params.
std::vector<torch::Tensor> defined_grads(const std::vector<torch::Tensor>& params) {
  std::vector<torch::Tensor> out;
  for (const auto& p : params)
    if (p.grad().defined()) out.push_back(p.grad());
  return out;
}
// CUDA gradients' global norm on the device: per-tensor norms in one multi-tensor launch, their
// float64 sum of squares, its square root ([] float64). Shared by the host-sync and device paths.
torch::Tensor device_grad_norm(const std::vector<torch::Tensor>& grads) {
  return torch::stack(at::_foreach_norm(grads, 2)).to(torch::kFloat64).pow(2).sum().sqrt();
}
}  // namespace

double global_grad_norm(const std::vector<torch::Tensor>& params) {
  const auto grads = defined_grads(params);
  if (grads.empty()) return 0.0;
  // CUDA: per-tensor norms in one multi-tensor launch, their float64 sum of squares on the device,
  // one host sync.
  if (grads.front().is_cuda()) return device_grad_norm(grads).item<double>();
  // CPU: sum of squared per-tensor norms, in float64.
  double sq = 0.0;
  for (const auto& g : grads) {
    const double n = g.detach().to(torch::kFloat64).norm().item<double>();
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
      auto grads = defined_grads(params);
      at::_foreach_mul_(grads, coef);  // every gradient times coef (one multi-tensor launch on CUDA)
    }
  }
  return norm;
}

torch::Tensor clip_grad_norm_on_device(const std::vector<torch::Tensor>& params, double max_norm) {
  auto grads = defined_grads(params);
  SIMU_CHECK(!grads.empty() && grads.front().is_cuda(), "clip_grad_norm_on_device: needs CUDA gradients, got {}",
             grads.empty() ? std::string("none") : grads.front().device().str());
  for (const auto& g : grads)
    SIMU_CHECK(g.device() == grads.front().device() && g.scalar_type() == grads.front().scalar_type(),
               "clip_grad_norm_on_device: gradients must share one device and dtype ({} {} vs {} {})",
               g.device().str(), c10::toString(g.scalar_type()), grads.front().device().str(),
               c10::toString(grads.front().scalar_type()));
  torch::NoGradGuard ng;
  auto norm = device_grad_norm(grads);  // [] float64, as global_grad_norm
  if (max_norm > 0) {
    // coef = max_norm / (norm + 1e-6) in float64, clamped to 1 (x * 1 is exact), rounded to the
    // gradients' dtype as the Scalar overload rounds its double.
    auto coef = (max_norm / (norm + 1e-6)).clamp_max(1.0).to(grads.front().scalar_type());
    at::_foreach_mul_(grads, coef);
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
  cfg_ = cfg;
  fused_ = params_.front().second.is_cuda();
  if (!fused_) opt_ = std::make_unique<torch::optim::AdamW>(tensors(), opts);
  for (const auto& [name, p] : params_)
    SIMU_CHECK(p.is_cuda() == fused_ && (!fused_ || p.scalar_type() == torch::kFloat32),
               "AdamW: parameter {} must be {} like the first one{}", name, fused_ ? "on CUDA" : "on the CPU",
               fused_ ? " and float32 (the fused CUDA update)" : "");
}

std::vector<torch::Tensor> AdamW::tensors() const {
  std::vector<torch::Tensor> out;
  for (const auto& [n, p] : params_) out.push_back(p);
  return out;
}

void AdamW::step(double lr) { fused_step(lr, c10::nullopt); }

void AdamW::step(double lr, const torch::Tensor& skip) {
  SIMU_CHECK(fused_ && skip.defined() && skip.dim() == 0 && skip.scalar_type() == torch::kFloat32 &&
                 skip.device() == params_.front().second.device(),
             "AdamW::step: a skip flag needs CUDA parameters and a 0-dim float32 flag on their device, got {}",
             skip.defined() ? skip.device().str() + " " + c10::toString(skip.scalar_type()) : std::string("none"));
  fused_step(lr, skip);
}

void AdamW::fused_step(double lr, const c10::optional<torch::Tensor>& skip) {
  if (!fused_) {
    for (auto& group : opt_->param_groups()) static_cast<torch::optim::AdamWOptions&>(group.options()).lr(lr);
    opt_->step();
    return;
  }
  // The parameters that have a gradient (torch.optim.AdamW skips the others), with their state,
  // created at their first step: zero moments, step 0.
  std::vector<torch::Tensor> p, g, m, v, st;
  for (size_t i = 0; i < params_.size(); ++i) {
    const auto& t = params_[i].second;
    if (!t.grad().defined()) continue;
    auto& s = fused_state_[i];
    if (!s.exp_avg.defined()) {
      s.exp_avg = torch::zeros_like(t);
      s.exp_avg_sq = torch::zeros_like(t);
      s.step = torch::zeros({}, t.options());
    }
    p.push_back(t);
    g.push_back(t.grad());
    m.push_back(s.exp_avg);
    v.push_back(s.exp_avg_sq);
    st.push_back(s.step);
  }
  if (p.empty()) return;
  // torch.optim.AdamW(fused=True): steps + 1, then the fused multi-tensor update of every parameter.
  // With a skip flag the steps advance by 1 - skip and the kernel returns early where skip is set.
  torch::NoGradGuard ng;
  if (skip) {
    at::_foreach_add_(st, 1.0 - *skip);
  } else {
    at::_foreach_add_(st, 1);
  }
  at::_fused_adamw_(p, g, m, v, /*max_exp_avg_sqs=*/{}, st, lr, cfg_.betas.at(0), cfg_.betas.at(1), cfg_.weight_decay,
                    cfg_.eps, /*amsgrad=*/false, /*maximize=*/false, /*grad_scale=*/c10::nullopt,
                    /*found_inf=*/skip ? c10::optional<at::Tensor>(*skip) : c10::nullopt);
}

void AdamW::zero_grad() {
  for (auto& [name, p] : params_) p.mutable_grad().reset();  // set to none, as zero_grad(set_to_none=True)
}

std::map<std::string, torch::Tensor> AdamW::state_dict() const {
  std::map<std::string, torch::Tensor> out;
  if (fused_) {
    for (size_t i = 0; i < params_.size(); ++i) {
      const auto it = fused_state_.find(i);
      if (it == fused_state_.end() || !it->second.exp_avg.defined()) continue;  // no step taken yet
      const auto& name = params_[i].first;
      out[name + ".exp_avg"] = it->second.exp_avg.detach().to(torch::kCPU).clone();
      out[name + ".exp_avg_sq"] = it->second.exp_avg_sq.detach().to(torch::kCPU).clone();
      out[name + ".step"] = torch::tensor(static_cast<int64_t>(std::llround(it->second.step.item<double>())), torch::kInt64);
    }
    return out;
  }
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
  if (opt_) opt_->state().clear();
  fused_state_.clear();
  for (size_t i = 0; i < params_.size(); ++i) {
    const auto& [name, p] = params_[i];
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
    if (fused_) {
      auto& fs = fused_state_[i];
      fs.exp_avg = a->second.to(p.device(), p.scalar_type()).clone();
      fs.exp_avg_sq = b->second.to(p.device(), p.scalar_type()).clone();
      fs.step = torch::full({}, static_cast<double>(s->second.item<int64_t>()), p.options());
      continue;
    }
    auto ps = std::make_unique<torch::optim::AdamWParamState>();
    ps->step(s->second.item<int64_t>());
    ps->exp_avg(a->second.to(p.device(), p.scalar_type()).clone());
    ps->exp_avg_sq(b->second.to(p.device(), p.scalar_type()).clone());
    opt_->state()[p.unsafeGetTensorImpl()] = std::move(ps);
  }
  if (!problems.empty()) fail("{}: optimizer state does not match the adapters:\n  {}", source, fmt::join(problems, "\n  "));
}

}  // namespace simu::training
