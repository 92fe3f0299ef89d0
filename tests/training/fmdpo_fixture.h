// The FM-DPO fixture (fmdpo_small_io.safetensors, made by the official-style Python reference): its
// inputs as FmdpoInputs, for the tests that evaluate the objective on it, and its optimizer step.
#pragma once

#include <map>
#include <string>
#include <utility>
#include <vector>

#include "data/safetensors.h"
#include "test_util.h"
#include "training/fmdpo.h"
#include "training/optim.h"

namespace simu::testing {

// The fixture's tensors by name (in.*, out.*, grad.* ...).
inline std::map<std::string, torch::Tensor> fmdpo_fixture() {
  return simu::data::load_safetensors(fixture("fmdpo_small_io.safetensors"));
}

// The objective's inputs from the fixture's in.* tensors.
inline simu::training::FmdpoInputs fmdpo_fixture_inputs(const std::map<std::string, torch::Tensor>& io) {
  simu::training::FmdpoInputs in;
  in.x_pos = io.at("in.x_pos");
  in.x_neg = io.at("in.x_neg");
  in.cond = io.at("in.cond");
  in.w = io.at("in.w");
  in.t = io.at("in.t");
  in.eps_pos = io.at("in.eps_pos");
  in.eps_neg = io.at("in.eps_neg");
  return in;
}

// The fixture's optimizer step on params (gradients set): clip_grad_norm to 1.0, then one AdamW step
// with its settings (lr 1e-3, betas (0.9, 0.999), eps 1e-8, weight decay 0.01). Returns the gradient
// norm before clipping (the fixture's out.grad_norm_before_clip); the parameters after it are after_adamw.*.
inline double fmdpo_fixture_clipped_adamw_step(std::vector<std::pair<std::string, torch::Tensor>> params) {
  simu::training::OptimConfig c;
  c.lr = 1e-3;
  c.betas = {0.9, 0.999};
  c.eps = 1e-8;
  c.weight_decay = 0.01;
  simu::training::AdamW opt(std::move(params), c);
  const double norm = simu::training::clip_grad_norm(opt.tensors(), 1.0);
  opt.step(1e-3);
  return norm;
}

}  // namespace simu::testing
