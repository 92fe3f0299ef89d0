// models/linear.h on CUDA: the compute copy under CUDA fp16 and bf16 autocast gives autocast's cast
// path bit for bit, for one Linear (forward, input gradient) and for the whole flow model on the
// fused path (fc1's GELU epilogue included) in inference and in training mode with a frozen base;
// sampling turns the copies on and reads them (no autocast copy of those weights).
#include <ATen/CPUGeneratorImpl.h>
#include <ATen/autocast_mode.h>

#include "data/safetensors.h"
#include "flow_mid_config.h"
#include "models/generator.h"
#include "models/linear.h"
#include "models/precision.h"
#include "test_util.h"

namespace sm = simu::models;

namespace {
const std::vector<sm::Precision> kLow = {sm::Precision::kFp16, sm::Precision::kBf16};

// Copies off / on for every Linear under root (frozen or not).
void copies(torch::nn::Module& root, c10::optional<torch::ScalarType> dtype) {
  sm::set_compute_copies(root, dtype, /*frozen_only=*/false);
}
}  // namespace

// One frozen Linear: output and input gradient equal the cast path's (the fp32 weight through
// autocast), in fp16 and bf16.
TEST(LinearGpu, ComputeCopyMatchesAutocastCast) {
  SIMU_REQUIRE_CUDA();
  const auto f32 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat32);
  torch::manual_seed(2);
  sm::Linear l(1024, 3072);
  l->to(torch::kCUDA);
  for (auto& p : l->parameters()) p.set_requires_grad(false);
  auto x0 = torch::randn({2, 301, 1024}, f32);
  for (const auto p : kLow) {
    const auto dt = sm::precision_dtype(p);
    auto run = [&](bool copy) {
      l->set_compute_copy(copy ? c10::optional<torch::ScalarType>(dt) : c10::nullopt);
      auto x = x0.clone().requires_grad_(true);
      sm::Autocast ac(p);
      auto y = l->forward(x);
      (y.to(torch::kFloat32) * 0.01).sum().backward();
      return std::make_pair(y.detach(), x.grad());
    };
    const auto [y_ref, g_ref] = run(false);
    const auto [y, g] = run(true);
    ASSERT_NE(l->compute_copy(), nullptr) << sm::precision_name(p);
    EXPECT_EQ(l->compute_copy()->weight().device(), x0.device());
    EXPECT_EQ(y.scalar_type(), dt);
    EXPECT_TRUE(torch::equal(y, y_ref)) << sm::precision_name(p);
    EXPECT_TRUE(torch::equal(g, g_ref)) << sm::precision_name(p);
  }
}

// The flow model (mid-size config, fused path): copies on equal copies off bit for bit, inference in
// fp16 and bf16 (fc1's fused GELU takes the copy too), and training mode in bf16 with a frozen base:
// outputs and input-latent gradients.
TEST(LinearGpu, FlowForwardWithComputeCopiesIsBitIdentical) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  auto gen = sm::load_generator(simu::testing::mid_flow_config("linear_copy_flow"), "", dev);
  for (auto& p : gen->parameters()) p.set_requires_grad(false);
  auto bb = gen->backbone();
  auto rng = at::make_generator<at::CPUGeneratorImpl>(9);
  auto x = gen->noise(2, rng, dev);
  auto cond = torch::randn({2, 77, gen->config().backbone.cond_channels}, rng).to(dev);
  auto t = torch::full({1}, 400.0, torch::TensorOptions().device(dev));
  c10::optional<torch::Tensor> d = torch::zeros({1}, torch::TensorOptions().device(dev));
  for (const auto p : kLow) {
    torch::NoGradGuard ng;
    sm::Autocast ac(p);
    copies(*bb, c10::nullopt);
    const auto want = bb->forward(x, t, cond, d);
    copies(*bb, sm::precision_dtype(p));
    const auto got = bb->forward(x, t, cond, d);
    ASSERT_NE(bb->blocks->ptr<sm::MOTBlockImpl>(0)->mlp[0]->fc1->compute_copy(), nullptr) << "fc1 (GELU epilogue) skipped its copy";
    for (const auto& [k, v] : want) EXPECT_TRUE(torch::equal(got.at(k), v)) << sm::precision_name(p) << " " << k;
  }
  // Training mode, bf16, graph through the input latents (the frozen base of FM-DPO).
  bb->set_training_kernels(true);
  auto train = [&](bool on) {
    copies(*bb, on ? c10::optional<torch::ScalarType>(torch::kBFloat16) : c10::nullopt);
    sm::Latents xs;
    std::vector<torch::Tensor> leaves;
    for (const auto& [k, v] : x) leaves.push_back(xs[k] = v.clone().requires_grad_());
    auto tt = torch::tensor({300.0f, 700.0f}, torch::TensorOptions().device(dev));
    sm::Autocast ac(sm::Precision::kBf16);
    auto out = bb->forward(xs, tt, cond, torch::zeros({2}, torch::TensorOptions().device(dev)));
    torch::Tensor loss = torch::zeros({}, torch::TensorOptions().device(dev));
    for (const auto& [k, v] : out) loss = loss + v.to(torch::kFloat32).square().mean();
    auto grads = torch::autograd::grad({loss}, leaves);
    std::vector<torch::Tensor> res;
    for (const auto& [k, v] : out) res.push_back(v.detach());
    res.insert(res.end(), grads.begin(), grads.end());
    return res;
  };
  const auto ref = train(false), got = train(true);
  ASSERT_EQ(ref.size(), got.size());
  // Outputs bit for bit. The input gradients pass through the attention backward, whose query gradient
  // cuDNN accumulates with fp32 atomics (run-to-run order differs, seen on an H200 for a pose latent's
  // gradient): those are compared at bf16 rounding.
  const size_t n_out = x.size();
  for (size_t i = 0; i < ref.size(); ++i) {
    if (i < n_out) EXPECT_TRUE(torch::equal(got[i], ref[i])) << "training output " << i;
    else EXPECT_TRUE(simu::testing::close(got[i], ref[i], 1e-2, "training input gradient " + std::to_string(i - n_out)));
  }
  bb->set_training_kernels(false);
}

// sample() on CUDA turns the copies on in its precision; a graph captured then reads them, so the
// Linear weights get no autocast copy in the graph's list, and eager and graph sampling agree.
TEST(LinearGpu, SamplingUsesComputeCopies) {
  SIMU_REQUIRE_CUDA();
  const torch::Device dev(torch::kCUDA);
  auto gen = sm::load_generator(simu::testing::fixture("ss_generator_small.json"),
                                simu::testing::fixture("ss_generator_small.safetensors"), dev);
  auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  auto o = sm::SampleOptions::from(gen->config());
  o.precision = sm::Precision::kFp16;
  const auto cond = io.at("in.cond").to(dev);
  auto run = [&](bool graphs) {
    o.cuda_graphs = graphs;
    auto g = at::make_generator<at::CPUGeneratorImpl>(11);
    return gen->sample(cond, gen->noise(cond.size(0), g, dev), o);
  };
  gen->reverse_fn->clear_graphs();
  const auto eager = run(false);
  int with_copy = 0, linears = 0;
  for (const auto& m : gen->backbone()->modules())
    if (const auto* l = dynamic_cast<const sm::LinearImpl*>(m.get())) {
      ++linears;
      with_copy += l->compute_copy() != nullptr && l->compute_copy()->dtype() == torch::kHalf;
    }
  EXPECT_GT(with_copy, linears / 2) << "most Linear layers run in sampling and should hold an fp16 copy";
  const auto graphed = run(true);
  ASSERT_FALSE(gen->reverse_fn->graph_cache.graphs.empty());
  for (const auto& g : gen->reverse_fn->graph_cache.graphs) {
    EXPECT_EQ(static_cast<int>(g->copies.size()), with_copy);
    for (const auto& [p, w] : g->weights)
      for (const auto& c : g->copies)
        EXPECT_FALSE(p.is_same(c.weight) || p.is_same(c.bias)) << "a copied weight also got an autocast copy";
  }
  // The same kernels on the same inputs (the graph tests' bound, flow_gpu.cpp).
  for (const auto& [k, v] : eager) EXPECT_TRUE(simu::testing::close(graphed.at(k), v, 1e-6, "graph vs eager " + k));
  gen->reverse_fn->clear_graphs();
}
