// bench_step_cache: the fidelity of step-cached Stage-1 sampling (models/step_cache.h) against full
// sampling from the same noise and condition. For every condition x seed: one full sampling, then one
// per full-evaluation interval k; the shape latents are decoded by the sparse-structure decoder to
// occupancy grids (logit > 0; 64^3 for the real decoder) and compared (IoU), the pose latents decoded
// (plain decode, models/pose.h) and compared (rotation angle, translation distance, relative scale),
// plus the shape latent's relative error. A reference row gives the IoU of two full samplings of the
// same condition from DIFFERENT noise: what an unrelated sample scores.
// Weights: real-size random init by default (the released checkpoint is not on the device machines;
// random weights make noise shapes, so the figures say little about trained models), or with
// --fixtures the small official-architecture fixture models of ../shared/fixtures (also random
// weights, made by the official code). Say which when quoting the figures.
#include <ATen/CPUGeneratorImpl.h>
#include <fmt/ranges.h>
#include <torch/cuda.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>

#include "common/source_dir.h"
#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "models/generator.h"
#include "models/pose.h"
#include "models/precision.h"
#include "models/ss_decoder.h"

namespace {

namespace sm = simu::models;

// One comparison of a sampling with the full one.
struct Diff {
  double iou = 0, occupied = 0, shape_err = 0, rot_deg = 0, trans = 0, scale_rel = 0;
};

struct Summary {
  std::string what;
  int full_steps = 0;
  std::vector<Diff> diffs;
};

// Occupancy grids (logit > 0) of shape latents [B, T, 8]: bool [B, 1, R, R, R] on the CPU.
torch::Tensor occupancy(sm::SparseStructureDecoder& dec, const torch::Tensor& shape) {
  torch::NoGradGuard ng;
  return (dec->forward(sm::shape_tokens_to_grid(shape.to(torch::kFloat32))) > 0).cpu();
}

Diff compare(sm::SparseStructureDecoder& dec, const sm::Latents& got, const sm::Latents& ref) {
  // A non-finite sample would decode to an empty grid and compare as equal: refuse it instead.
  for (const auto* l : {&got, &ref})
    for (const auto& [k, v] : *l)
      SIMU_CHECK(torch::isfinite(v).all().item<bool>(), "sampled latent '{}' holds non-finite values (try --precision fp32)",
                 k);
  Diff d;
  const auto oa = occupancy(dec, got.at("shape")), ob = occupancy(dec, ref.at("shape"));
  const double inter = (oa & ob).sum().item<double>(), uni = (oa | ob).sum().item<double>();
  d.iou = uni > 0 ? inter / uni : 1.0;
  d.occupied = ob.to(torch::kFloat64).mean().item<double>();
  d.shape_err = ((got.at("shape") - ref.at("shape")).norm() / ref.at("shape").norm().clamp_min(1e-12)).item<double>();
  sm::PoseDecodeOptions po;
  po.convention = "default";
  const auto pa = sm::decode_pose(got, po), pb = sm::decode_pose(ref, po);
  // Angle of Ra^T Rb: acos((trace - 1) / 2).
  const auto rel = torch::matmul(pa.rotation.transpose(1, 2), pb.rotation);
  const double tr = rel.diagonal(0, 1, 2).sum(-1).max().item<double>();
  d.rot_deg = std::acos(std::clamp((tr - 1) / 2, -1.0, 1.0)) * 180.0 / M_PI;
  d.trans = (pa.translation - pb.translation).norm().item<double>();
  d.scale_rel = ((pa.scale - pb.scale).abs() / pb.scale.abs().clamp_min(1e-12)).max().item<double>();
  return d;
}

void print_table(const std::vector<Summary>& rows, int steps) {
  fmt::print("\n| sampling | full evaluations | occupancy IoU mean | IoU min | occupied (full) | shape latent rel err "
             "mean | rotation deg mean / max | translation mean / max | scale rel mean / max |\n"
             "|---|---|---|---|---|---|---|---|---|\n");
  for (const auto& r : rows) {
    auto mean = [&](double Diff::*f) {
      double s = 0;
      for (const auto& d : r.diffs) s += d.*f;
      return s / std::max<size_t>(r.diffs.size(), 1);
    };
    auto extreme = [&](double Diff::*f, bool lo) {
      double v = lo ? 1e30 : -1e30;
      for (const auto& d : r.diffs) v = lo ? std::min(v, d.*f) : std::max(v, d.*f);
      return v;
    };
    fmt::print("| {} | {} of {} | {:.4f} | {:.4f} | {:.3f} | {:.4f} | {:.3f} / {:.3f} | {:.4f} / {:.4f} | {:.4f} / {:.4f} |\n",
               r.what, r.full_steps, steps, mean(&Diff::iou), extreme(&Diff::iou, true), mean(&Diff::occupied),
               mean(&Diff::shape_err), mean(&Diff::rot_deg), extreme(&Diff::rot_deg, false), mean(&Diff::trans),
               extreme(&Diff::trans, false), mean(&Diff::scale_rel), extreme(&Diff::scale_rel, false));
  }
}

struct Args {
  std::string config = simu::source_dir() + "/configs/stage1_real.yaml", weights,
              decoder_config = simu::source_dir() + "/configs/ss_decoder.yaml", decoder_weights,
              device = "cuda", precision = "fp16";
  bool fixtures = false, graphs = false;
  int64_t cond_len = 2800;
  int conditions = 2, seeds = 3, steps = 25;
  std::vector<int> intervals = {2, 3, 4};
  sm::StepCacheOptions cache;
};

void run(Args& a) {
  const torch::Device dev(a.device);
  SIMU_CHECK(!dev.is_cuda() || torch::cuda::is_available(), "--device {}: no CUDA device here (use --device cpu --fixtures)",
             a.device);
  if (a.fixtures) {
    const char* env = std::getenv("SIMU_SHARED_DIR");  // as the tests find the fixtures
    const std::string fx = (env && *env ? std::string(env) : simu::source_dir() + "/../shared") + "/fixtures/";
    a.config = fx + "ss_generator_small.json", a.weights = fx + "ss_generator_small.safetensors";
    a.decoder_config = fx + "ss_decoder_small.json", a.decoder_weights = fx + "ss_decoder_small.safetensors";
    a.cond_len = std::min<int64_t>(a.cond_len, 10);
  }
  auto gen = sm::load_generator(a.config, a.weights, dev);
  auto dec = sm::load_ss_decoder(a.decoder_config, a.decoder_weights, dev);
  sm::SamplerOverrides user;
  user.steps = a.steps;
  auto o = sm::official_inference_options(gen->config(), user);
  o.precision = sm::parse_precision(a.precision, dev, "--precision");
  o.cuda_graphs = a.graphs && dev.is_cuda();
  fmt::print("generator {} ({}), decoder {} ({}), {} condition tokens, device {}, precision {}\nsampler: {}\n"
             "step caching: {} (interval k per row)\n",
             a.config, a.weights.empty() ? "RANDOM WEIGHTS" : a.weights, a.decoder_config,
             a.decoder_weights.empty() ? "RANDOM WEIGHTS" : a.decoder_weights, a.cond_len, a.device, a.precision,
             sm::describe_sampler(o, gen->config()), [&] { auto c = a.cache; c.enabled = true; return c.describe(); }());
  std::vector<Summary> rows = {{"full, different noise (reference)", a.steps, {}}};
  for (const int k : a.intervals) rows.push_back({fmt::format("step cache k={}", k), 0, {}});
  const auto Cc = gen->config().backbone.cond_channels;
  for (int c = 0; c < a.conditions; ++c) {
    auto crng = at::make_generator<at::CPUGeneratorImpl>(1000 + c);
    const auto cond = torch::randn({1, a.cond_len, Cc}, crng).to(dev);
    std::vector<sm::Latents> fulls;
    for (int s = 0; s <= a.seeds; ++s) {  // one seed more for the different-noise reference
      auto rng = at::make_generator<at::CPUGeneratorImpl>(static_cast<uint64_t>(s));
      auto x0 = gen->noise(1, rng, dev);
      o.step_cache.enabled = false;
      fulls.push_back(gen->sample(cond, x0, o));
      if (s > 0) rows[0].diffs.push_back(compare(dec, fulls[s], fulls[s - 1]));
      if (s == a.seeds) break;  // the extra seed serves the reference only
      for (size_t r = 1; r < rows.size(); ++r) {
        o.step_cache = a.cache;
        o.step_cache.enabled = true;
        o.step_cache.interval = a.intervals[r - 1];
        rows[r].diffs.push_back(compare(dec, gen->sample(cond, x0, o), fulls[s]));
        rows[r].full_steps = gen->step_cache_stats().full_steps();
      }
    }
    simu::log::info("condition {} of {} done", c + 1, a.conditions);
  }
  print_table(rows, a.steps);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Fidelity of step-cached Stage-1 sampling against full sampling (same noise and condition): decoded "
               "occupancy IoU, pose differences, latent error"};
  Args a;
  app.add_option("--config", a.config, "generator config")->capture_default_str();
  app.add_option("--weights", a.weights, "generator safetensors (default: random init)");
  app.add_option("--decoder-config", a.decoder_config, "sparse-structure decoder config")->capture_default_str();
  app.add_option("--decoder-weights", a.decoder_weights, "decoder safetensors (default: random init)");
  app.add_flag("--fixtures", a.fixtures,
               "use the small fixture generator and decoder of ../shared/fixtures (official code, random weights; "
               "condition length at most 10) instead of --config/--weights/--decoder-*");
  app.add_option("--device", a.device, "cuda | cuda:N | cpu")->capture_default_str();
  app.add_option("--precision", a.precision, "fp16 (released) | bf16 | fp32 (CPU: fp32)")->capture_default_str();
  app.add_flag("--cuda-graphs", a.graphs, "sample through persistent CUDA graphs");
  app.add_option("--cond-len", a.cond_len, "condition tokens (random, one draw per condition)")->capture_default_str();
  app.add_option("--conditions", a.conditions, "random conditions")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--seeds", a.seeds, "noise seeds per condition")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--steps", a.steps, "sampling steps")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--intervals", a.intervals, "full-evaluation intervals k to compare")->capture_default_str();
  app.add_option("--order", a.cache.order, "shape extrapolation order 0 | 1 | 2")->capture_default_str();
  app.add_option("--momentum", a.cache.pose_momentum, "pose momentum in [0, 1]")->capture_default_str();
  app.add_option("--warmup", a.cache.warmup, "leading full steps")->capture_default_str();
  app.add_option("--tail", a.cache.tail, "trailing full steps")->capture_default_str();
  app.add_option("--tolerance", a.cache.tolerance, "error-adaptive refresh above this relative error (0 = off)")
      ->capture_default_str();
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    for (const int k : a.intervals) SIMU_CHECK(k >= 1, "--intervals: every k must be >= 1, got {}", k);
    a.cache.validate("step caching option ");
    torch::NoGradGuard ng;
    run(a);
    return 0;
  });
}
