// Builds an FM-DPO pair cache (data/pair_cache.h, docs/pair_cache.md) from images, with the same
// in-process runtime as the resampler (condition embedder + Stage-1 generator, resample/resampler.h).
// The pairs are the paper's (supplementary "SAM3D Fine-tuning Details"):
//
//   occlusion-completion (kind 0, weight 1.0): an occluded image I with the target's modal mask M_i,
//     and an edited image (occluder removed, target completed) with the full-object mask M'_i.
//     rejected x- = Stage 1 on (I, M_i)           (the occluded input, plain official preprocessing)
//     preferred x+ = Stage 1 on (edited, M'_i)    (the full-object input)
//     stored condition c_i = (I, M_i, I_{M'_i}, D): the occluded image and modal mask, crop box and
//       background removal from M'_i (the resampling input, preprocess.h `crop_mask`).
//   clean-preservation (kind 1, weight 0.1): a clean image with the object's mask M, and a corrupted
//     mask (part of M dropped).
//     preferred x+ = Stage 1 on (I, M), rejected x- = Stage 1 on (I, corrupted M),
//     stored condition = (I, M, I_M, D) (the clean input; its M' is M itself).
//
// Both sides of a pair start from the same initial noise, drawn from a CPU generator seeded with
// pair_noise_seed(seed, id), so a pair's latents depend only on its inputs, the seed and its id (not
// on the batch it was built in, nor on resuming). The condition is stored as the embedder's tokens
// (cond_mode "tokens") or as the embedder's inputs (cond_mode "inputs": the six preprocessed tensors,
// which train_fmdpo embeds in the step). Manifest format: see parse_manifest_line and docs/pair_cache.md.
//
//   simu::resample::PairBuilderConfig cfg;
//   cfg.resampler.generator_config = ...; cfg.resampler.embedder_config = ...;   // models
//   cfg.out = "pairs.h5";
//   auto report = simu::resample::build_pairs("manifest.jsonl", cfg);
#pragma once

#include <torch/torch.h>

#include <atomic>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "data/pair_cache.h"
#include "data/preprocess.h"
#include "pipeline/resample/resampler.h"

namespace simu::resample {

// One manifest line (JSON object). Keys (paths relative to the manifest's directory unless absolute):
//   id              string, unique, non-empty (required)
//   kind            "occlusion_completion" | "clean_preservation" (required)
//   image, mask     the occluded (kind 0) or clean (kind 1) image and the modal (kind 0) or clean mask
//   full_image, full_mask   kind 0 only: the edited full-object image and the full-object mask M'
//   corrupted_mask  kind 1 only: the corrupted mask
//   pointmap        optional point map of `image` (safetensors, see load_pointmap_file)
//   full_pointmap   optional, kind 0: point map of `full_image` (default: `pointmap`)
//   weight          optional loss weight (default 1.0 kind 0, 0.1 kind 1)
//   gt_occupancy    optional .npy uint8 [R, R, R]: the object's filled occupancy in the decoder's
//                   canonical frame (world pairs writes it); used by PairBuilderConfig::filter_gt
// Images: anything OpenCV reads (PNG, JPEG, ...); masks: grey (object > 0), RGBA (alpha) or RGB (max).
// Unknown keys are errors. Blank lines and lines starting with '#' are skipped.
struct PairManifestRecord {
  int64_t line = 0;  // 1-based line of the manifest
  std::string id;
  data::PairKind kind = data::PairKind::OcclusionCompletion;
  float weight = 1.0f;
  std::string image, mask, full_image, full_mask, corrupted_mask, pointmap, full_pointmap, gt_occupancy;
};

// Parses one manifest line (already known not to be blank or a comment). Throws simu::Error (without
// the line number) for malformed JSON, a missing/unknown key, an unknown kind or a bad weight.
PairManifestRecord parse_manifest_line(const std::string& text, const std::string& base_dir);

// A manifest line that was not turned into a pair.
struct PairIssue {
  int64_t line = 0;
  std::string id;  // "" when the line has none
  std::string message;
};

// A whole manifest: the good records in line order, the bad lines (malformed, duplicate id) as issues.
struct ManifestParse {
  std::vector<PairManifestRecord> pairs;
  std::vector<PairIssue> issues;
  int64_t records = 0;  // non-blank, non-comment lines
};
ManifestParse parse_manifest(const std::string& text, const std::string& base_dir);

// Point map file: safetensors holding one tensor (or one named "pointmap") [3, H, W] or [H, W, 3],
// float, points in the PyTorch3D camera frame (x left, y up, z forward; NaN = invalid); or an .npy
// [H, W, 3] in the OpenCV camera frame (x right, y down: what lift --pointmap and `world` read and
// write), turned into PyTorch3D's by negating x and y. Returns [3, H, W].
torch::Tensor load_pointmap_file(const std::string& path);

// The point map used when a record has none: a fronto-parallel plane at depth 1 seen by a pinhole
// camera with a 60 degree horizontal field of view, principal point at the image centre,
// in the PyTorch3D camera frame: x = -(u + 0.5 - W/2) / f, y = -(v + 0.5 - H/2) / f, z = 1, with
// f = (W/2) / tan(30 deg). [3, H, W] float32. (The official pipeline estimates depth with MoGe,
// which this toolkit does not port; give real point maps per record when you have them.)
torch::Tensor default_pointmap(int64_t height, int64_t width);

// The seed of a pair's initial noise: splitmix64(seed ^ FNV-1a 64 of id).
uint64_t pair_noise_seed(uint64_t seed, const std::string& id);

struct PairBuilderConfig {
  ResamplerConfig resampler;          // models and sampling (num_samples is ignored: one per side)
  data::PreprocessConfig preprocess;  // Stage-1 preprocessing; default: the released pipeline.yaml preset
  std::string out;                    // the cache (.h5); written atomically
  torch::ScalarType dtype = torch::kFloat16;  // storage of latents and cond (float16 | float32)
  std::string cond_mode = "tokens";   // "tokens" (embedder output) or "inputs" (embedder inputs)
  std::string inputs_storage = "exact";  // inputs mode: "exact" (float32) or "compact" (data::InputsLayout)
  int64_t batch = 4;                  // pairs embedded and sampled per batched call
  uint64_t seed = 0;                  // noise seed (see pair_noise_seed)
  bool resume = true;                 // an existing `out` is kept and extended; false replaces it
  int64_t commit_every = 256;         // pairs between commits of `out` (0: only at the end)
  std::string created_by = "build_pairs";
  // The paper's filter: decode both sides of every pair whose record has gt_occupancy and drop the
  // pair unless x+ is closer to the ground truth than x- (occupancy IoU, logits > 0). Needs the
  // decoder (its weights) in the resampler; a record without gt_occupancy is an issue.
  bool filter_gt = false;
  // Where x+ comes from. "sample" (the paper): Stage 1 on the preferred input. "gt_latent": the
  // sparse-structure encoder's posterior mean of the record's gt_occupancy (tokens [k^3, C], the
  // targets train_stage1 trains on), the ideal completion rather than the base model's own best; only x-
  // is sampled. The cache's created_by says so ("x+ = ground-truth encoder latent"). Needs
  // encoder_config / encoder_weights (a train_ss_vae output) and gt_occupancy in every record.
  std::string preferred = "sample";
  std::string encoder_config, encoder_weights;
};

// What the filter measured for one pair.
struct PairFilterRow {
  std::string id;
  data::PairKind kind = data::PairKind::OcclusionCompletion;
  double iou_pos = 0, iou_neg = 0;
  bool kept = false;
};

struct PairBuildReport {
  int64_t records = 0;           // non-blank, non-comment manifest lines
  int64_t written = 0;           // pairs added by this run
  int64_t skipped_existing = 0;  // already in the cache (resume)
  int64_t cache_size = 0;        // pairs in the cache at the end
  bool interrupted = false;      // stopped by the stop flag (what was done is committed)
  std::vector<PairIssue> issues;  // bad records, in line order; skipped
  std::vector<PairFilterRow> filtered;  // filter_gt: every pair it judged, kept or dropped, in build order
  double seconds = 0;
};

// Progress callback: (records handled, records in the manifest).
using PairBuildProgress = std::function<void(int64_t done, int64_t total)>;

// Reads the manifest, skips the ids the cache already holds, builds the others in batches of
// cfg.batch and appends them. A bad record (malformed line, missing file, mask/image size mismatch,
// empty mask, duplicate id, point-map problem, non-finite output) is logged with its line number,
// listed in the report and skipped. The cache is committed (finish + reopen) every cfg.commit_every
// pairs and at the end; an exception or a crash in between loses only the uncommitted pairs and never
// leaves a half-written `out` (PairCacheWriter's atomic rename). When *stop becomes true the run
// commits what it has and returns with interrupted = true.
PairBuildReport build_pairs(const std::string& manifest_path, const PairBuilderConfig& cfg, Resampler& resampler,
                            const PairBuildProgress& progress = nullptr, const std::atomic<bool>* stop = nullptr);
// Same, loading the models from cfg.resampler (cfg.resampler.embedder_config is required).
PairBuildReport build_pairs(const std::string& manifest_path, const PairBuilderConfig& cfg,
                            const PairBuildProgress& progress = nullptr, const std::atomic<bool>* stop = nullptr);

}  // namespace simu::resample
