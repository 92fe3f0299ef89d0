// lora.h's set_fp8_base (the opt-in FP8 frozen base) on the CPU, where the FP8 products run through
// the reference emulation: with scope adapted only LoRA-wrapped layers switch (scope all: every frozen
// Linear too), their output is the FP8 base product plus the unchanged adapter term, the adapters still
// get gradients, switching off restores the layers bit for bit and frees the copies, and merging and
// FP8 exclude each other. (lora_test.cpp holds the rest of lora.h's tests.)
#include "lora/lora.h"
#include "models/fp8_linear.h"
#include "models/linear.h"
#include "test_util.h"

namespace {

using simu::models::Linear;

// root.blocks.{a, b}: a [32 -> 48] is wrapped (r 4, alpha 8), b [32 -> 16] is not; B randomised.
struct Tree {
  std::shared_ptr<torch::nn::Module> root = std::make_shared<torch::nn::Module>("Root");
  Linear a{32, 48}, b{32, 16};
  Tree() {
    auto blocks = root->register_module("blocks", std::make_shared<torch::nn::Module>("Blocks"));
    blocks->register_module("a", a.ptr());
    blocks->register_module("b", b.ptr());
    simu::lora::LoraConfig c;
    c.r = 4;
    c.alpha = 8;
    c.target_suffixes = {"blocks.a"};
    simu::lora::inject_lora(*root, c);
    torch::NoGradGuard ng;
    for (auto& [name, t] : simu::lora::lora_parameters(*root)) t.copy_(torch::randn_like(t) * 0.1);
  }
};

}  // namespace

// On: a computes fp8_linear + the adapter term, b is untouched; the adapters get gradients.
TEST(LoraFp8, WrappedLayersOnlyAdaptersTrain) {
  torch::manual_seed(1);
  Tree t;
  auto x = torch::randn({3, 5, 32});
  auto a_before = t.a->forward(x), b_before = t.b->forward(x);
  EXPECT_EQ(simu::lora::set_fp8_base(*t.root, true), 1);
  ASSERT_TRUE(t.a->fp8_weight());
  EXPECT_FALSE(t.b->fp8_weight());
  auto adapter = simu::lora::lora_adapter(*t.a);
  auto y = t.a->forward(x);
  auto want = simu::models::fp8_linear(x, *t.a->fp8_weight()) + adapter->delta(x);
  EXPECT_TRUE(torch::equal(y, want));
  EXPECT_FALSE(torch::equal(y, a_before));
  EXPECT_TRUE(torch::equal(t.b->forward(x), b_before));
  // Gradients reach A and B (and only them: the base stays frozen).
  y.square().sum().backward();
  ASSERT_TRUE(adapter->A->weight.grad().defined());
  EXPECT_GT(adapter->A->weight.grad().abs().max().item<double>(), 0);
  EXPECT_GT(adapter->B->weight.grad().abs().max().item<double>(), 0);
  EXPECT_FALSE(t.a->weight.grad().defined());
}

// Scope all: the frozen Linear without an adapter switches too (sizes multiples of 16); off frees both.
TEST(LoraFp8, ScopeAllCoversEveryFrozenLinear) {
  torch::manual_seed(3);
  Tree t;
  auto x = torch::randn({4, 32});
  auto b_before = t.b->forward(x);
  EXPECT_EQ(simu::lora::set_fp8_base(*t.root, true, simu::models::Fp8Backward::kFp8, simu::lora::Fp8Scope::kAll), 2);
  ASSERT_TRUE(t.b->fp8_weight());
  EXPECT_TRUE(torch::equal(t.b->forward(x), simu::models::fp8_linear(x, *t.b->fp8_weight())));
  EXPECT_EQ(simu::lora::set_fp8_base(*t.root, false), 2);
  EXPECT_FALSE(t.a->fp8_weight());
  EXPECT_TRUE(torch::equal(t.b->forward(x), b_before));
  EXPECT_EQ(simu::lora::parse_fp8_scope("all", "k"), simu::lora::Fp8Scope::kAll);
  EXPECT_EQ(simu::lora::fp8_scope_name(simu::lora::parse_fp8_scope("adapted", "k")), "adapted");
  EXPECT_THROW(simu::lora::parse_fp8_scope("mlp", "k"), simu::Error);
}

// Off: the FP8 copies are freed and outputs are the bf16/fp32 path's bit for bit.
TEST(LoraFp8, OffRestoresExactly) {
  torch::manual_seed(2);
  Tree t;
  auto x = torch::randn({4, 32});
  auto before = t.a->forward(x);
  simu::lora::set_fp8_base(*t.root, true, simu::models::Fp8Backward::kBf16);
  EXPECT_EQ(t.a->fp8_weight()->backward, simu::models::Fp8Backward::kBf16);
  simu::lora::set_fp8_base(*t.root, false);
  EXPECT_FALSE(t.a->fp8_weight());
  EXPECT_TRUE(torch::equal(t.a->forward(x), before));
}

// Merged adapters and the FP8 base exclude each other; a tree without adapters is refused.
TEST(LoraFp8, MergeAndNoAdapterErrors) {
  Tree t;
  simu::lora::set_fp8_base(*t.root, true);
  EXPECT_THROW(simu::lora::merge_lora(*t.root), simu::Error);
  simu::lora::set_fp8_base(*t.root, false);
  simu::lora::merge_lora(*t.root);
  EXPECT_THROW(simu::lora::set_fp8_base(*t.root, true), simu::Error);
  Linear plain(16, 16);
  EXPECT_THROW(simu::lora::set_fp8_base(*plain, true), simu::Error);
}
