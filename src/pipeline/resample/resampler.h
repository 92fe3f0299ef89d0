// In-process amodal resampler: SAM 3D Objects Stage 1 (generator + optional LoRA adapter) ->
// sparse-structure decoder -> 64^3 occupancy -> watertight marching-cubes mesh in the canonical frame,
// plus the decoded rotation / scale / translation. Loaded once per process; every call samples ALL
// requested objects (x num_samples) in one batched generator call (one call per distinct condition
// length, since condition tokens are not padded).
//
//   simu::resample::ResamplerConfig cfg;             // official sampling defaults
//   cfg.generator_weights = "ss_generator.safetensors";
//   cfg.decoder_weights = "ss_decoder.safetensors";
//   cfg.adapter_dir = "runs/x/adapter";              // optional PEFT adapter
//   simu::resample::Resampler resampler(cfg);
//   auto result = resampler.resample({{cond_tokens /*[L, C]*/}}, /*seed=*/42);
//   result.objects[0][0].mesh  // canonical mesh; .rotation, .scale_canonical, ...
//
// Condition: each request carries either condition tokens [L, C] (an embedder's output) or the
// embedder's inputs (official kwarg names: image, rgb_image, mask, rgb_image_mask, pointmap,
// rgb_pointmap, each [1, ...] or unbatched, already preprocessed); the latter run through the
// condition embedder (embedder_config / embedder_weights) in one batched forward per call.
#pragma once

#include <torch/torch.h>

#include <Eigen/Core>

#include <array>
#include <functional>
#include <map>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "common/source_dir.h"
#include "common/config.h"
#include "models/cond_embedder.h"
#include "models/generator.h"
#include "models/pose.h"
#include "models/ss_decoder.h"
#include "pipeline/resample/marching_cubes.h"

namespace simu::resample {

using physics::Mesh;

// Seed of the random initialisation of modules without weights (ResamplerConfig::random_weights).
constexpr uint64_t kRandomWeightsSeed = 0;

struct ResamplerConfig {
  std::string generator_config = simu::source_dir() + "/configs/stage1_real.yaml";
  std::string generator_weights;  // safetensors; "" keeps the random init (benchmarks only)
  std::string decoder_config = simu::source_dir() + "/configs/ss_decoder.yaml";
  std::string decoder_weights;    // safetensors; "" keeps the random init (benchmarks only)
  std::string adapter_dir;        // PEFT adapter directory; "" = base model
  // The adapter is switched off inside lift_objects (the first lift runs the base model, as the paper
  // does) and on for every other resample() call (the probe's resampling). Set with the shipped
  // model's resampling adapter (shipped_resample_adapter).
  bool adapter_resample_only = false;
  // With the shipped model (default_model.h: no weights given) and no adapter_dir: also load the model
  // folder's resampling adapter (its manifest's files.resample_adapter, the FM-DPO adapter of
  // docs/results.md) with adapter_resample_only. probe --resample and reconstruct set it (their
  // --base-resampling clears it); lift, eval_lift, build_pairs and the Python module keep the base.
  bool shipped_resample_adapter = false;
  std::vector<std::string> generator_overrides;  // "a.b=v" edits of the generator config
  std::string embedder_config;    // condition embedder config; "" = requests must carry tokens
  std::string embedder_weights;   // its safetensors (official prefix stripped when present)
  // The condition preprocessing the model expects: "" = the released preset, else a preset name or a
  // YAML file (preprocess_choice in default_model.h; the shipped miniature sets its file). Programs use it
  // unless their own preprocessing flag names another.
  std::string preprocess;
  // Missing weight files are an error naming the flag (--generator-weights, --decoder-weights,
  // --embedder-weights) unless this is set: then those modules keep their random init and a
  // RANDOM WEIGHTS banner is logged (random_weights_banner(), for reports). Benchmarks and demos only.
  // The random init is drawn with torch's CPU generator seeded with kRandomWeightsSeed, whose state is
  // restored afterwards: every program (and the Python module) builds the same models.
  bool random_weights = false;
  // false: the decoder is built but never run (build_pairs stores latents only): its weights are not
  // required.
  bool use_decoder = true;
  std::string device = "auto";    // auto (CUDA when present, else CPU) | cpu | cuda | cuda:N
  // Stage-1 sampling: defaults = the official inference values (models::official_inference_options:
  // inference_pipeline.py overrides the training-time values of a released ss_generator.yaml), also
  // unconditional_handling add_flag; a value changed here is logged as the user's. The values used
  // are logged when the Resampler is made.
  int steps = 25;
  double rescale_t = 3.0;
  double cfg_strength = 7.0;
  std::pair<double, double> cfg_interval{0.0, 500.0};
  bool shortcut = false;  // official default: no_shortcut (d = 0)
  std::string solver;     // "" = the generator config's solver_method (euler in the released yaml)
  // Inference precision of embedder, generator and decoder (models/precision.h): auto = fp16 on CUDA
  // (the released pipeline.yaml dtype), fp32 on CPU; fp16 | bf16 need CUDA; fp32.
  std::string precision = "auto";
  // Sampling through persistent CUDA graphs (models::SampleOptions::cuda_graphs): each batch shape's
  // graph is recorded right after its first, eager evaluation (the capture overlaps the device's work,
  // models::GraphedForward::set_overlapped_capture); later evaluations and later calls replay. Off by
  // default: at 7,528 condition tokens replays measured no faster than eager launches, and the first
  // call of a fresh process (one `lift` run) measured slower with graphs (docs/lift.md). Pays in a
  // long-lived process at shorter conditions (2,800 tokens: 663 vs 681-832 ms per sampling).
  bool cuda_graphs = false;
  // Opt-in step caching of the Stage-1 sampling (models::StepCacheOptions; docs/step_cache.md):
  // off by default. Keys under `step_cache:` (enabled, interval, order, warmup, tail,
  // pose_momentum, tolerance).
  models::StepCacheOptions step_cache;
  // The meshes' surface moved inward by this many voxels of the occupancy grid after marching cubes
  // (offset_surface: the learnt occupancy marks every voxel the surface touches, so its iso-0 surface sits
  // outside the object). NaN = the model's: the shipped model's manifest (mesh.surface_offset_voxels,
  // chosen on the validation split, docs/miniature.md), else 0. The occupied voxels (coords) do not move.
  double surface_offset = std::numeric_limits<double>::quiet_NaN();
  int num_samples = 1;    // shapes drawn per object
  // A sample whose decoded occupancy is empty (no logit > 0: no occupied voxel) is drawn again with
  // fresh noise, at most this many more times (0 = off): retry k draws the noise of every row from a CPU
  // generator seeded with retry_noise_seed(seed, k) and keeps the empty rows' (so a retry does not
  // depend on which other rows were empty). Such a sample's `retries` counts the redraws and its message
  // says "retried N times"; only when every attempt is empty does it fail (ok false), as without retries.
  int empty_retries = 2;
  int decode_batch = 8;   // objects per decoder forward
  std::string pose_convention = "ScaleShiftInvariant";  // see models::PoseDecodeOptions

  // Keys as the fields above (cfg_interval as [lo, hi]); unknown keys are errors.
  static ResamplerConfig from(simu::config::Reader& r);
};

// One object to resample.
struct ResampleRequest {
  torch::Tensor cond;                          // [L, C] condition tokens, or undefined and:
  std::map<std::string, torch::Tensor> inputs;  // embedder inputs by official kwarg name
  double scene_scale = 1.0;                    // point-map scale for the pose convention
  std::array<double, 3> scene_shift{0, 0, 0};  // point-map shift for the pose convention
};

// One sampled shape of one object.
struct ResampledShape {
  bool ok = false;      // false when no voxel is occupied (then mesh is empty)
  std::string message;  // why not ok; for an ok sample drawn again after empty decodes, "retried N times ..."
  int retries = 0;      // fresh-noise redraws after empty decodes (ResamplerConfig::empty_retries)
  Mesh mesh;              // canonical frame: AABB centred, longest side 1
  CanonicalTransform canonical;   // official voxel frame ([-0.5, 0.5]^3) -> canonical
  torch::Tensor coords;           // [N, 3] int32 occupied voxels (x, y, z) of the 64^3 grid
  // Decoded pose (column vectors): p_cam = rotation * (scale .* p_voxel_frame) + translation.
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  Eigen::Vector4d quaternion{1, 0, 0, 0};  // (w, x, y, z) of the official (row-vector) rotation
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  Eigen::Vector3d scale = Eigen::Vector3d::Ones();
  // The same pose for the canonical mesh: p_cam = rotation * (scale_canonical .* p_canonical) + translation_canonical.
  Eigen::Vector3d scale_canonical = Eigen::Vector3d::Ones();
  Eigen::Vector3d translation_canonical = Eigen::Vector3d::Zero();
  models::Latents latents;  // this sample's latents, [1, T, ch] float32 on the CPU
};

struct ResampleResult {
  std::vector<std::vector<ResampledShape>> objects;  // [request][sample]
  int sampling_calls = 0;                            // batched generator calls made
  double seconds_embed = 0, seconds_sample = 0, seconds_decode = 0, seconds_mesh = 0;
};

// Loads a PEFT adapter directory into the generator module tree (root = the Generator, whose PEFT keys
// read base_model.model.reverse_fn.backbone...). Default (nullptr): simu::lora::load_peft.
using AdapterLoader = std::function<void(const std::string& dir, torch::nn::Module& generator)>;

class Resampler {
 public:
  // Loads generator, decoder, the embedder when configured, and (if cfg.adapter_dir is set) the
  // adapter through `adapter_loader` (default simu::lora::load_peft).
  explicit Resampler(ResamplerConfig config, AdapterLoader adapter_loader = nullptr);

  // Samples num_samples shapes per request in one batched call per condition length, decodes them.
  // Noise: drawn for all (request, sample) rows in request order from a CPU generator seeded with
  // `seed`, so results do not depend on the device or on the batch composition's grouping. Rows whose
  // occupancy came out empty are sampled again (ResamplerConfig::empty_retries; sample_with_retries).
  // `samples` > 0 draws that many per request instead of num_samples (a first lift's best of K).
  ResampleResult resample(const std::vector<ResampleRequest>& requests, uint64_t seed, int samples = 0);

  // Decodes shape latents [B, T, 8] -> occupancy logits [B, 1, R, R, R] (decoder batched by decode_batch).
  torch::Tensor decode_logits(const torch::Tensor& shape_latent);

  models::Generator& generator() { return generator_; }
  models::SparseStructureDecoder& decoder() { return decoder_; }
  // The condition embedder (null when embedder_config is empty).
  models::CondEmbedder& embedder() { return embedder_; }
  // Condition tokens of every request [L, C] (embedding the ones given as inputs, batched).
  std::vector<torch::Tensor> conditions(const std::vector<ResampleRequest>& requests);
  const torch::Device& device() const { return device_; }
  models::Precision precision() const { return precision_; }
  const ResamplerConfig& config() const { return config_; }
  // Switches sampling through CUDA graphs (ResamplerConfig::cuda_graphs) for later calls; off drops the
  // graphs kept so far.
  void set_cuda_graphs(bool on);
  bool has_adapter() const { return has_adapter_; }
  // The adapter is for resampling only (ResamplerConfig::adapter_resample_only with an adapter loaded).
  bool adapter_resample_only() const { return has_adapter_ && config_.adapter_resample_only; }
  // Switches the loaded adapter's LoRA layers on or off for later calls (no-op without an adapter).
  void set_adapter_enabled(bool enabled);
  // Loads a PEFT adapter directory into the generator (simu::lora::load_peft; adapters already there are
  // replaced by the directory's), as the constructor does for config.adapter_dir.
  void load_adapter(const std::string& dir);
  // Non-empty when some module runs on random weights (random_weights): a one-line banner naming them,
  // to print in outputs and reports.
  const std::string& random_weights_banner() const { return random_banner_; }
  // Set when no weights were given and the shipped miniature was loaded (default_model.h): says which
  // model this is, and that it is not SAM 3D. "" otherwise.
  const std::string& shipped_model_note() const { return shipped_note_; }
  // The sampler options every resample() call uses, and the values among them the config changed.
  models::SampleOptions sample_options() const;
  models::SamplerOverrides sampler_overrides() const;

 private:
  ResamplerConfig config_;
  torch::Device device_;
  models::Precision precision_ = models::Precision::kFp32;
  models::Generator generator_{nullptr};
  models::SparseStructureDecoder decoder_{nullptr};
  models::CondEmbedder embedder_{nullptr};
  bool has_adapter_ = false;
  std::string random_banner_, shipped_note_;
};

// The noise seed of retry `attempt` (1, 2, ...) of a resample() call seeded with `seed`: the attempt-th
// output of the SplitMix64 generator started at state `seed` (common/random.h); attempt 0 is `seed`.
uint64_t retry_noise_seed(uint64_t seed, int attempt);

// True when a sample failed because its decoded occupancy has no occupied voxel (mesh_from_logits).
bool empty_occupancy(const ResampledShape& shape);

// One sampling attempt: fills *outs[k] for each k of `rows` from noise drawn with `noise_seed`.
using SampleAttempt = std::function<void(const std::vector<size_t>& rows, uint64_t noise_seed)>;

// Runs `attempt` on every row with `seed`, then, while some rows are empty (empty_occupancy) and at most
// `max_retries` times, on those rows alone with retry_noise_seed(seed, k) (each reset before its redraw).
// A row drawn again gets `retries` and, when a redraw succeeds, the message "retried N times: ..."; a row
// empty after every attempt keeps ok false with a message naming the attempts. resample() runs through it.
void sample_with_retries(const std::vector<ResampledShape*>& outs, uint64_t seed, int max_retries,
                         const SampleAttempt& attempt);

// Per batch row k: outs[k]'s latents (row k of `latents`, on the CPU) and its pose decoded in
// `convention` with requests[k]'s scene scale and shift (models::decode_pose).
void decode_poses(const models::Latents& latents, const std::vector<const ResampleRequest*>& requests,
                  const std::vector<ResampledShape*>& outs, const std::string& convention);

// Per batch row k of logits [rows, 1, R, R, R]: outs[k]'s mesh (mesh_from_logits) and its pose carried
// over to the canonical frame (scale_canonical, translation_canonical); rows in parallel when there are
// at least as many as threads.
void mesh_rows(const torch::Tensor& logits, const std::vector<ResampledShape*>& outs, double surface_offset = 0.0);

// Meshes one occupancy logit grid [R, R, R] (or [1, 1, R, R, R]): marching cubes at iso 0, the surface
// moved inward by `surface_offset` voxels (offset_surface; ResamplerConfig::surface_offset), official
// voxel frame, then the canonical frame. Fills mesh, canonical, coords, ok/message of `out`.
void mesh_from_logits(const torch::Tensor& logits, ResampledShape& out, double surface_offset = 0.0);

}  // namespace simu::resample
