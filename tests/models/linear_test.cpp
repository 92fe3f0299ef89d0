// models/linear.h on the CPU: the compute copy (weight/bias kept in the autocast dtype) under CPU
// autocast gives bit for bit what autocast's own cast of the fp32 weight gives (forward and input
// gradient); a weight changed in place (copy_, add_, merge_lora / unmerge_lora) or a changed bias is
// never read stale; the copy is used only where autocast would cast (matching dtype, no weight
// gradient wanted) and made only there; set_compute_copies picks frozen layers; the whole flow model
// under CPU autocast computes the same with and without copies.
#include <ATen/CPUGeneratorImpl.h>
#include <ATen/autocast_mode.h>

#include "data/safetensors.h"
#include "lora/lora.h"
#include "models/generator.h"
#include "models/linear.h"
#include "test_util.h"

namespace sm = simu::models;

namespace {

// CPU autocast in `dtype` for the scope (restores the previous state, clears the cache at exit).
class CpuAutocast {
 public:
  explicit CpuAutocast(torch::ScalarType dtype)
      : prev_on_(at::autocast::is_autocast_enabled(at::kCPU)), prev_dtype_(at::autocast::get_autocast_dtype(at::kCPU)) {
    at::autocast::set_autocast_enabled(at::kCPU, true);
    at::autocast::set_autocast_dtype(at::kCPU, dtype);
    at::autocast::increment_nesting();
  }
  ~CpuAutocast() {
    if (at::autocast::decrement_nesting() == 0) at::autocast::clear_cache();
    at::autocast::set_autocast_enabled(at::kCPU, prev_on_);
    at::autocast::set_autocast_dtype(at::kCPU, prev_dtype_);
  }

 private:
  bool prev_on_;
  at::ScalarType prev_dtype_;
};

// A frozen Linear [in -> out] with seeded weights.
sm::Linear frozen_linear(int64_t in, int64_t out, uint64_t seed) {
  torch::manual_seed(seed);
  sm::Linear l(in, out);
  for (auto& p : l->parameters()) p.set_requires_grad(false);
  return l;
}

// The reference: what the layer computes without a copy, autocast casting the fp32 weight itself.
torch::Tensor cast_path(sm::LinearImpl& l, const torch::Tensor& x) { return torch::linear(x, l.weight, l.bias); }

}  // namespace

// Under CPU autocast (bf16 and fp16) the copy gives autocast's cast path bit for bit, with and without
// bias, and the copy is made in the autocast dtype on the first product.
TEST(LinearComputeCopy, MatchesAutocastCastBitwise) {
  for (const auto dt : {torch::kBFloat16, torch::kHalf}) {
    for (const bool with_bias : {true, false}) {
      torch::manual_seed(3);
      sm::Linear l(96, 160, with_bias);
      for (auto& p : l->parameters()) p.set_requires_grad(false);
      auto x = torch::randn({3, 7, 96}) * 2;  // [B, L, in] fp32
      l->set_compute_copy(dt);
      EXPECT_EQ(l->compute_copy(), nullptr) << "made before any product";
      CpuAutocast ac(dt);
      auto got = l->forward(x);
      ASSERT_NE(l->compute_copy(), nullptr);
      EXPECT_EQ(l->compute_copy()->dtype(), dt);
      EXPECT_EQ(l->compute_copy()->bias().defined(), with_bias);
      // The copy holds one rounding of the fp32 weight (independent of the layer's product).
      EXPECT_TRUE(torch::equal(l->compute_copy()->weight(), l->weight.to(dt)));
      auto want = cast_path(*l, x);
      ASSERT_EQ(got.scalar_type(), dt);
      EXPECT_TRUE(torch::equal(got, want)) << c10::toString(dt) << " bias " << with_bias;
      // Within 16-bit rounding of the fp32 product (the copy is not some other weight): x and W rounded
      // to 16 bits, fp32 accumulation of 96 terms, the output rounded to 16 bits (bf16's u covers fp16's).
      const double tol = 3 * simu::testing::kBf16Unit + simu::testing::two_paths(96);
      EXPECT_TRUE(simu::testing::close(got.to(torch::kFloat32), torch::linear(x, l->weight, l->bias), tol, "vs fp32"));
    }
  }
}

// With the weight frozen and the input requiring a gradient (the frozen base in training), output and
// input gradient equal the cast path's.
TEST(LinearComputeCopy, InputGradientMatchesCastPath) {
  auto l = frozen_linear(64, 48, 4);
  l->set_compute_copy(torch::kBFloat16);
  auto x0 = torch::randn({2, 5, 64});
  auto run = [&](bool copy) {
    auto x = x0.clone().requires_grad_(true);
    CpuAutocast ac(torch::kBFloat16);
    auto y = copy ? l->forward(x) : cast_path(*l, x);
    (y.to(torch::kFloat32) * torch::linspace(-1, 1, 48)).sum().backward();
    return std::make_pair(y.detach(), x.grad());
  };
  const auto [y_copy, g_copy] = run(true);
  ASSERT_NE(l->compute_copy(), nullptr) << "the frozen layer should have used its copy in grad mode";
  const auto [y_ref, g_ref] = run(false);
  EXPECT_TRUE(torch::equal(y_copy, y_ref));
  EXPECT_TRUE(torch::equal(g_copy, g_ref));
}

// A weight or bias changed in place after the copy was made is not read stale: the next product
// equals the cast path on the new values (and differs from the old output).
TEST(LinearComputeCopy, StaleWeightIsNotUsed) {
  auto l = frozen_linear(32, 40, 5);
  l->set_compute_copy(torch::kBFloat16);
  auto x = torch::randn({4, 32});
  CpuAutocast ac(torch::kBFloat16);
  const auto first = l->forward(x);
  const auto copy = l->compute_copy();
  ASSERT_NE(copy, nullptr);
  std::vector<std::pair<std::string, std::function<void()>>> writers = {
      {"weight.copy_", [&] { l->weight.copy_(torch::randn({40, 32})); }},
      {"weight.add_", [&] { l->weight.add_(0.25); }},
      {"bias.mul_", [&] { l->bias.mul_(-3); }},
  };
  torch::Tensor before = first;
  for (auto& [what, write] : writers) {
    {
      torch::NoGradGuard ng;
      write();
    }
    auto got = l->forward(x);
    EXPECT_TRUE(torch::equal(got, cast_path(*l, x))) << what;
    EXPECT_FALSE(torch::equal(got, before)) << what << ": the change should show";
    // Refreshed in place: the same copy object and memory (CUDA graphs reading it stay valid).
    EXPECT_EQ(l->compute_copy(), copy) << what;
    before = got;
  }
  // A weight replaced by another storage (a move, a reload by assignment) gets a new copy.
  {
    torch::NoGradGuard ng;
    l->weight.set_data(torch::randn({40, 32}));
  }
  EXPECT_TRUE(torch::equal(l->forward(x), cast_path(*l, x)));
  EXPECT_NE(l->compute_copy(), copy);
}

// merge_lora / unmerge_lora write the base weight in place: the products after each equal autocast's
// cast path on the weight as it is then.
TEST(LinearComputeCopy, MergeAndUnmergeLoraAreSeen) {
  torch::manual_seed(6);
  struct Net : torch::nn::Module {
    sm::Linear proj{nullptr};
    Net() { proj = register_module("proj", sm::Linear(48, 48)); }
  };
  auto net = std::make_shared<Net>();
  simu::lora::LoraConfig cfg;
  cfg.r = 4;
  cfg.alpha = 8;
  cfg.target_suffixes = {"proj"};
  simu::lora::inject_lora(*net, cfg);  // freezes the base
  auto adapter = simu::lora::lora_adapter(*net->proj);
  ASSERT_NE(adapter, nullptr);
  {
    torch::NoGradGuard ng;
    adapter->B->weight.normal_(0, 0.5);  // a trained (non-zero) up-projection
  }
  EXPECT_EQ(sm::set_compute_copies(*net, torch::kBFloat16), 1) << "only the frozen base Linear is a simu Linear";
  auto x = torch::randn({3, 48});
  torch::NoGradGuard ng;
  CpuAutocast ac(torch::kBFloat16);
  const auto y0 = net->proj->forward(x);  // the copy is made of the unmerged base
  ASSERT_NE(net->proj->compute_copy(), nullptr);
  // Merged (the adapter is off then): the product of the merged weight.
  simu::lora::merge_lora(*net);
  EXPECT_TRUE(torch::equal(net->proj->forward(x), cast_path(*net->proj, x))) << "merged weight read stale";
  // Unmerged, adapter off: the product of the restored base weight.
  simu::lora::unmerge_lora(*net);
  simu::lora::set_lora_enabled(*net, false);
  EXPECT_TRUE(torch::equal(net->proj->forward(x), cast_path(*net->proj, x))) << "unmerged weight read stale";
  // Adapter on again: the layer's first output, up to the fp32 rounding of merge + unmerge, which can
  // flip the bf16 rounding of the weight copy and so of the output: 2 bf16 roundings in each of the two
  // products (x rounds alike in both, the adapter path is the same arithmetic).
  simu::lora::set_lora_enabled(*net, true);
  EXPECT_TRUE(simu::testing::close(net->proj->forward(x).to(torch::kFloat32), y0.to(torch::kFloat32),
                                   4 * simu::testing::kBf16Unit, "unmerged"));
}

// The copy is neither used nor made where autocast would not cast to its dtype: autocast off, another
// autocast dtype, or a weight that wants a gradient (trainable layer in grad mode).
TEST(LinearComputeCopy, OnlyWhereAutocastWouldCast) {
  auto l = frozen_linear(16, 24, 7);
  l->set_compute_copy(torch::kBFloat16);
  auto x = torch::randn({5, 16});
  // Autocast off: the fp32 product.
  EXPECT_TRUE(torch::equal(l->forward(x), torch::linear(x, l->weight, l->bias)));
  EXPECT_EQ(l->compute_copy(), nullptr);
  {
    // Autocast in fp16, copy dtype bf16: autocast's fp16 cast.
    CpuAutocast ac(torch::kHalf);
    auto y = l->forward(x);
    EXPECT_EQ(y.scalar_type(), torch::kHalf);
    EXPECT_TRUE(torch::equal(y, cast_path(*l, x)));
    EXPECT_EQ(l->compute_copy(), nullptr);
  }
  {
    // Trainable weight in grad mode: autocast's cast, and the weight gets its gradient.
    l->weight.set_requires_grad(true);
    CpuAutocast ac(torch::kBFloat16);
    auto y = l->forward(x);
    EXPECT_EQ(l->compute_copy(), nullptr);
    y.to(torch::kFloat32).sum().backward();
    EXPECT_TRUE(l->weight.grad().defined());
    // The same layer without grad mode: no gradient wanted, the copy applies.
    torch::NoGradGuard ng;
    EXPECT_TRUE(torch::equal(l->forward(x), cast_path(*l, x)));
    EXPECT_NE(l->compute_copy(), nullptr);
  }
  // Off again: the copy is freed.
  l->set_compute_copy(c10::nullopt);
  EXPECT_EQ(l->compute_copy(), nullptr);
  EXPECT_THROW(l->set_compute_copy(torch::kFloat32), simu::Error);
}

// set_compute_copies: frozen layers only by default, every layer on request, nullopt switches off.
TEST(LinearComputeCopy, SetComputeCopiesPicksFrozenLayers) {
  struct Net : torch::nn::Module {
    sm::Linear a{nullptr}, b{nullptr};
    Net() {
      a = register_module("a", sm::Linear(8, 8));
      b = register_module("b", sm::Linear(8, 8));
    }
  };
  Net net;
  net.a->weight.set_requires_grad(false);
  net.a->bias.set_requires_grad(false);
  net.b->bias.set_requires_grad(false);  // b's weight still trains
  EXPECT_EQ(sm::set_compute_copies(net, torch::kHalf), 1);
  EXPECT_EQ(net.a->compute_copy_dtype(), c10::optional<torch::ScalarType>(torch::kHalf));
  EXPECT_FALSE(net.b->compute_copy_dtype().has_value());
  EXPECT_EQ(sm::set_compute_copies(net, torch::kBFloat16, /*frozen_only=*/false), 2);
  EXPECT_EQ(net.b->compute_copy_dtype(), c10::optional<torch::ScalarType>(torch::kBFloat16));
  EXPECT_EQ(sm::set_compute_copies(net, c10::nullopt), 2);
  EXPECT_FALSE(net.a->compute_copy_dtype().has_value());
}

// The whole flow model (the fixture's small generator) under CPU bf16 autocast: copies on equal
// copies off bit for bit; a weight changed in place between forwards shows in the next one.
TEST(LinearComputeCopy, FlowForwardUnderCpuAutocastIsBitIdentical) {
  auto gen = sm::load_generator(simu::testing::fixture("ss_generator_small.json"),
                                simu::testing::fixture("ss_generator_small.safetensors"), torch::kCPU);
  auto bb = gen->backbone();
  auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  auto rng = at::make_generator<at::CPUGeneratorImpl>(4);
  const auto cond = io.at("in.cond");
  auto x = gen->noise(cond.size(0), rng, torch::kCPU);
  auto t = torch::full({1}, 400.0);
  c10::optional<torch::Tensor> d;
  if (gen->config().backbone.is_shortcut_model) d = torch::zeros({1});
  torch::NoGradGuard ng;
  auto forward = [&](bool on) {
    sm::set_compute_copies(*bb, on ? c10::optional<torch::ScalarType>(torch::kBFloat16) : c10::nullopt, /*frozen_only=*/false);
    // One autocast region per forward: autocast's own cache (these weights require a gradient) would
    // otherwise keep the casts of the weights from before the change below.
    CpuAutocast ac(torch::kBFloat16);
    return bb->forward(x, t, cond, d);
  };
  auto check = [&](const std::string& what) {
    const auto on = forward(true), off = forward(false);
    for (const auto& [k, v] : off) EXPECT_TRUE(torch::equal(on.at(k), v)) << what << " " << k;
  };
  check("fresh copies");
  // Copies made by a first forward, then every weight changed in place: the next forward reads the new values.
  (void)forward(true);
  for (auto& p : bb->parameters()) p.mul_(1.01);
  check("after an in-place change");
}
