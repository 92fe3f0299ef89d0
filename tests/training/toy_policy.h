// A small stand-in policy for trainer tests: one nonlinear layer over the shape latent with a
// LoRA-style adapter (random A and B), conditioned on t and the condition tokens.
#pragma once

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "training/fmdpo.h"
#include "training/trainer.h"

namespace simu::testing {

struct ToyPolicy : public simu::training::PolicyModel, public torch::nn::Module {
  // C: latent channels, Cc: condition channels, r: adapter rank. Same seed -> same weights.
  // base_seed: frozen weights; adapter_seed: A and B (defaults to base_seed). Own generators, so
  // threads building policies at once get the same weights.
  ToyPolicy(int64_t C, int64_t Cc, int64_t r, uint64_t base_seed, int64_t adapter_seed = -1) {
    auto g = at::make_generator<at::CPUGeneratorImpl>(base_seed);
    auto ga = at::make_generator<at::CPUGeneratorImpl>(adapter_seed < 0 ? base_seed + 1000 : adapter_seed);
    W = register_buffer("W", at::randn({C, C}, g) / std::sqrt(double(C)));
    P = register_buffer("P", at::randn({Cc, C}, g) / std::sqrt(double(Cc)));
    A = register_parameter("lora_A", at::randn({r, C}, ga) * 0.3);
    B = register_parameter("lora_B", at::randn({C, r}, ga) * 0.3);
  }
  torch::Tensor predict_shape(const torch::Tensor& x, const torch::Tensor& t_scaled, const torch::Tensor& cond,
                              const torch::Tensor& d) override {
    // [B, T, C]
    auto h = torch::matmul(x, W.t()) + torch::matmul(cond.mean(1), P).unsqueeze(1) +
             torch::sin(t_scaled / 1000.0).view({-1, 1, 1}) + d.view({-1, 1, 1});
    if (enabled) h = h + torch::matmul(torch::matmul(x, A.t()), B.t()) * 0.5;
    return torch::tanh(h) * 2.0;
  }
  void set_adapters_enabled(bool e) override { enabled = e; }
  std::vector<std::pair<std::string, torch::Tensor>> adapter_parameters() override {
    return {{"base_model.model.toy.lora_A.weight", A}, {"base_model.model.toy.lora_B.weight", B}};
  }
  void export_peft(const std::string& dir) override {
    std::filesystem::create_directories(dir);
    std::ofstream(dir + "/adapter_config.json") << "{}";
  }
  torch::Tensor W, P, A, B;
  bool enabled = true;
};

// n random pairs: latents [T, C], conditions [L, Cc]; kinds alternate.
inline std::shared_ptr<std::vector<simu::training::Pair>> toy_pairs(int64_t n, int64_t T, int64_t C, int64_t L,
                                                                     int64_t Cc, uint64_t seed) {
  torch::manual_seed(seed);
  auto v = std::make_shared<std::vector<simu::training::Pair>>();
  for (int64_t i = 0; i < n; ++i) {
    simu::training::Pair p;
    p.id = i;
    p.kind = static_cast<simu::data::PairKind>(i % 2);
    p.x_pos = torch::randn({T, C});
    p.x_neg = torch::randn({T, C});
    p.cond = torch::randn({L, Cc});
    v->push_back(p);
  }
  return v;
}

// A training config for the toy policy (device cpu, fp32, seed 7, checkpoints every 2 steps) in out/cfg.yaml.
inline simu::training::TrainConfig toy_config(const std::string& out, int64_t steps, int64_t global_batch, int64_t micro) {
  const std::string file = out + "/cfg.yaml";
  std::filesystem::create_directories(out);
  std::ofstream(file) << "model: {config: none}\n"
                         "lora: {r: 2}\n"
                         "objective: {beta: 2.0}\n"
                         "optim: {lr: 0.01, warmup_steps: 2, clip_grad_norm: 1.0, weight_decay: 0.01}\n"
                      << "data: {global_batch: " << global_batch << ", micro_batch: " << micro << "}\n"
                      << "train: {steps: " << steps << ", device: cpu, precision: fp32, seed: 7}\n"
                      << "run: {out_dir: " << out << ", checkpoint_every: 2, keep_last: 5, progress: false}\n";
  return simu::training::TrainConfig::load(file);
}

// The trainer's source over in-memory pairs.
inline simu::training::PairSourceFactory memory_source(std::shared_ptr<const std::vector<simu::training::Pair>> pairs) {
  return [pairs](int rank, int world, int64_t gb, uint64_t seed, simu::training::DataPosition pos) {
    return std::make_unique<simu::training::MemoryPairSource>(pairs, rank, world, gb, seed, pos);
  };
}

}  // namespace simu::testing
