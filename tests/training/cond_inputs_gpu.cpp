// Inputs-mode training on CUDA (src/training/cond_inputs.cpp, Trainer::group_condition): with bf16
// autocast, pairs that carry the condition embedder's inputs train like pairs that carry the tokens
// the same embedder made beforehand under the same autocast and grouping (adapters within bf16
// noise, cosine > 0.999), and the embedder's parameters get no gradient.
#include <ATen/CPUGeneratorImpl.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "common/fs.h"
#include "models/cond_embedder.h"
#include "models/precision.h"
#include "test_util.h"
#include "training/cond_inputs.h"
#include "training/generator_policy.h"

using namespace simu::training;

TEST(CondInputsGpu, EmbeddingInTheStepFollowsPrecomputedTokens) {
  SIMU_REQUIRE_CUDA();
  const torch::Device cuda(torch::kCUDA);
  const std::string dir = simu::testing::temp_dir("cond_inputs_gpu");
  // The demo's small embedder (ViTs at 70 px), random weights, frozen, on the GPU.
  auto j = nlohmann::json::parse(simu::fs::read_file(simu::testing::source_dir() + "/configs/demo_embedder_small.json"));
  j["dino_image_input_size"] = 70;
  simu::fs::atomic_write(dir + "/embedder.json", j.dump(1));
  torch::manual_seed(4);
  auto emb = simu::models::load_cond_embedder(dir + "/embedder.json", "", "", cuda);
  // 4 pairs of the small generator's latents [64, 8] with inputs at 84 px (point maps 32 px).
  auto rng = at::make_generator<at::CPUGeneratorImpl>(9);
  auto with_inputs = std::make_shared<std::vector<Pair>>(), with_tokens = std::make_shared<std::vector<Pair>>();
  for (int64_t i = 0; i < 4; ++i) {
    Pair p{i, static_cast<simu::data::PairKind>(i % 2), torch::randn({64, 8}, rng), torch::randn({64, 8}, rng), {}};
    p.inputs = {{"image", torch::rand({3, 84, 84}, rng)},          {"rgb_image", torch::rand({3, 84, 84}, rng)},
                {"mask", (torch::rand({1, 84, 84}, rng) > 0.5).to(torch::kFloat32)},
                {"rgb_image_mask", (torch::rand({1, 84, 84}, rng) > 0.5).to(torch::kFloat32)},
                {"pointmap", torch::randn({3, 32, 32}, rng)},       {"rgb_pointmap", torch::randn({3, 32, 32}, rng)}};
    with_inputs->push_back(p);
  }
  // Tokens made beforehand, two pairs per call (the micro-batch) under the step's bf16 autocast.
  for (int64_t m0 = 0; m0 < 4; m0 += 2) {
    std::map<std::string, torch::Tensor> batch;
    for (const auto& [name, t] : (*with_inputs)[m0].inputs)
      batch[name] = torch::stack({t, (*with_inputs)[m0 + 1].inputs.at(name)}).to(cuda);
    torch::NoGradGuard ng;
    simu::models::Autocast ac(simu::models::Precision::kBf16, true);
    const auto tokens = emb->forward(batch).to(torch::kFloat32).cpu();  // [2, L, Cc]
    for (int64_t k = 0; k < 2; ++k) {
      Pair p = (*with_inputs)[m0 + k];
      p.inputs.clear();
      p.cond = tokens[k].clone();
      with_tokens->push_back(p);
    }
  }
  std::ofstream(dir + "/cfg.yaml") << "model: {config: " << simu::testing::fixture("ss_generator_small.json")
                                   << ", weights: " << simu::testing::fixture("ss_generator_small.safetensors") << "}\n"
                                   << "lora: {r: 4, alpha: 8}\n"
                                      "optim: {lr: 0.001, warmup_steps: 0}\n"
                                      "data: {global_batch: 4, micro_batch: 2}\n"
                                      "train: {steps: 3, device: cuda, precision: bf16, seed: 3}\n"
                                   << "run: {out_dir: " << dir << "/run, progress: false}\n";
  const auto cfg = TrainConfig::load(dir + "/cfg.yaml");
  auto train = [&](std::shared_ptr<std::vector<Pair>> pairs, bool embed) {
    auto policy = make_generator_policy(cfg, cuda);
    auto comm = Communicator::create(DistEnv{}, cuda, std::chrono::milliseconds(60000));
    auto source = [pairs](int rank, int world, int64_t gb, uint64_t seed, DataPosition pos) -> std::unique_ptr<PairSource> {
      return std::make_unique<MemoryPairSource>(pairs, rank, world, gb, seed, pos);
    };
    Trainer trainer(cfg, *policy, source, *comm, cuda);
    if (embed) trainer.set_condition_embedder(condition_embed_fn(emb));
    for (int s = 0; s < cfg.train.steps; ++s) trainer.step();
    return trainer.checkpoint_data().adapter;
  };
  const auto a = train(with_tokens, false), b = train(with_inputs, true);
  double dot = 0, na = 0, nb = 0;
  for (const auto& [name, t] : a) {
    const auto x = t.to(torch::kFloat64), y = b.at(name).to(torch::kFloat64);
    dot += (x * y).sum().item<double>(), na += (x * x).sum().item<double>(), nb += (y * y).sum().item<double>();
  }
  EXPECT_GT(dot / std::sqrt(na * nb), 0.999);
  for (const auto& p : emb->parameters()) EXPECT_FALSE(p.grad().defined());
}
