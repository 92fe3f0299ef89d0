// LoRA on a toy module tree shaped like the small Stage-1 generator (same paths and shapes as the
// fixture adapter lora_small/), checked against independent math and the PEFT fixture files.
#include <fmt/format.h>

#include <sys/wait.h>
#include <unistd.h>

#include <cmath>
#include <limits>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include <ATen/autocast_mode.h>

#include "common/config.h"
#include "common/error.h"
#include "data/safetensors.h"
#include "lora/lora.h"
#include "models/generator.h"
#include "models/linear.h"
#include "test_util.h"

namespace {

using simu::lora::LoraConfig;
using simu::models::Linear;

// The small fixture generator's shape (ss_generator_small.json), which the toy and the fixture adapter
// lora_small/ share: model channels, condition channels, blocks.
struct FixtureDims {
  int64_t channels, cond_channels;
  int blocks;
};
const FixtureDims& dims() {
  static const FixtureDims d = [] {
    const auto c = simu::models::GeneratorConfig::from_official_file(simu::testing::fixture("ss_generator_small.json"));
    return FixtureDims{c.backbone.model_channels, c.backbone.cond_channels, static_cast<int>(c.backbone.num_blocks)};
  }();
  return d;
}
int64_t kC() { return dims().channels; }
int64_t kCond() { return dims().cond_channels; }

// Registers `child` under root at a dotted path, creating plain container modules on the way.
void add_at(torch::nn::Module& root, const std::string& path, std::shared_ptr<torch::nn::Module> child) {
  torch::nn::Module* node = &root;
  std::string rest = path;
  while (true) {
    const auto dot = rest.find('.');
    if (dot == std::string::npos) {
      node->register_module(rest, child);
      return;
    }
    const std::string name = rest.substr(0, dot);
    rest = rest.substr(dot + 1);
    std::shared_ptr<torch::nn::Module> next;
    for (auto& c : node->named_children())
      if (c.key() == name) next = c.value();
    if (!next) next = node->register_module(name, std::make_shared<torch::nn::Module>("Node"));
    node = next.get();
  }
}

// Toy generator tree: per block the shape and pose projections of self/cross attention plus an MLP.
struct Toy {
  std::shared_ptr<torch::nn::Module> root = std::make_shared<torch::nn::Module>("ShortCut");
  std::map<std::string, Linear> linears;
  explicit Toy(int blocks = 2) {
    for (int b = 0; b < blocks; ++b) {
      const std::string p = fmt::format("reverse_fn.backbone.blocks.{}.", b);
      for (const std::string lat : {"shape", "6drotation_normalized"}) {
        add(p + "self_attn.to_qkv." + lat, kC(), 3 * kC());
        add(p + "self_attn.to_out." + lat, kC(), kC());
        add(p + "cross_attn." + lat + ".to_q", kC(), kC());
        add(p + "cross_attn." + lat + ".to_kv", kCond(), 2 * kC());
        add(p + "cross_attn." + lat + ".to_out", kC(), kC());
        add(p + "mlp." + lat + ".mlp.0", kC(), 4 * kC());
      }
    }
  }
  void add(const std::string& path, int64_t in, int64_t out) {
    Linear l(in, out);
    add_at(*root, path, l.ptr());
    linears.emplace(path, l);
  }
  // Runs every Linear on a fixed input of its width; returns outputs by path.
  std::map<std::string, torch::Tensor> run(int64_t seed = 7) {
    std::map<std::string, torch::Tensor> out;
    for (auto& [path, l] : linears) {
      torch::manual_seed(seed);
      out[path] = l->forward(torch::randn({2, 5, l->in_features}));
    }
    return out;
  }
};

const std::vector<std::string> kShapeTargets = LoraConfig::default_targets();

// Expected adapter parameter count of the default targets per block: r * (in + out) summed.
int64_t analytic_params(int64_t r, int blocks) {
  const int64_t per_block = (kC() + 3 * kC()) + (kC() + kC()) + (kC() + kC()) + (kCond() + 2 * kC()) + (kC() + kC());
  return r * per_block * blocks;
}

LoraConfig small_cfg(int64_t r = 4, double alpha = 8) {
  LoraConfig c;
  c.r = r;
  c.alpha = alpha;
  return c;
}

// Fills every adapter with random values (B is zero after injection).
void randomize(torch::nn::Module& root, int64_t seed = 3) {
  torch::manual_seed(seed);
  torch::NoGradGuard g;
  for (auto& [name, t] : simu::lora::lora_parameters(root)) t.copy_(torch::randn_like(t) * 0.1);
}

bool is_shape_target(const std::string& path) {
  for (const auto& s : kShapeTargets)
    if (path.size() >= s.size() && path.compare(path.size() - s.size(), s.size(), s) == 0) return true;
  return false;
}

}  // namespace

TEST(Lora, DefaultTargetsWrapFiveShapeProjectionsPerBlock) {
  Toy toy(2);
  auto before = toy.run();
  auto report = simu::lora::inject_lora(*toy.root, small_cfg());
  EXPECT_EQ(report.layers, 10);
  EXPECT_EQ(report.parameters, analytic_params(4, 2));
  for (const auto& p : report.paths) EXPECT_TRUE(is_shape_target(p)) << p;
  // Parameter names follow PEFT's module layout.
  auto params = simu::lora::lora_parameters(*toy.root);
  ASSERT_EQ(params.size(), 20u);
  EXPECT_EQ(params[0].first, report.paths[0] + ".lora_A.weight");
  EXPECT_EQ(params[1].first, report.paths[0] + ".lora_B.weight");
  // Only adapter parameters train; names in the module tree carry lora_A / lora_B.
  int trainable = 0;
  for (auto& p : toy.root->named_parameters()) {
    const bool lora = p.key().find(".lora_") != std::string::npos;
    EXPECT_EQ(p.value().requires_grad(), lora) << p.key();
    trainable += lora;
  }
  EXPECT_EQ(trainable, 20);
  // B = 0: outputs are exactly the base outputs.
  auto after = toy.run();
  for (auto& [path, y] : before) EXPECT_TRUE(torch::equal(y, after[path])) << path;
}

TEST(Lora, InitMatchesKaimingUniformSqrt5) {
  Toy toy(2);
  simu::lora::inject_lora(*toy.root, small_cfg(64, 128));
  for (auto& [name, t] : simu::lora::lora_parameters(*toy.root)) {
    EXPECT_EQ(t.scalar_type(), torch::kFloat32);
    if (name.find("lora_B") != std::string::npos) {
      EXPECT_EQ(t.abs().max().item<double>(), 0.0) << name;
    } else {
      // kaiming_uniform(a=sqrt(5)) on [r, in]: U(-1/sqrt(in), 1/sqrt(in)), std = bound / sqrt(3).
      const double bound = 1.0 / std::sqrt(static_cast<double>(t.size(1)));
      EXPECT_LE(t.abs().max().item<double>(), bound) << name;
      // The sample std of n uniform values has standard error ~0.26 bound / sqrt(n) (fourth moment
      // b^4 / 5): 0.1 bound is 0.39 sqrt(n) >= 12 of them for these n = r x in >= 1024 values.
      EXPECT_NEAR(t.std().item<double>(), bound / std::sqrt(3.0), 0.1 * bound) << name;
    }
  }
}

TEST(Lora, ForwardEqualsIndependentFormula) {
  for (bool rs : {false, true}) {
    Toy toy(1);
    auto cfg = small_cfg(4, 8);
    cfg.use_rslora = rs;
    simu::lora::inject_lora(*toy.root, cfg);
    randomize(*toy.root);
    const double scale = rs ? 8.0 / 2.0 : 8.0 / 4.0;
    auto& l = toy.linears.at("reverse_fn.backbone.blocks.0.cross_attn.shape.to_kv");
    auto x = torch::randn({2, 5, kCond()}, torch::kFloat64);
    auto W = l->weight.detach().to(torch::kFloat64), b = l->bias.detach().to(torch::kFloat64);
    auto adapter = simu::lora::lora_adapter(*l);
    auto A = adapter->A->weight.detach().to(torch::kFloat64), B = adapter->B->weight.detach().to(torch::kFloat64);
    auto want = x.matmul(W.t()) + b + scale * x.matmul(A.t()).matmul(B.t());
    auto got = l->forward(x.to(torch::kFloat32));
    // One fp32 path against float64: x rounded (1), the Cc-term products, the r-term product, the
    // scale and the sums (3).
    const double tol = simu::testing::gamma(1 + kCond() + cfg.r + 3);
    EXPECT_TRUE(simu::testing::close(got, want, tol, rs ? "rslora" : "lora"));
  }
}

TEST(Lora, RegexAndSuffixTargetsAndErrors) {
  // The regex of the PEFT fixture selects the same 10 layers as the default suffix list.
  const std::string regex =
      R"(.*blocks\.\d+\.(self_attn\.(to_qkv|to_out)\.shape|cross_attn\.shape\.(to_q|to_kv|to_out))$)";
  {
    Toy a(2), b(2);
    auto cfg = small_cfg();
    cfg.target_regex = regex;
    cfg.target_suffixes.clear();
    auto ra = simu::lora::inject_lora(*a.root, cfg);
    auto rb = simu::lora::inject_lora(*b.root, small_cfg());
    EXPECT_EQ(ra.paths, rb.paths);
  }
  // Full match: a regex matching only a prefix of the path selects nothing -> error.
  {
    Toy t(1);
    auto cfg = small_cfg();
    cfg.target_regex = R"(reverse_fn\.backbone\.blocks\.0\.self_attn)";
    cfg.target_suffixes.clear();
    EXPECT_THROW(simu::lora::inject_lora(*t.root, cfg), simu::Error);
  }
  // A regex that reaches a container module -> error naming it.
  {
    Toy t(1);
    auto cfg = small_cfg();
    cfg.target_regex = R"(.*cross_attn\.shape(\.to_q)?)";
    cfg.target_suffixes.clear();
    try {
      simu::lora::inject_lora(*t.root, cfg);
      FAIL() << "expected an error";
    } catch (const simu::Error& e) {
      EXPECT_NE(std::string(e.what()).find("'reverse_fn.backbone.blocks.0.cross_attn.shape' is a"), std::string::npos)
          << e.what();
    }
  }
  // A suffix that matches nothing -> error naming it.
  {
    Toy t(1);
    auto cfg = small_cfg();
    cfg.target_suffixes = {"self_attn.to_qkv.shape", "attn.to_v"};
    try {
      simu::lora::inject_lora(*t.root, cfg);
      FAIL() << "expected an error";
    } catch (const simu::Error& e) {
      EXPECT_NE(std::string(e.what()).find("'attn.to_v' matches no module"), std::string::npos) << e.what();
    }
  }
  // Suffixes match at a dot boundary only ("to_q" does not match "to_qkv.x" or "xto_q").
  {
    Toy t(1);
    auto cfg = small_cfg();
    cfg.target_suffixes = {"to_q"};
    auto r = simu::lora::inject_lora(*t.root, cfg);
    EXPECT_EQ(r.layers, 2);  // cross_attn.{shape,6drotation_normalized}.to_q
    // Injecting twice is an error.
    EXPECT_THROW(simu::lora::inject_lora(*t.root, cfg), simu::Error);
  }
}

TEST(Lora, EnableDisableGivesBaseOutputsExactly) {
  Toy toy(2);
  auto base = toy.run();
  simu::lora::inject_lora(*toy.root, small_cfg());
  randomize(*toy.root);
  auto adapted = toy.run();
  simu::lora::set_lora_enabled(*toy.root, false);
  auto off = toy.run();
  simu::lora::set_lora_enabled(*toy.root, true);
  auto on = toy.run();
  for (auto& [path, y] : base) {
    EXPECT_TRUE(torch::equal(off[path], y)) << path;
    EXPECT_TRUE(torch::equal(on[path], adapted[path])) << path;
    // The adapter (0.1-sized random A, B) moves a target's output far beyond rounding (one path of its
    // products: gamma(in + r + 3)).
    if (is_shape_target(path)) EXPECT_GT(simu::testing::rel_err(adapted[path], y), simu::testing::gamma(4 * kC() + 3)) << path;
  }
}

TEST(Lora, MergeMatchesUnmergedAndUnmergeRestoresWeights) {
  Toy toy(2);
  const auto cfg = small_cfg();
  simu::lora::inject_lora(*toy.root, cfg);
  randomize(*toy.root);
  std::map<std::string, torch::Tensor> weights;
  for (auto& [path, l] : toy.linears) weights[path] = l->weight.detach().clone();
  auto unmerged = toy.run();
  simu::lora::merge_lora(*toy.root);
  auto merged = toy.run();
  // Merged weight = W + d, d = scale * B A, checked in float64: the r-term product, the scale and the
  // sum: r + 2 roundings of |W| + |d|, relative to |W + d|. Unmerging, (W + d) - d: the sum's and the
  // difference's roundings (and d's): 4 of |W + d| + |W|, relative to |W|.
  std::map<std::string, double> unmerge_tol;
  double worst_unmerge = 0;
  for (auto& [path, l] : toy.linears) {
    const auto w = weights[path].to(torch::kFloat64);
    const double w_max = w.abs().max().item<double>(), merged_max = l->weight.abs().max().item<double>();
    unmerge_tol[path] = simu::testing::gamma(cfg.r + 4) * (merged_max + w_max) / w_max;
    worst_unmerge = std::max(worst_unmerge, unmerge_tol[path]);
    auto adapter = simu::lora::lora_adapter(*l);
    if (!adapter) continue;
    const auto d = 2.0 * adapter->B->weight.detach().to(torch::kFloat64).matmul(adapter->A->weight.detach().to(torch::kFloat64));
    const auto want = w + d;
    const double tol = simu::testing::gamma(cfg.r + 2) * (w_max + d.abs().max().item<double>()) / want.abs().max().item<double>();
    EXPECT_TRUE(simu::testing::close(l->weight, want, tol, "merged weight " + path));
  }
  // The merged weight's product against base + adapter products: two fp32 paths of at most in + r + 3
  // roundings, plus the merged weight's own (above, relative to the output: bounded by the same).
  const double path_tol = simu::testing::two_paths(std::max(kC(), kCond()) + cfg.r + 3) + simu::testing::gamma(cfg.r + 4);
  for (auto& [path, y] : unmerged) EXPECT_TRUE(simu::testing::close(merged[path], y, path_tol, "merged " + path));
  simu::lora::merge_lora(*toy.root);  // idempotent
  EXPECT_TRUE(simu::testing::close(toy.run().begin()->second, merged.begin()->second, 0.0, "merge twice"));
  simu::lora::unmerge_lora(*toy.root);
  for (auto& [path, l] : toy.linears) EXPECT_TRUE(simu::testing::close(l->weight, weights[path], unmerge_tol[path], path));
  auto again = toy.run();
  // Products of weights within unmerge_tol of the first ones: that much more than two paths' rounding.
  for (auto& [path, y] : unmerged)
    EXPECT_TRUE(simu::testing::close(again[path], y, path_tol + worst_unmerge, "unmerged " + path));
  // Disabling a merged model unmerges it: outputs are the base outputs.
  simu::lora::merge_lora(*toy.root);
  simu::lora::set_lora_enabled(*toy.root, false);
  for (auto& [path, l] : toy.linears) EXPECT_TRUE(simu::testing::close(l->weight, weights[path], unmerge_tol[path], path));
  EXPECT_THROW(simu::lora::merge_lora(*toy.root), simu::Error);  // merging disabled adapters
}

TEST(Lora, AdapterStaysFp32WhenModelIsCast) {
  Toy toy(1);
  simu::lora::inject_lora(*toy.root, small_cfg());
  randomize(*toy.root);
  auto& l = toy.linears.at("reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape");
  torch::manual_seed(1);
  auto x = torch::randn({2, 5, kC()});
  auto want = l->forward(x);
  toy.root->to(torch::kBFloat16);
  EXPECT_EQ(l->weight.scalar_type(), torch::kBFloat16);
  for (auto& [name, t] : simu::lora::lora_parameters(*toy.root)) EXPECT_EQ(t.scalar_type(), torch::kFloat32) << name;
  auto got = l->forward(x.to(torch::kBFloat16));
  EXPECT_EQ(got.scalar_type(), torch::kBFloat16);
  // bf16 base (x, W, the output), the fp32 adapter's result rounded to bf16, the bf16 sum: 5 bf16
  // roundings, plus fp32 accumulation of in + r terms.
  const double fp32_terms = simu::testing::gamma(kC() + small_cfg().r);
  EXPECT_TRUE(simu::testing::close(got, want, simu::testing::gamma(5, simu::testing::kBf16Unit) + fp32_terms, "bf16 forward"));
  // Under CPU autocast (bf16) the adapter follows autocast.
  toy.root->to(torch::kFloat32);
  {
    at::autocast::set_autocast_enabled(at::kCPU, true);
    at::autocast::set_autocast_dtype(at::kCPU, at::kBFloat16);
    auto y = l->forward(x);
    at::autocast::set_autocast_enabled(at::kCPU, false);
    at::autocast::clear_cache();
    EXPECT_EQ(y.scalar_type(), torch::kBFloat16);
    // Every product in bf16: x, W, the base output, A, A x, B, B A x, the sum: 8 bf16 roundings.
    EXPECT_TRUE(simu::testing::close(y, want, simu::testing::gamma(8, simu::testing::kBf16Unit) + fp32_terms, "autocast forward"));
  }
}

TEST(Lora, DropoutOnlyInTraining) {
  Toy toy(1);
  auto cfg = small_cfg();
  cfg.dropout = 0.5;
  simu::lora::inject_lora(*toy.root, cfg);
  randomize(*toy.root);
  auto& l = toy.linears.at("reverse_fn.backbone.blocks.0.self_attn.to_out.shape");
  auto x = torch::randn({4, 16, kC()});
  toy.root->train(true);
  auto a = l->forward(x), b = l->forward(x);
  // Equal masks would give equal bits (the same arithmetic): the two draws differ.
  EXPECT_FALSE(torch::equal(a, b));
  toy.root->eval();
  EXPECT_TRUE(torch::equal(l->forward(x), l->forward(x)));
  // Dropout never touches the base term: with adapters off, train mode is deterministic.
  toy.root->train(true);
  simu::lora::set_lora_enabled(*toy.root, false);
  EXPECT_TRUE(torch::equal(l->forward(x), l->forward(x)));
}

TEST(Lora, ImportsPythonPeftFixture) {
  const std::string dir = simu::testing::fixture("lora_small");
  Toy toy(dims().blocks);
  auto cfg = simu::lora::load_peft(dir, *toy.root);
  // The settings of the file (PEFT's names), read independently.
  const auto jf = nlohmann::json::parse(std::ifstream(dir + "/adapter_config.json"));
  EXPECT_EQ(cfg.r, jf.at("r").get<int64_t>());
  EXPECT_EQ(cfg.alpha, jf.at("lora_alpha").get<double>());
  EXPECT_EQ(cfg.dropout, jf.at("lora_dropout").get<double>());
  EXPECT_EQ(cfg.use_rslora, jf.value("use_rslora", false));
  EXPECT_FALSE(cfg.target_regex.empty());
  // Every tensor of the file landed in the parameter of the same path, bit for bit.
  auto file = simu::data::load_safetensors(dir + "/adapter_model.safetensors");
  auto params = simu::lora::lora_parameters(*toy.root);
  ASSERT_EQ(params.size(), file.size());
  for (auto& [name, t] : params) {
    auto it = file.find("base_model.model." + name);
    ASSERT_NE(it, file.end()) << name;
    EXPECT_TRUE(torch::equal(t, it->second)) << name;
  }
  // The adapted output uses scale = alpha / r (PEFT's, without rslora).
  const std::string last = fmt::format("reverse_fn.backbone.blocks.{}.self_attn.to_qkv.shape", dims().blocks - 1);
  auto& l = toy.linears.at(last);
  auto x = torch::randn({3, kC()});
  auto A = file.at("base_model.model." + last + ".lora_A.weight");
  auto B = file.at("base_model.model." + last + ".lora_B.weight");
  const double scale = jf.at("lora_alpha").get<double>() / jf.at("r").get<double>();
  auto want = torch::linear(x, l->weight, l->bias) + scale * x.matmul(A.t()).matmul(B.t());
  // Two fp32 paths of the base (C terms) and adapter (C + r terms) products, the scale and the sum.
  const double tol = simu::testing::two_paths(kC() + cfg.r + 2);
  EXPECT_TRUE(simu::testing::close(l->forward(x), want, tol, "fixture adapter forward"));
}

TEST(Lora, ImportMismatchNamesKeyAndBothShapes) {
  const std::string dir = simu::testing::fixture("lora_small");
  const int64_t file_r = simu::lora::read_peft_config(dir).r;
  // Another rank already injected: every key mismatches; the message names key and both shapes.
  {
    Toy toy(dims().blocks);
    const int64_t other_r = 2 * file_r;
    simu::lora::inject_lora(*toy.root, small_cfg(other_r, 2.0 * other_r));
    try {
      simu::lora::load_peft(dir, *toy.root);
      FAIL() << "expected an error";
    } catch (const simu::Error& e) {
      const std::string m = e.what();
      EXPECT_NE(m.find(fmt::format("base_model.model.reverse_fn.backbone.blocks.0.self_attn.to_out.shape.lora_A.weight: "
                                   "file [{}, {}] vs model [{}, {}]",
                                   file_r, kC(), other_r, kC())),
                std::string::npos)
          << m;
    }
  }
  // Different targets: the file's extra keys are unexpected, the model's extra adapters missing.
  {
    Toy toy(dims().blocks);
    auto cfg = small_cfg();
    cfg.target_suffixes = {"self_attn.to_qkv.shape", "mlp.shape.mlp.0"};
    simu::lora::inject_lora(*toy.root, cfg);
    try {
      simu::lora::load_peft(dir, *toy.root);
      FAIL() << "expected an error";
    } catch (const simu::Error& e) {
      const std::string m = e.what();
      // Missing: the mlp adapters (A and B per block); unexpected: the file's other targets than to_qkv.
      const auto file_keys = simu::data::SafeTensorsFile::open(dir + "/adapter_model.safetensors").keys().size();
      EXPECT_NE(m.find(fmt::format("missing ({}): base_model.model.reverse_fn.backbone.blocks.0.mlp.shape.mlp.0.lora_A.weight",
                                   2 * dims().blocks)),
                std::string::npos)
          << m;
      EXPECT_NE(m.find(fmt::format("unexpected ({})", file_keys - 2 * dims().blocks)), std::string::npos) << m;
    }
  }
  // A model with one block fewer: the last block's keys are unexpected.
  {
    Toy toy(dims().blocks - 1);
    auto base = toy.run();
    EXPECT_THROW(simu::lora::load_peft(dir, *toy.root), simu::Error);
    // The failed load removed the adapters it had injected: the model is as before.
    EXPECT_TRUE(simu::lora::lora_layers(*toy.root).empty());
    for (auto& p : toy.root->named_parameters()) EXPECT_EQ(p.key().find("lora_"), std::string::npos) << p.key();
    auto after = toy.run();
    for (auto& [path, y] : base) EXPECT_TRUE(torch::equal(after[path], y)) << path;
  }
}

TEST(Lora, ExportImportRoundTripIsLossless) {
  const std::string out = simu::testing::temp_dir("lora_roundtrip") + "/adapter";
  Toy a(dims().blocks);  // the fixture adapter's key set below
  auto cfg = small_cfg(4, 8);
  cfg.dropout = 0.1;
  cfg.use_rslora = true;
  simu::lora::inject_lora(*a.root, cfg);
  randomize(*a.root, 11);
  simu::lora::save_peft(out, *a.root, cfg, "sam-3d-objects ss_generator (test toy)");

  // Files: same key set as the Python PEFT fixture; config fields as PEFT writes them.
  auto file = simu::data::SafeTensorsFile::open(out + "/adapter_model.safetensors");
  auto fixture = simu::data::SafeTensorsFile::open(simu::testing::fixture("lora_small/adapter_model.safetensors"));
  std::set<std::string> ka(file.keys().begin(), file.keys().end()), kb(fixture.keys().begin(), fixture.keys().end());
  EXPECT_EQ(ka, kb);
  EXPECT_EQ(file.metadata().at("format"), "pt");
  auto j = nlohmann::json::parse(std::ifstream(out + "/adapter_config.json"));
  EXPECT_EQ(j["peft_type"], "LORA");
  EXPECT_EQ(j["r"], 4);
  EXPECT_EQ(j["lora_alpha"], 8);
  EXPECT_EQ(j["lora_dropout"], 0.1);
  EXPECT_EQ(j["use_rslora"], true);
  EXPECT_EQ(j["bias"], "none");
  EXPECT_EQ(j["fan_in_fan_out"], false);
  EXPECT_TRUE(j["task_type"].is_null());
  EXPECT_TRUE(j["target_modules"].is_array());
  EXPECT_EQ(j["base_model_name_or_path"], "sam-3d-objects ss_generator (test toy)");
  // Every key of the Python fixture config is present (PEFT reads what it wrote).
  auto jf = nlohmann::json::parse(std::ifstream(simu::testing::fixture("lora_small/adapter_config.json")));
  for (const char* k : {"peft_type", "r", "lora_alpha", "lora_dropout", "target_modules", "bias", "use_rslora",
                        "fan_in_fan_out", "task_type", "peft_version", "use_dora", "rank_pattern", "alpha_pattern"})
    EXPECT_TRUE(j.contains(k) && jf.contains(k)) << k;

  // Import into a fresh tree: identical config, parameters and outputs.
  Toy b(dims().blocks);
  auto cfg2 = simu::lora::load_peft(out, *b.root);
  EXPECT_EQ(cfg2.r, cfg.r);
  EXPECT_EQ(cfg2.alpha, cfg.alpha);
  EXPECT_EQ(cfg2.dropout, cfg.dropout);
  EXPECT_EQ(cfg2.use_rslora, cfg.use_rslora);
  EXPECT_EQ(cfg2.target_suffixes, cfg.target_suffixes);
  auto pa = simu::lora::lora_parameters(*a.root), pb = simu::lora::lora_parameters(*b.root);
  ASSERT_EQ(pa.size(), pb.size());
  for (size_t i = 0; i < pa.size(); ++i) {
    EXPECT_EQ(pa[i].first, pb[i].first);
    EXPECT_TRUE(torch::equal(pa[i].second, pb[i].second)) << pa[i].first;
  }
  // Overwriting an existing directory works (per-file atomic replace).
  simu::lora::save_peft(out, *b.root, cfg2, "again");
  EXPECT_TRUE(std::filesystem::exists(out + "/adapter_model.safetensors"));
}

TEST(Lora, SavedMergedCheckpointHasOfficialNamesAndMergedWeights) {
  const std::string path = simu::testing::temp_dir("lora_merged") + "/merged.safetensors";
  Toy toy(1);
  simu::lora::inject_lora(*toy.root, small_cfg());
  randomize(*toy.root);
  std::map<std::string, torch::Tensor> before;
  for (auto& [path_, l] : toy.linears) before[path_] = l->weight.detach().clone();
  simu::lora::save_merged(path, *toy.root);
  auto file = simu::data::load_safetensors(path);
  EXPECT_EQ(file.size(), toy.linears.size() * 2);  // weight + bias per Linear, no lora keys
  for (auto& [p, l] : toy.linears) {
    const auto key = "_base_models.generator." + p + ".weight";
    ASSERT_TRUE(file.count(key)) << key;
    EXPECT_TRUE(torch::equal(l->weight, before[p])) << "model modified: " << p;
    auto adapter = simu::lora::lora_adapter(*l);
    auto want = adapter ? before[p].to(torch::kFloat64) + 2.0 * adapter->B->weight.detach().to(torch::kFloat64).matmul(
                                                                    adapter->A->weight.detach().to(torch::kFloat64))
                        : before[p].to(torch::kFloat64);
    // W + scale B A in fp32: r + 2 roundings of |W| + |B A| (as in the merge test), relative to |want|.
    const double w_max = before[p].abs().max().item<double>();
    const double tol = simu::testing::gamma(small_cfg().r + 2) * (w_max + (want.abs().max().item<double>() + w_max)) /
                       want.abs().max().item<double>();
    EXPECT_TRUE(simu::testing::close(file.at(key), want, tol, key));
    EXPECT_TRUE(torch::equal(file.at("_base_models.generator." + p + ".bias"), l->bias)) << p;
  }
}

TEST(Lora, ConfigFromReaderAcceptsRegexOrList) {
  {
    YAML::Node n = YAML::Load("{r: 16, alpha: 32, dropout: 0.05, use_rslora: true, target_modules: '.*to_q'}");
    simu::config::Reader r(n, "test.yaml");
    auto c = LoraConfig::from(r);
    r.finish();
    EXPECT_EQ(c.r, 16);
    EXPECT_EQ(c.alpha, 32.0);
    EXPECT_EQ(c.dropout, 0.05);
    EXPECT_TRUE(c.use_rslora);
    EXPECT_EQ(c.target_regex, ".*to_q");
    EXPECT_TRUE(c.target_suffixes.empty());
    EXPECT_DOUBLE_EQ(c.scale(), 32.0 / 4.0);
  }
  {
    YAML::Node n = YAML::Load("{target_modules: [to_q, to_kv]}");
    simu::config::Reader r(n, "test.yaml");
    auto c = LoraConfig::from(r);
    EXPECT_EQ(c.r, 64);
    EXPECT_EQ(c.alpha, 128.0);
    EXPECT_DOUBLE_EQ(c.scale(), 2.0);
    EXPECT_EQ(c.target_suffixes, (std::vector<std::string>{"to_q", "to_kv"}));
  }
  {
    YAML::Node n = YAML::Load("{r: 0}");
    simu::config::Reader r(n, "bad.yaml");
    EXPECT_THROW(LoraConfig::from(r), simu::Error);
  }
}

TEST(Lora, PeftNames) {
  const std::string n = "reverse_fn.backbone.blocks.0.cross_attn.shape.to_q.lora_B.weight";
  EXPECT_EQ(simu::lora::peft_file_key(n), "base_model.model." + n);
  EXPECT_EQ(simu::lora::peft_param_key(n),
            "base_model.model.reverse_fn.backbone.blocks.0.cross_attn.shape.to_q.lora_B.default.weight");
  EXPECT_EQ(simu::lora::model_name_from_peft(simu::lora::peft_param_key(n)), n);
  EXPECT_EQ(simu::lora::model_name_from_peft(simu::lora::peft_file_key(n)), n);
  EXPECT_THROW(simu::lora::model_name_from_peft("base_model.model.x.lora_magnitude_vector.default"), simu::Error);
}

// export_adapter / load_peft refuse what would silently produce a broken adapter: NaN/Inf values,
// non-float dtypes, a lora_A without its lora_B (and back), mixed ranks; each error names the tensor.
TEST(Lora, AdapterTensorChecksNameTheTensor) {
  const std::string a = "base_model.model.blocks.0.to_q.lora_A.weight";
  const std::string b = "base_model.model.blocks.0.to_q.lora_B.weight";
  auto good = [&] {
    return std::map<std::string, torch::Tensor>{{a, torch::randn({4, 8})}, {b, torch::zeros({6, 4})}};
  };
  EXPECT_NO_THROW(simu::lora::check_adapter_tensors(good(), 4, "src"));
  auto err = [&](std::map<std::string, torch::Tensor> t, int64_t r = 4) {
    try {
      simu::lora::check_adapter_tensors(t, r, "src");
    } catch (const simu::Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  auto t = good();
  t[a][1][2] = std::numeric_limits<float>::quiet_NaN();
  EXPECT_NE(err(t).find("src: tensor '" + a + "' holds NaN or Inf (1 non-finite"), std::string::npos) << err(t);
  t = good();
  t[b] = torch::full({6, 4}, std::numeric_limits<float>::infinity());
  EXPECT_NE(err(t).find("'" + b + "' holds NaN or Inf"), std::string::npos) << err(t);
  t = good();
  t[a] = torch::ones({4, 8}, torch::kInt32);
  EXPECT_NE(err(t).find("'" + a + "' has dtype Int, expected a float type"), std::string::npos) << err(t);
  t = good();
  t[a] = torch::ones({4, 8}, torch::kBool);
  EXPECT_NE(err(t).find("expected a float type"), std::string::npos) << err(t);
  t = good();
  t.erase(b);
  EXPECT_NE(err(t).find("'" + a + "' has no lora_B partner"), std::string::npos) << err(t);
  t = good();
  t.erase(a);
  EXPECT_NE(err(t).find("'" + b + "' has no lora_A partner"), std::string::npos) << err(t);
  t = good();
  EXPECT_NE(err(t, 8).find("which is not rank 8"), std::string::npos) << err(t, 8);
  t = good();
  t["base_model.model.x.weight"] = torch::ones({2, 2});
  EXPECT_NE(err(t).find("'base_model.model.x.weight' is not a LoRA A/B weight"), std::string::npos) << err(t);
  t = good();
  t[a] = torch::ones({4, 8, 1});
  EXPECT_NE(err(t).find("expected a non-empty 2-D matrix"), std::string::npos) << err(t);
}

// save_peft_tensors builds the directory beside the target and swaps it in whole: a refused export
// leaves the previous adapter untouched; a dead writer's temporary directory is removed.
TEST(Lora, PeftExportIsAtomicAndRefusesBadTensors) {
  const std::string dir = simu::testing::temp_dir("peft_atomic");
  const std::string out = dir + "/adapter";
  LoraConfig cfg;
  cfg.r = 4;
  cfg.alpha = 8;
  cfg.target_suffixes = {"to_q"};
  const std::string a = "base_model.model.blocks.0.to_q.lora_A.weight";
  const std::string b = "base_model.model.blocks.0.to_q.lora_B.weight";
  std::map<std::string, torch::Tensor> t{{a, torch::randn({4, 8})}, {b, torch::randn({6, 4})}};
  simu::lora::save_peft_tensors(out, t, cfg, "test");
  const auto first = simu::data::load_safetensors(out + "/adapter_model.safetensors");
  auto bad = t;
  bad[b] = torch::full({6, 4}, std::numeric_limits<float>::quiet_NaN());
  EXPECT_THROW(simu::lora::save_peft_tensors(out, bad, cfg, "test"), simu::Error);
  const auto kept = simu::data::load_safetensors(out + "/adapter_model.safetensors");
  EXPECT_TRUE(torch::equal(kept.at(b), first.at(b)));
  // A dead writer's leftover is cleaned by the next export; nothing else is left beside the target.
  const pid_t dead = ::fork();
  if (dead == 0) ::_exit(0);
  int status = 0;
  ::waitpid(dead, &status, 0);
  std::filesystem::create_directories(out + ".tmp-" + std::to_string(dead));
  simu::lora::save_peft_tensors(out, t, cfg, "test");
  int entries = 0;
  for (const auto& e : std::filesystem::directory_iterator(dir)) entries += e.path() != out;
  EXPECT_EQ(entries, 0);
  EXPECT_EQ(simu::lora::read_peft_config(out).r, 4);
}
