// Stage-1 generator (generator.h): configs, the official inference sampler values, classifier-free
// guidance and the sampling loop. The CUDA graphs it samples through: sampling_graphs.cpp.
#include "common/cancel.h"
#include "models/generator.h"

#include <fmt/ranges.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "common/config.h"
#include "common/error.h"
#include "models/official_yaml.h"
#include "common/log.h"
#include "data/safetensors.h"
#include "models/linear.h"
#include "models/weights.h"

#include <ATen/autocast_mode.h>

namespace simu::models {

namespace {

// interval: [lo, hi] or null (CFG never active: {inf, -inf}).
std::pair<double, double> read_interval(const YAML::Node& n, const std::string& file) {
  if (!n || n.IsNull()) return {std::numeric_limits<double>::infinity(), -std::numeric_limits<double>::infinity()};
  SIMU_CHECK(n.IsSequence() && n.size() == 2, "{}: cfg interval must be [lo, hi] or null", file);
  return {n[0].as<double>(), n[1].as<double>()};
}

Latents combine(const Latents& a, const Latents& b, double wa, double wb) {
  Latents out;
  for (const auto& [k, v] : a) out[k] = v * wa + b.at(k) * wb;
  return out;
}

// x + v * dt per latent (official linear_approximation_step).
Latents step(const Latents& x, const Latents& v, double dt) {
  Latents out;
  for (const auto& [k, xi] : x) out[k] = xi + v.at(k) * dt;
  return out;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Config

GeneratorConfig GeneratorConfig::from_official(const YAML::Node& root, const std::string& file) {
  const YAML::Node g = root["module"]["generator"]["backbone"];
  SIMU_CHECK(g && g.IsMap(), "{}: module.generator.backbone missing (official ss_generator layout expected)", file);
  GeneratorConfig c;
  c.kind = short_target(g);
  SIMU_CHECK(c.kind == "ShortCut" || c.kind == "FlowMatching",
             "{}: module.generator.backbone._target_ '{}' is not ShortCut or FlowMatching", file, c.kind);
  c.time_scale = get_or<double>(g, "time_scale", c.time_scale, file);
  c.inference_steps = get_or<int>(g, "inference_steps", 100, file);
  c.rescale_t = get_or<double>(g, "rescale_t", c.rescale_t, file);
  c.reversed_timestamp = get_or<bool>(g, "reversed_timestamp", false, file);
  c.sigma_min = get_or<double>(g, "sigma_min", 0.0, file);
  c.no_shortcut = get_or<bool>(g, "no_shortcut", false, file);
  c.solver = get_or<std::string>(g, "solver_method", "euler", file);
  const YAML::Node r = g["reverse_fn"];
  SIMU_CHECK(r && r.IsMap(), "{}: module.generator.backbone.reverse_fn missing", file);
  const std::string rt = short_target(r);
  SIMU_CHECK(rt.rfind("ClassifierFreeGuidance", 0) == 0,
             "{}: reverse_fn._target_ '{}' is not a ClassifierFreeGuidance", file, rt);
  c.cfg_strength = get_or<double>(r, "strength", 3.0, file);
  c.cfg_interval = read_interval(r["interval"], file);
  c.unconditional_handling = get_or<std::string>(r, "unconditional_handling", "zeros", file);
  c.p_unconditional = get_or<double>(r, "p_unconditional", 0.1, file);
  c.backbone = FlowModelConfig::from_official(r["backbone"], file);
  SIMU_CHECK(c.unconditional_handling == "add_flag" || c.unconditional_handling == "zeros",
             "{}: unconditional_handling '{}' is not supported (add_flag or zeros)", file, c.unconditional_handling);
  SIMU_CHECK(c.solver == "euler" || c.solver == "midpoint" || c.solver == "rk4",
             "{}: solver_method '{}' is not supported (euler, midpoint, rk4)", file, c.solver);
  SIMU_CHECK(!c.is_shortcut() || c.backbone.is_shortcut_model,
             "{}: a ShortCut generator needs a backbone with is_shortcut_model: true (it always passes d)", file);
  return c;
}

GeneratorConfig GeneratorConfig::from(config::Reader& root) {
  GeneratorConfig c;
  auto g = root.child("generator");
  g.field("kind", c.kind);
  g.field("time_scale", c.time_scale);
  g.field("inference_steps", c.inference_steps);
  g.field("rescale_t", c.rescale_t);
  g.field("reversed_timestamp", c.reversed_timestamp);
  g.field("sigma_min", c.sigma_min);
  g.field("no_shortcut", c.no_shortcut);
  g.field("solver", c.solver);
  g.field("cfg_strength", c.cfg_strength);
  if (g.has("cfg_interval")) c.cfg_interval = read_interval(g.raw("cfg_interval"), root.file());
  g.field("unconditional_handling", c.unconditional_handling);
  g.field("p_unconditional", c.p_unconditional);
  auto f = root.child("flow_model");
  c.backbone = FlowModelConfig::from(f);
  root.finish();
  SIMU_CHECK(c.kind == "ShortCut" || c.kind == "FlowMatching", "{}: generator.kind must be ShortCut or FlowMatching, got '{}'",
             root.file(), c.kind);
  SIMU_CHECK(c.solver == "euler" || c.solver == "midpoint" || c.solver == "rk4",
             "{}: generator.solver must be euler, midpoint or rk4, got '{}'", root.file(), c.solver);
  SIMU_CHECK(c.unconditional_handling == "add_flag" || c.unconditional_handling == "zeros",
             "{}: generator.unconditional_handling must be add_flag or zeros, got '{}'", root.file(), c.unconditional_handling);
  SIMU_CHECK(!c.is_shortcut() || c.backbone.is_shortcut_model,
             "{}: a ShortCut generator needs flow_model.is_shortcut_model: true", root.file());
  return c;
}

GeneratorConfig GeneratorConfig::from_official_file(const std::string& path, const std::vector<std::string>& overrides) {
  const YAML::Node root = config::load_file(path, overrides);
  if (root["module"]) return from_official(root, path);
  config::Reader r(root, path);
  return from(r);
}

SampleOptions SampleOptions::from(const GeneratorConfig& c) {
  SampleOptions o;
  o.steps = c.inference_steps;
  o.cfg_strength = c.cfg_strength;
  o.cfg_interval = c.cfg_interval;
  o.rescale_t = c.rescale_t;
  o.reversed_timestamp = c.reversed_timestamp;
  o.shortcut = c.is_shortcut() && !c.no_shortcut;
  o.solver = c.solver;
  return o;
}

SampleOptions official_inference_options(const GeneratorConfig& c, const SamplerOverrides& user) {
  SampleOptions o = SampleOptions::from(c);  // time grid direction and solver stay the config's
  o.steps = user.steps.value_or(25);
  o.rescale_t = user.rescale_t.value_or(3.0);
  o.cfg_interval = user.cfg_interval.value_or(std::pair<double, double>{0.0, 500.0});
  o.unconditional_handling = "add_flag";
  o.precision = Precision::kFp16;  // on CUDA (the released pipeline's dtype); CPU runs fp32
  o.shortcut = c.is_shortcut() && user.shortcut.value_or(false);
  // Distillation (shortcut) mode samples without CFG unless the user asks for it.
  o.cfg_strength = user.cfg_strength.value_or(o.shortcut ? 0.0 : 7.0);
  if (user.solver) o.solver = *user.solver;
  SIMU_CHECK(o.steps > 0, "sampler: steps must be positive, got {}", o.steps);
  SIMU_CHECK(!user.shortcut.value_or(false) || c.is_shortcut(),
             "sampler: shortcut mode needs a ShortCut generator (this one is {})", c.kind);
  return o;
}

std::string describe_sampler(const SampleOptions& o, const GeneratorConfig& c, const SamplerOverrides& user) {
  auto src = [](bool given, const char* otherwise) { return given ? std::string("user") : std::string(otherwise); };
  std::string d = c.is_shortcut() ? (o.shortcut ? fmt::format("d = 1/{} (shortcut)", o.steps) : "d = 0 (no_shortcut)")
                                  : "no d (FlowMatching)";
  return fmt::format(
      "steps {} ({}), rescale_t {} ({}), cfg {} on t*{} in [{}, {}] ({}{}), unconditional {}, {} ({}), solver {} ({}), "
      "reversed_timestamp {} (config), precision {} on CUDA (CPU: fp32)",
      o.steps, src(user.steps.has_value(), "official inference"), o.rescale_t,
      src(user.rescale_t.has_value(), "official inference"), o.cfg_strength, c.time_scale, o.cfg_interval.first,
      o.cfg_interval.second, src(user.cfg_strength.has_value(), "official inference"),
      user.cfg_interval ? ", interval user" : "",
      o.unconditional_handling.empty() ? c.unconditional_handling : o.unconditional_handling, d,
      src(user.shortcut.has_value(), "official inference"), o.solver, src(user.solver.has_value(), "config"),
      o.reversed_timestamp,
      precision_name(o.precision.value_or(o.bf16_autocast ? Precision::kBf16 : Precision::kFp32)));
}

// ---------------------------------------------------------------------------------------------
// CFG

ClassifierFreeGuidanceImpl::ClassifierFreeGuidanceImpl(const GeneratorConfig& c)
    : unconditional_handling(c.unconditional_handling) {
  backbone = register_module("backbone", SparseStructureFlowTdfyWrapper(c.backbone));
}

PreparedCondition ClassifierFreeGuidanceImpl::prepare(const torch::Tensor& cond, bool cache) {
  PreparedCondition pc;
  pc.cond = cond;
  torch::Tensor cond_u = cond;
  if (unconditional_handling == "zeros" || backbone->config().force_zeros_cond) {
    cond_u = cond * 0;
    // All zero unless cond holds inf/NaN (0 * inf = NaN): then the shortcut would hide them.
    pc.zero_unconditional = cache && (!cond.is_floating_point() || torch::isfinite(cond).all().item<bool>());
  }
  pc.pair = torch::cat({cond, cond_u}, 0);
  pc.cache = cache;
  return pc;
}

bool guidance_active(double t_scaled, double strength, std::pair<double, double> interval) {
  // The official compares the float32 time tensor with the interval bounds.
  const double tf = static_cast<float>(t_scaled);
  return strength > 0.0 && interval.first <= tf && tf <= interval.second;
}

Latents ClassifierFreeGuidanceImpl::forward(const Latents& x, double t_scaled, const torch::Tensor& cond,
                                            c10::optional<double> d_scaled, double strength,
                                            std::pair<double, double> interval) {
  auto pc = prepare(cond, false);
  return forward(x, t_scaled, pc, d_scaled, strength, interval);
}

Latents ClassifierFreeGuidanceImpl::forward(const Latents& x, double t_scaled, PreparedCondition& pc,
                                            c10::optional<double> d_scaled, double strength,
                                            std::pair<double, double> interval) {
  const auto& cond = pc.cond;
  const int64_t B = cond.size(0);
  const auto opts = torch::TensorOptions().dtype(torch::kFloat32).device(cond.device());
  const bool guided = guidance_active(t_scaled, strength, interval);
  // t (and d) as one value for the whole batch ([1], like the official ShortCut): the modulation is
  // then computed once and broadcast, which lets the blocks fuse it into the LayerNorms.
  // Backbone forward: through a persistent CUDA graph when enabled, else eager (with the condition's
  // keys/values computed once per call when pc.cache).
  auto run = [&](std::shared_ptr<SamplingGraph>& graph, const Latents& xs, const torch::Tensor& c,
                 c10::optional<ConditionCache>& kv, const torch::Tensor& t, const c10::optional<torch::Tensor>& d,
                 int64_t zero_from) -> Latents {
    if (pc.graphs && pc.cache) {
      try {
        if (!graph) graph = attach_graph(c, xs, t, d, zero_from);
        auto y = graph->graph->run(xs, t, d);
        // The 16-bit weight copies the capture read: kept alive with the graph, refreshed at later calls.
        if (!graph->weights_known) graph->remember_weights(backbone);
        return y;
      } catch (const std::exception& e) {
        log::warn("sampling: CUDA graph capture failed, continuing with eager launches: {}", e.what());
        pc.graphs = false;
        auto& gs = graph_cache.graphs;
        gs.erase(std::remove(gs.begin(), gs.end(), graph), gs.end());
        graph.reset();
      }
    }
    if (pc.cache && !kv) kv = backbone->condition_cache(c, zero_from);
    return backbone->forward(xs, t, c, d, kv ? &*kv : nullptr);
  };
  if (!guided) {
    c10::optional<torch::Tensor> d;
    if (d_scaled) d = torch::full({1}, *d_scaled, opts);
    return run(pc.single_graph, x, cond, pc.single_kv, torch::full({1}, t_scaled, opts), d, -1);
  }
  // One batched forward: first half conditional, second half unconditional.
  Latents x2;
  for (const auto& [k, v] : x) x2[k] = torch::cat({v, v}, 0);
  c10::optional<torch::Tensor> d2;
  if (d_scaled) {
    if (unconditional_handling == "zeros")  // zero_out also zeroes d in the unconditional half
      d2 = torch::cat({torch::full({B}, *d_scaled, opts), torch::zeros({B}, opts)});
    else
      d2 = torch::full({1}, *d_scaled, opts);
  }
  auto y = run(pc.pair_graph, x2, pc.pair, pc.pair_kv, torch::full({1}, t_scaled, opts), d2, pc.zero_unconditional ? B : -1);
  Latents out;
  for (const auto& [k, v] : y) {
    auto yc = v.narrow(0, 0, B), yu = v.narrow(0, B, B);
    out[k] = (1 + strength) * yc - strength * yu;  // y = (1+s) y_cond - s y_uncond
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// Generator

GeneratorImpl::GeneratorImpl(GeneratorConfig c) : config_(std::move(c)) {
  reverse_fn = register_module("reverse_fn", ClassifierFreeGuidance(config_));
}

std::vector<double> GeneratorImpl::time_grid(int steps, double rescale_t, bool reversed) const {
  SIMU_CHECK(steps > 0, "sampling: steps must be positive, got {}", steps);
  std::vector<double> t(steps + 1);
  if (config_.is_shortcut()) {
    // numpy float64 (official ShortCut._prepare_t_and_d)
    for (int i = 0; i <= steps; ++i) {
      double s = static_cast<double>(i) / steps;
      if (rescale_t != 0) s = s / (1 + (rescale_t - 1) * (1 - s));
      t[i] = reversed ? 1 - s : s;
    }
  } else {
    // torch float32 (official FlowMatching._prepare_t)
    auto s = torch::linspace(0, 1, steps + 1, torch::kFloat32);
    if (rescale_t != 0) s = s / (1 + (rescale_t - 1) * (1 - s));
    if (reversed) s = 1 - s;
    for (int i = 0; i <= steps; ++i) t[i] = s[i].item<float>();
  }
  return t;
}

Latents GeneratorImpl::sample(const torch::Tensor& cond, const Latents& x0, const SampleOptions& o) {
  torch::NoGradGuard no_grad;
  const auto& c = config_;
  SIMU_CHECK(o.solver == "euler" || o.solver == "midpoint" || o.solver == "rk4",
             "sampling: solver must be euler, midpoint or rk4, got '{}'", o.solver);
  SIMU_CHECK(!o.shortcut || c.is_shortcut(), "sampling: shortcut mode needs a ShortCut generator (this one is {})", c.kind);
  const auto grid = time_grid(o.steps, o.rescale_t, o.reversed_timestamp);
  // Time arithmetic in the official precision: float64 for ShortCut, float32 for FlowMatching.
  const bool f32 = !c.is_shortcut();
  auto tp = [&](double v) { return f32 ? static_cast<double>(static_cast<float>(v)) : v; };
  c10::optional<double> d;
  if (c.is_shortcut()) d = (o.shortcut ? 1.0 / o.steps : 0.0) * c.time_scale;
  const Precision precision = o.precision.value_or(o.bf16_autocast ? Precision::kBf16 : Precision::kFp32);
  Autocast autocast(precision, cond.is_cuda());
  // On CUDA in 16 bits: the backbone's Linear weights in that dtype, kept with the layers between calls
  // (linear.h compute copies; sampling wants no weight gradient), not cast again at every call.
  if (cond.is_cuda() && precision != Precision::kFp32)
    set_compute_copies(*reverse_fn->backbone, precision_dtype(precision), /*frozen_only=*/false);

  Latents x;
  for (const auto& [k, v] : x0) x[k] = v.to(torch::kFloat32);
  // The unconditional handling of these options (official inference forces add_flag), for this call.
  const std::string saved_handling = reverse_fn->unconditional_handling;
  if (!o.unconditional_handling.empty()) {
    SIMU_CHECK(o.unconditional_handling == "add_flag" || o.unconditional_handling == "zeros",
               "sampling: unconditional_handling must be add_flag or zeros, got '{}'", o.unconditional_handling);
    reverse_fn->unconditional_handling = o.unconditional_handling;
  }
  auto pc = reverse_fn->prepare(cond, o.cache_condition);
  reverse_fn->unconditional_handling = saved_handling;
  pc.graphs = o.cuda_graphs && o.cache_condition && cond.is_cuda();
  // Velocity at time t (in [0, 1]).
  auto velocity = [&](const Latents& xt, double t) {
    return reverse_fn->forward(xt, tp(t * c.time_scale), pc, d, o.cfg_strength, o.cfg_interval);
  };
  auto cache = make_step_cache(o);
  for (int i = 0; i < o.steps; ++i) {
    simu::check_cancel();  // an embedding program's interrupt (common/cancel.h): between steps only
    const double t0 = grid[i], dt = tp(grid[i + 1] - grid[i]);
    if (cache) {
      // Step caching: a full evaluation (recorded) or the cache's prediction.
      Latents v;
      if (cache->need_full(i, guidance_active(tp(t0 * c.time_scale), o.cfg_strength, o.cfg_interval))) {
        v = velocity(x, t0);
        cache->record(i, t0, v);
      } else {
        v = cache->predict(t0);
      }
      x = step(x, v, dt);
    } else if (o.solver == "euler") {
      x = step(x, velocity(x, t0), dt);
    } else if (o.solver == "midpoint") {
      const double half = tp(0.5 * dt);
      auto x_mid = step(x, velocity(x, t0), half);
      x = step(x, velocity(x_mid, tp(t0 + half)), dt);
    } else {  // rk4
      const double half = tp(dt * 0.5);
      auto k1 = velocity(x, t0);
      auto k2 = velocity(step(x, k1, half), tp(t0 + half));
      auto k3 = velocity(step(x, k2, half), tp(t0 + half));
      auto k4 = velocity(step(x, k3, dt), tp(t0 + dt));
      Latents v;
      for (const auto& [k, a] : k1) v[k] = (a + 2 * k2.at(k) + 2 * k3.at(k) + k4.at(k)) / 6;
      x = step(x, v, dt);
    }
    if (o.on_step) o.on_step(i + 1, o.steps);
  }
  step_cache_stats_ = cache ? cache->stats() : StepCacheStats{};
  for (auto& [k, v] : x) v = v.to(torch::kFloat32);
  return x;
}

std::unique_ptr<StepCache> GeneratorImpl::make_step_cache(const SampleOptions& o) const {
  if (!o.step_cache.enabled) return nullptr;
  o.step_cache.validate();
  SIMU_CHECK(o.solver == "euler", "sampling: step_cache needs the euler solver, got solver '{}'", o.solver);
  // The protected streams' latents (shape) are extrapolated; the others (pose) are momentum-anchored.
  const auto& b = config_.backbone;
  std::set<std::string> extrapolated;
  for (const auto& s : b.latents)
    if (b.is_protected(b.stream_of(s.name))) extrapolated.insert(s.name);
  return std::make_unique<StepCache>(o.step_cache, o.steps, std::move(extrapolated));
}

Latents GeneratorImpl::noise(int64_t batch, torch::Generator& gen, torch::Device device) const {
  Latents out;
  for (const auto& s : config_.backbone.latents) {
    auto opts = torch::TensorOptions().dtype(torch::kFloat32).device(gen.device());
    out[s.name] = torch::randn({batch, s.tokens(), s.in_channels}, gen, opts).to(device);
  }
  return out;
}

Generator load_generator(const std::string& config_path, const std::string& weights_path, torch::Device device,
                         const std::vector<std::string>& overrides) {
  auto cfg = GeneratorConfig::from_official_file(config_path, overrides);
  Generator g(cfg);
  if (!weights_path.empty()) {
    LoadOptions lo;
    // A condition embedder passed into the wrapper (official `condition_embedder` kwarg) is another
    // component (loaded by the condition-embedder code), not part of this flow model.
    lo.ignore_prefixes = {"reverse_fn.backbone.condition_embedder."};
    // The official checkpoint prefixes generator weights with "_base_models.generator."; other
    // sub-models (condition embedder) live under other prefixes and are skipped by the prefix filter.
    const std::string ext = ".safetensors";
    if (weights_path.size() >= ext.size() && weights_path.compare(weights_path.size() - ext.size(), ext.size(), ext) == 0) {
      const auto f = data::SafeTensorsFile::open(weights_path);
      for (const auto& k : f.keys())
        if (k.rfind("_base_models.generator.", 0) == 0) {
          lo.strip_prefix = "_base_models.generator.";
          break;
        }
    }
    const auto n = load_safetensors_into(*g, weights_path, lo);
    log::info("loaded {} generator tensors from {}", n, weights_path);
  }
  g->to(device);
  g->eval();
  return g;
}

torch::Tensor sample_training_t(int64_t batch, torch::Generator& gen) {
  auto opts = torch::TensorOptions().dtype(torch::kFloat32).device(gen.device());
  return torch::sigmoid(torch::randn({batch}, gen, opts) * 1.0 + 0.0);
}

}  // namespace simu::models
