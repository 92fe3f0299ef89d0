// The FM-DPO fixture (fmdpo_small_io.safetensors, made by the official-style Python reference): its
// inputs as FmdpoInputs, for the tests that evaluate the objective on it.
#pragma once

#include <map>
#include <string>

#include "data/safetensors.h"
#include "test_util.h"
#include "training/fmdpo.h"

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

}  // namespace simu::testing
