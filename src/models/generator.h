// Stage-1 generator: flow-matching / shortcut sampling with classifier-free guidance around the MOT
// flow model. Port of sam3d_objects/model/backbone/generator/{base.py, flow_matching/model.py,
// flow_matching/solver.py, shortcut/model.py, classifier_free_guidance.py}.
//
// Module tree (so weights load by the official names after stripping "_base_models.generator."):
//   Generator
//     reverse_fn  (ClassifierFreeGuidance)
//       backbone  (SparseStructureFlowTdfyWrapper)
//
// Sampling (official generate_iter): x starts at the noise x0 (t = 0) and integrates the predicted
// velocity to t = 1 over the grid t_i = s_i / (1 + (rescale_t - 1) (1 - s_i)), s = linspace(0, 1,
// steps + 1) (then 1 - t when reversed_timestamp). The backbone sees t * time_scale. ShortCut passes
// d = 0 (no_shortcut) or d = 1/steps, times time_scale; FlowMatching passes no d.
// CFG: when strength > 0 and interval[0] <= t*time_scale <= interval[1], the conditional and the
// unconditional branch run as ONE batched forward ([x; x], [cond; cond_uncond]) and
// y = (1 + s) y_cond - s y_uncond; otherwise one conditional forward. Unconditional branch:
// "add_flag" -> cond * 0 when the backbone has force_zeros_cond (else cond unchanged), "zeros" ->
// cond and d set to zero (official zero_out).
#pragma once

#include <torch/torch.h>

#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>

#include "models/flow_model.h"
#include "models/precision.h"
#include "models/step_cache.h"

namespace simu::models {

struct GeneratorConfig {
  std::string kind = "ShortCut";  // "ShortCut" or "FlowMatching"
  double time_scale = 1000.0;
  int inference_steps = 25;
  double rescale_t = 1.0;
  bool reversed_timestamp = false;
  double sigma_min = 0.0;  // training only (x_t = (1 - (1 - sigma_min) t) x0 + t x1)
  bool no_shortcut = false;  // ShortCut: d = 0 at inference instead of 1/steps
  std::string solver = "euler";  // euler | midpoint | rk4
  // ClassifierFreeGuidance
  double cfg_strength = 0.0;
  std::pair<double, double> cfg_interval{0.0, 1000.0};  // time_scale units; null in YAML -> {inf, -inf} (never)
  std::string unconditional_handling = "add_flag";      // add_flag | zeros
  double p_unconditional = 0.1;                          // training: condition dropout probability
  FlowModelConfig backbone;

  bool is_shortcut() const { return kind == "ShortCut"; }
  // Official layout (module.generator.backbone ... with _target_ names), as YAML or JSON.
  static GeneratorConfig from_official(const YAML::Node& root, const std::string& file = "");
  // Either layout, detected from the file: official (`module:` at the top) or the project's own
  // (`generator:` + `flow_model:` sections, see configs/stage1_small.yaml). Overrides "a.b=v" apply.
  static GeneratorConfig from_official_file(const std::string& json_or_yaml,
                                            const std::vector<std::string>& overrides = {});
  // Project layout from a reader at the file root (strict keys).
  static GeneratorConfig from(config::Reader& r);
};

struct SampleOptions {
  int steps = 25;
  double cfg_strength = 0.0;
  std::pair<double, double> cfg_interval{0.0, 1000.0};
  double rescale_t = 1.0;
  bool reversed_timestamp = false;
  // ShortCut generators: true -> d = 1/steps (shortcut mode), false -> d = 0. Ignored (no d) for
  // FlowMatching generators.
  bool shortcut = false;
  std::string solver = "euler";  // euler | midpoint | rk4
  // On CUDA: the autocast precision of the backbone. When set it decides (fp16 = the released
  // pipeline, bf16, fp32 = none); unset: bf16 autocast when bf16_autocast (the training recipe).
  // Ignored on CPU (fp32).
  std::optional<Precision> precision;
  bool bf16_autocast = true;
  // Compute the condition's cross-attention keys/values once and reuse them at every step (same
  // result up to rounding order: none, the same ops run once instead of per step).
  bool cache_condition = true;
  // On CUDA, with cache_condition: replay the backbone forward from a CUDA graph at every step. The
  // same kernels run on the same inputs, without the per-kernel launch gaps. Graphs persist across
  // sample() calls (ClassifierFreeGuidanceImpl::graph_cache): one per shape (batch, condition length,
  // latents, autocast dtype, device), captured on first use after an eager warm-up forward and
  // replayed from then on; each call copies its condition, the condition's keys/values and the
  // current weights' 16-bit copies into the graph's buffers. Falls back to eager launches (with a
  // warning) where capture fails.
  bool cuda_graphs = false;
  // Unconditional branch for CFG: "" keeps the generator config's, else "add_flag" or "zeros" (the
  // official inference forces "add_flag").
  std::string unconditional_handling;
  // Called after each solver step with (step index from 1, steps).
  std::function<void(int, int)> on_step;
  // Opt-in step caching (models/step_cache.h; euler only): full flow-model evaluations on some steps,
  // the shape velocity extrapolated in t and the pose velocity momentum-anchored on the others. Faster
  // by about the fraction of skipped full evaluations, at a measured cost in fidelity
  // (docs/step_cache.md). Default off: the sampler is then exactly the full one.
  StepCacheOptions step_cache;

  // Defaults from the config (inference_steps, CFG strength/interval, rescale_t, !no_shortcut, solver):
  // the TRAINING-time values of a released ss_generator.yaml (2 steps, rescale_t 1, CFG 2, shortcut).
  // Inference entry points use official_inference_options() instead.
  static SampleOptions from(const GeneratorConfig& c);
};

// Sampler values a user gave explicitly (command line or config); unset ones take the official
// inference values (official_inference_options).
struct SamplerOverrides {
  std::optional<int> steps;
  std::optional<double> rescale_t;
  std::optional<double> cfg_strength;
  std::optional<std::pair<double, double>> cfg_interval;  // time_scale units
  std::optional<bool> shortcut;                           // true: d = 1/steps and (unless cfg given) no CFG
  std::optional<std::string> solver;
};

// The official inference values (sam3d_objects/pipeline/inference_pipeline.py: InferencePipeline
// defaults ss_inference_steps 25, ss_rescale_t 3, ss_cfg_strength 7, ss_cfg_interval [0, 500];
// override_ss_generator_cfg_config forces unconditional_handling "add_flag"; sample_sparse_structure
// sets no_shortcut = true, i.e. d = 0 for a ShortCut generator; precision fp16 on CUDA, the released
// pipeline.yaml dtype). They replace the training-time values
// a released ss_generator.yaml carries (inference_steps 2, rescale_t 1, strength 2.0, no no_shortcut).
// Kept from the config: time_scale, reversed_timestamp, solver (solver_method; euler when absent).
// `user` overrides single values; user.shortcut = true is the official use_distillation path
// (d = 1/steps, CFG strength 0 unless user.cfg_strength is set).
SampleOptions official_inference_options(const GeneratorConfig& c, const SamplerOverrides& user = {});

// One line naming every sampler value and where it came from, e.g. "steps 25 (official inference),
// rescale_t 3 (official inference), cfg 7 on t*1000 in [0, 500] (official inference), unconditional
// add_flag, d = 0 (no_shortcut), solver euler (config)"; values the user set are marked "(user)".
std::string describe_sampler(const SampleOptions& o, const GeneratorConfig& c, const SamplerOverrides& user = {});

// Whether CFG runs at time t_scaled (time_scale units): strength > 0 and t inside the interval, compared
// in float32 as the official compares its float32 time tensor.
bool guidance_active(double t_scaled, double strength, std::pair<double, double> interval);

// A condition prepared for repeated guided evaluations: the conditional/unconditional pair built once,
// and (when `cache`) the cross-attention keys/values of both computed on first use and reused.
// A CUDA-graph capture of one backbone forward for a fixed condition (and its cache), fixed input
// shapes and the autocast state at capture. run() copies x, t, d into the graph's own input buffers
// and replays it, returning copies of the graph's outputs. Captured on first run(): one eager forward
// (plans, workspaces, autocast weight copies; its result is that run's answer), then the capture (see
// set_overlapped_capture). Without CUDA support compiled in, run() is the eager forward.
class GraphedForward {
 public:
  GraphedForward(SparseStructureFlowTdfyWrapper backbone, torch::Tensor cond, const ConditionCache* cache);
  ~GraphedForward();
  // x: latents [B, T, ch] on the condition's device; t: [1] or [B]; d: like t, or nullopt.
  Latents run(const Latents& x, const torch::Tensor& t, const c10::optional<torch::Tensor>& d);
  // Graph replays and captures so far in this process (tests check that the graph path really ran
  // and that graphs are reused).
  static int64_t replay_count();
  static int64_t capture_count();
  // Capture scheme (process-wide). Overlapped (the default): the first run() evaluates eagerly on a
  // side stream and returns that result, and records the graph right after it without waiting for the
  // device (the host records while the device computes), so a capture costs about one eager
  // evaluation. Off: the earlier host-synchronous scheme (device synchronised, a discarded warm-up
  // forward, the capture, then a first replay). Both give the same numbers (tests/models/flow_gpu.cpp).
  static void set_overlapped_capture(bool on);
  static bool overlapped_capture();

 private:
  struct State;
  std::unique_ptr<State> s_;
};

// A persistent CUDA graph of one backbone forward for sampling: its own condition buffer and
// keys/values (the graph's inputs besides x, t, d), and the 16-bit weight copies the graph reads (under
// autocast the forward reads the Linear layers' compute copies, and the autocast cache's copies of the
// other weights, which live only as long as one autocast region; both are kept with the graph and
// refreshed from the parameters at every later call). `fingerprint` covers what changes
// the captured kernels (parameter storage, adapters on/off, kernel switches): a mismatch recaptures.
struct SamplingGraph {
  std::string key;
  uint64_t fingerprint = 0;
  int64_t last_use = 0;
  torch::Tensor cond;  // [B, L, Cc] static condition buffer
  ConditionCache kv;   // keys/values of `cond`, static
  std::unique_ptr<GraphedForward> graph;
  std::vector<std::pair<torch::Tensor, torch::Tensor>> weights;  // (parameter, the 16-bit copy the graph reads)
  // The Linear compute copies the graph reads instead (linear.h; sample() turns them on), with the
  // weight/bias they copy: refreshed in place at every later call where the weights changed.
  struct LinearCopy {
    torch::Tensor weight, bias;
    std::shared_ptr<ComputeCopy> copy;
  };
  std::vector<LinearCopy> copies;
  bool weights_known = false;
  // After the first capture (autocast still on): records the copies above; Linear weights read through
  // their compute copies get no autocast copy.
  void remember_weights(SparseStructureFlowTdfyWrapper& backbone);
  // At a later call: the current weights into the copies (autocast copies always, compute copies when
  // stale).
  void refresh_weights();
};

// The persistent sampling graphs of one generator, least recently used dropped beyond `max_graphs`.
struct SamplingGraphCache {
  std::vector<std::shared_ptr<SamplingGraph>> graphs;
  int64_t tick = 0;
  size_t max_graphs = 4;
};

struct PreparedCondition {
  torch::Tensor cond;  // [B, L, Cc]
  torch::Tensor pair;  // [2B, L, Cc]: cond, then the unconditional condition
  bool cache = false;
  // The unconditional half of `pair` is cond * 0 (force_zeros_cond or "zeros"): its cross attention
  // is the value bias (ConditionCache::zero_from), no attention over the condition tokens.
  bool zero_unconditional = false;
  c10::optional<ConditionCache> single_kv, pair_kv;
  // Persistent CUDA graphs of the unguided (B) and guided (2B) forwards when enabled, attached (and
  // refreshed with this condition) on first use in this call; `graphs` turns off after a failed capture.
  bool graphs = false;
  std::shared_ptr<SamplingGraph> single_graph, pair_graph;
};

// ClassifierFreeGuidance: holds the backbone; `forward` evaluates the guided velocity at one time.
class ClassifierFreeGuidanceImpl : public torch::nn::Module {
 public:
  ClassifierFreeGuidanceImpl(const GeneratorConfig& c);
  // x: latents [B, T, ch]; t_scaled: time in time_scale units; d_scaled: shortcut step in time_scale
  // units or nullopt (no d); strength/interval: CFG settings. Returns the velocity per latent.
  Latents forward(const Latents& x, double t_scaled, const torch::Tensor& cond, c10::optional<double> d_scaled,
                  double strength, std::pair<double, double> interval);
  // Same with a prepared condition (reuses its condition keys/values when pc.cache).
  Latents forward(const Latents& x, double t_scaled, PreparedCondition& pc, c10::optional<double> d_scaled,
                  double strength, std::pair<double, double> interval);
  // The unconditional condition of the official handling ("add_flag" + force_zeros_cond / "zeros": cond * 0).
  PreparedCondition prepare(const torch::Tensor& cond, bool cache);
  // Drops the persistent sampling graphs (and their memory).
  void clear_graphs() { graph_cache.graphs.clear(); }
  SparseStructureFlowTdfyWrapper backbone{nullptr};
  std::string unconditional_handling;
  SamplingGraphCache graph_cache;

 private:
  // The persistent graph for a forward of backbone on (c, xs, t, d), found or created, its inputs
  // refreshed for this call (condition, keys/values, weight copies).
  std::shared_ptr<SamplingGraph> attach_graph(const torch::Tensor& c, const Latents& xs, const torch::Tensor& t,
                                              const c10::optional<torch::Tensor>& d, int64_t zero_from);
};
TORCH_MODULE(ClassifierFreeGuidance);

class GeneratorImpl : public torch::nn::Module {
 public:
  explicit GeneratorImpl(GeneratorConfig config);
  SparseStructureFlowTdfyWrapper backbone() { return reverse_fn->backbone; }
  const GeneratorConfig& config() const { return config_; }

  // The official time grid (steps + 1 values in [0, 1]).
  std::vector<double> time_grid(int steps, double rescale_t, bool reversed) const;
  // Integrates from x0 (t = 0) to t = 1. cond: [B, L, cond_channels]; x0: one tensor per latent
  // [B, T, ch] on cond's device. Runs without gradients. Returns the final latents (float32).
  Latents sample(const torch::Tensor& cond, const Latents& x0, const SampleOptions& o);
  // Gaussian noise x0 per latent ([batch, T, ch], float32), drawn in latent_mapping order from `gen`
  // (on the generator's device), then moved to `device`. Same generator state -> same noise.
  Latents noise(int64_t batch, torch::Generator& gen, torch::Device device) const;
  // The last sample() call's step-caching schedule (which steps were full, which guided); empty
  // vectors after a call without step caching.
  const StepCacheStats& step_cache_stats() const { return step_cache_stats_; }

  ClassifierFreeGuidance reverse_fn{nullptr};

 private:
  // The step cache of a sample() call (null when options.step_cache is off); validates the options.
  std::unique_ptr<StepCache> make_step_cache(const SampleOptions& o) const;
  GeneratorConfig config_;
  StepCacheStats step_cache_stats_;
};
TORCH_MODULE(Generator);

// Builds the generator from a config file (official or project layout), loads weights from a
// safetensors file (official names, "_base_models.generator." stripped if present; "" = keep the
// random init) strictly, moves it to `device` and sets eval mode. `overrides` ("a.b=v") edit the config.
Generator load_generator(const std::string& config_path, const std::string& weights_path, torch::Device device,
                         const std::vector<std::string>& overrides = {});

// Training-time t sampler of the official FlowMatching (lognorm_sampler, mean 0, std 1):
// sigmoid(N(0,1)) -> [batch] float32 in (0, 1), on the generator's device.
torch::Tensor sample_training_t(int64_t batch, torch::Generator& gen);

}  // namespace simu::models
