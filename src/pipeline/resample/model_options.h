// The model / precision options shared by the programs that load the Stage-1 models (lift,
// reconstruct, bench_reconstruct): one block of command-line flags filling a ResamplerConfig, and the
// one way of finishing it (weights check with its RANDOM WEIGHTS banner, --precision, --random-weights).
//
//   flags   --generator-config, --generator-weights, --decoder-config, --decoder-weights,
//           --embedder-config, --embedder-weights, --adapter, --random-weights, --preprocess, --device, --precision,
//           --steps, --samples, --seed (each optional: ModelOptionFlags picks which a program has),
//           --step-cache, --step-cache-order, --step-cache-momentum (opt-in step caching, off by default)
#pragma once

#include "pipeline/resample/resampler.h"

#include <CLI/CLI.hpp>

#include <cstdint>
#include <string>

namespace simu::resample {

struct ModelOptions {
  ResamplerConfig config;          // filled by the flags (embedder config defaults to the Stage-1 one)
  std::string precision = "auto";  // auto | fp16 | bf16 | fp32 (apply_precision)
  bool random_weights = false;     // allow missing weight files (random init: smoke runs, benchmarks)
  uint64_t seed = 0;               // sampling seed
  int step_cache_interval = 0;     // --step-cache K: step caching every K steps (0 = off), into config.step_cache
  std::string preprocess;          // --preprocess: preset name or YAML file; "" = the model's (config.preprocess)
  std::string shipped_note;        // set by finish_model_options when the shipped miniature was loaded
  ModelOptions();
};

// Which of the optional flags a program offers (the weights, device, precision and step flags always).
struct ModelOptionFlags {
  bool adapter = true;   // --adapter
  bool samples = true;   // --samples
  bool seed = true;      // --seed
};

// Adds the flags to app, writing into opts (defaults shown in --help). `group` names the --help section.
void add_model_options(CLI::App& app, ModelOptions& opts, const ModelOptionFlags& flags = {},
                       const std::string& group = "Model");

// After parsing: with no weights at all (and no --random-weights), loads the shipped miniature
// (default_model.h; its note in opts.shipped_note); checks the weight files (an error naming the flag, unless --random-weights), applies
// --precision and --random-weights to opts.config. Returns the RANDOM WEIGHTS banner ("" with real
// weights) for the program to print and put in its report.
std::string finish_model_options(ModelOptions& opts);

}  // namespace simu::resample
