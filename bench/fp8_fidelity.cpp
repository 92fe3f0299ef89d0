// fp8_fidelity: what the opt-in FP8 frozen base (train.fp8_base, models/fp8_linear.h) costs in
// fidelity on one FM-DPO step, against the bf16 base on the same batch and the same noise.
//
// The real-size generator (random weights) with LoRA r 64 / alpha 128 on the 120 shape projections;
// lora_B is drawn N(0, --lora-b-std^2) (a fresh adapter has B = 0: policy = reference, d_theta - d_ref
// = 0 and no gradient into A). --pairs synthetic pairs (random latents, noise, t logit-normal, weights
// 1.0 / 0.1 alternating, --cond-len condition tokens) in micro-batches of --micro, the gradient
// accumulated over all of them as the trainer does (sum of w * loss / pairs). Variants on the same
// inputs: bf16 (the reference: bf16 autocast, bf16 base), fp8 (FP8 base on the LoRA-wrapped layers,
// FP8 input gradients: the default of train.fp8_base), fp8/bf16-bwd (FP8 forward, bf16 input gradients:
// train.fp8_base_backward bf16), fp8 all (every frozen Linear, MLPs included: fp8_base_layers all), and with --fp32 the IEEE fp32 step (no autocast, no TF32), to show how far bf16 itself is from fp32.
// Printed per variant against bf16: the adapters' gradient (all 240 tensors flattened) cosine and
// relative L2 error, the minimum and median per-tensor cosine (and which tensor is lowest), and per pair
// d_theta - d_ref (max abs difference, its scale, Pearson correlation, sign agreement) and the loss.
// --csv FILE writes the per-tensor cosines (tensor, variant, cosine, relative error).
#include <ATen/CPUGeneratorImpl.h>

#include <algorithm>
#include <tuple>
#include <fstream>
#include <sstream>

#include <fmt/format.h>

#include "common/cli.h"
#include "common/error.h"
#include "common/fs.h"
#include "models/fp8_linear.h"
#include "models/generator.h"
#include "models/precision.h"
#include "training/fmdpo.h"
#include "training/generator_policy.h"

using namespace simu::training;
namespace sm = simu::models;

namespace {

struct Options {
  std::string generator = "configs/stage1_real.yaml";
  int64_t cond_len = 2800, pairs = 8, micro = 2;
  double lora_b_std = 1e-3;
  uint64_t seed = 0;
  bool fp32 = false;
  std::string csv;
};

// One step's results: per-tensor gradients (float64, CPU), per-pair d_theta - d_ref and loss.
struct StepResult {
  std::vector<std::pair<std::string, torch::Tensor>> grads;
  torch::Tensor dd, loss;  // [pairs] float64
};

// The micro-batches: identical inputs for every variant (CPU generator seeded once).
std::vector<FmdpoInputs> make_inputs(const Options& o, const sm::FlowModelConfig& fc, torch::Device dev) {
  int64_t T = 0;
  for (const auto& s : fc.latents)
    if (s.name == "shape") T = s.tokens();
  auto rng = at::make_generator<at::CPUGeneratorImpl>(o.seed + 1);
  std::vector<FmdpoInputs> out;
  for (int64_t first = 0; first < o.pairs; first += o.micro) {
    const int64_t m = std::min(o.micro, o.pairs - first);
    FmdpoInputs in;
    for (auto* t : {&in.x_pos, &in.x_neg, &in.eps_pos, &in.eps_neg}) *t = torch::randn({m, T, fc.in_channels}, rng).to(dev);
    in.cond = torch::randn({m, o.cond_len, fc.cond_channels}, rng).to(dev);
    in.t = torch::sigmoid(torch::randn({m}, rng)).to(dev);  // logit-normal(0, 1)
    std::vector<float> w;
    for (int64_t i = 0; i < m; ++i) w.push_back((first + i) % 2 == 0 ? 1.0f : 0.1f);
    in.w = torch::tensor(w).to(dev);
    out.push_back(std::move(in));
  }
  return out;
}

// One accumulated step in `precision` (bf16 autocast or IEEE fp32) on the inputs.
StepResult run_step(PolicyModel& policy, const std::vector<FmdpoInputs>& inputs, int64_t pairs, sm::Precision precision) {
  for (auto& [name, p] : policy.adapter_parameters()) p.mutable_grad() = torch::Tensor();
  std::vector<torch::Tensor> dd, loss;
  for (const auto& in : inputs) {
    FmdpoTerms terms;
    {
      sm::Autocast ac(precision);
      terms = fmdpo_terms(policy, in, 500.0, false);
    }
    ((in.w * terms.per_pair).sum() / static_cast<double>(pairs)).backward();
    dd.push_back((terms.d_theta - terms.d_ref).detach().to(torch::kCPU, torch::kFloat64));
    loss.push_back(terms.per_pair.detach().to(torch::kCPU, torch::kFloat64));
  }
  StepResult r;
  for (auto& [name, p] : policy.adapter_parameters()) r.grads.emplace_back(name, p.grad().to(torch::kCPU, torch::kFloat64));
  r.dd = torch::cat(dd);
  r.loss = torch::cat(loss);
  return r;
}

double cosine(const torch::Tensor& a, const torch::Tensor& b) {
  return (a.flatten().dot(b.flatten()) / (a.norm() * b.norm()).clamp_min(1e-300)).item<double>();
}

double rel_l2(const torch::Tensor& got, const torch::Tensor& want) {
  return ((got - want).norm() / want.norm().clamp_min(1e-300)).item<double>();
}

// Pearson correlation of two vectors (float64).
double pearson(const torch::Tensor& a, const torch::Tensor& b) { return cosine(a - a.mean(), b - b.mean()); }

// The comparison of `got` against `ref` (one table line) and its per-tensor rows for the CSV.
void compare(const std::string& name, const StepResult& got, const StepResult& ref, std::ostringstream& csv) {
  std::vector<torch::Tensor> g, r;
  std::vector<std::pair<double, std::string>> per;
  for (size_t i = 0; i < got.grads.size(); ++i) {
    const auto& [key, t] = got.grads[i];
    const auto& w = ref.grads[i].second;
    g.push_back(t.flatten());
    r.push_back(w.flatten());
    per.emplace_back(cosine(t, w), key);
    csv << key << "," << name << "," << fmt::format("{:.7f},{:.5g}", per.back().first, rel_l2(t, w)) << "\n";
  }
  auto ga = torch::cat(g), ra = torch::cat(r);
  std::sort(per.begin(), per.end());
  const auto median = per[per.size() / 2].first;
  const double dd_diff = (got.dd - ref.dd).abs().max().item<double>();
  const double dd_scale = ref.dd.abs().max().item<double>();
  const double signs = (got.dd.sign() == ref.dd.sign()).to(torch::kFloat64).mean().item<double>();
  const double loss_diff = (got.loss - ref.loss).abs().max().item<double>();
  fmt::print("{:<14} {:>10.6f} {:>9.3g} {:>10.6f} {:>10.6f} {:>12.3g} {:>12.3g} {:>8.5f} {:>6.0f}% {:>10.3g}   {}\n", name,
             cosine(ga, ra), rel_l2(ga, ra), per.front().first, median, dd_diff, dd_scale, pearson(got.dd, ref.dd),
             100 * signs, loss_diff, per.front().second);
}

// The policy with random lora_B (std o.lora_b_std), the variants, the table.
void run(const Options& o) {
  const torch::Device dev(torch::kCUDA);
  sm::require_fp8_device(dev, "fp8_fidelity");
  const auto gcfg = sm::GeneratorConfig::from_official_file(o.generator);
  YAML::Node lora = YAML::Load(
      "{r: 64, alpha: 128, dropout: 0.0, target_modules: "
      "'.*blocks\\.\\d+\\.(self_attn\\.(to_qkv|to_out)\\.shape|cross_attn\\.shape\\.(to_q|to_kv|to_out))$'}");
  torch::manual_seed(o.seed);
  auto policy = make_generator_policy(o.generator, "", lora, "", dev);
  {
    torch::NoGradGuard ng;
    for (auto& [name, p] : policy->adapter_parameters())
      if (name.find("lora_B") != std::string::npos) p.normal_(0.0, o.lora_b_std);
  }
  const auto inputs = make_inputs(o, gcfg.backbone, dev);
  fmt::print("fp8_fidelity: {} (random weights), LoRA r64 shape branch, lora_B ~ N(0, {:g}^2), {} pairs of {} condition "
             "tokens in micro-batches of {}, seed {}; every variant against the bf16 step on the same inputs\n",
             o.generator, o.lora_b_std, o.pairs, o.cond_len, o.micro, o.seed);
  const auto ref = run_step(*policy, inputs, o.pairs, sm::Precision::kBf16);
  std::ostringstream csv;
  csv << "tensor,variant,cosine,rel_l2\n";
  fmt::print("{:<14} {:>10} {:>9} {:>10} {:>10} {:>12} {:>12} {:>8} {:>7} {:>10}   {}\n", "variant", "grad cos", "grad err",
             "min cos", "median cos", "dd max diff", "dd max |ref|", "dd corr", "sign", "loss diff", "lowest tensor");
  using simu::lora::Fp8Scope;
  for (auto [backward, scope, name] : {std::tuple{sm::Fp8Backward::kFp8, Fp8Scope::kAdapted, "fp8"},
                                       std::tuple{sm::Fp8Backward::kBf16, Fp8Scope::kAdapted, "fp8/bf16-bwd"},
                                       std::tuple{sm::Fp8Backward::kFp8, Fp8Scope::kAll, "fp8 all"}}) {
    set_policy_fp8_base(*policy, false, backward, "fp8_fidelity");
    set_policy_fp8_base(*policy, true, backward, "fp8_fidelity", scope);
    compare(name, run_step(*policy, inputs, o.pairs, sm::Precision::kBf16), ref, csv);
  }
  set_policy_fp8_base(*policy, false, sm::Fp8Backward::kFp8, "fp8_fidelity");
  compare("bf16 again", run_step(*policy, inputs, o.pairs, sm::Precision::kBf16), ref, csv);
  if (o.fp32) compare("fp32", run_step(*policy, inputs, o.pairs, sm::Precision::kFp32), ref, csv);
  fmt::print("dd = d_theta - d_ref per pair ({} pairs); sign: share of pairs whose dd has the reference's sign "
             "(accuracy agreement); \"bf16 again\": the bf16 step repeated (run-to-run noise of the GPU kernels)\n",
             o.pairs);
  if (!o.csv.empty()) {
    simu::fs::atomic_write(o.csv, csv.str());
    fmt::print("per-tensor cosines: {}\n", o.csv);
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Fidelity of the FP8 frozen base on one FM-DPO step, against the bf16 step (GPU, real-size generator "
               "with random weights)"};
  Options o;
  app.add_option("--generator", o.generator, "generator config (official layout)")->capture_default_str();
  app.add_option("--cond-len", o.cond_len, "condition tokens per pair")->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--pairs", o.pairs, "pairs in the step")->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--micro", o.micro, "pairs per forward/backward")->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--lora-b-std", o.lora_b_std, "standard deviation of the random lora_B")->capture_default_str();
  app.add_option("--seed", o.seed, "seed of the adapters and the inputs")->capture_default_str();
  app.add_flag("--fp32", o.fp32, "also run the IEEE fp32 step (slow) to show bf16's own distance from fp32");
  app.add_option("--csv", o.csv, "write the per-tensor cosines here (written atomically)");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&]() -> int {
    SIMU_CHECK(common.sets.empty(), "fp8_fidelity: --set has no config to apply to (got --set {})", common.sets.front());
    if (!torch::cuda::is_available()) {
      fmt::print("fp8_fidelity: skipped: needs a CUDA device (none here)\n");
      return 0;
    }
    run(o);
    return 0;
  });
}
