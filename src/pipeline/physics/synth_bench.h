// The synthetic benchmark of the gravity diagnostics (the synth_bench program): scenes with known
// ground truth and injected monocular errors (or written ones), each probed with MuJoCo (or the
// ideal oracle), scored before / after correction, and the table of decision accuracy per injected
// error, overlap metrics and (MuJoCo) physics and headline metrics.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "pipeline/physics/probe.h"
#include "pipeline/physics/synthetic.h"

namespace simu::physics {

struct SynthBenchOptions {
  int num_scenes = 20;            // scenes to generate (from_dir: every scene found there instead)
  uint64_t seed = 1;              // scene k uses seed + k
  int threads = 1;                // scenes evaluated in parallel
  std::string write_dir;          // also write each scene (scene.json, meshes, masks) here ("" = no)
  std::string from_dir;           // evaluate the written scenes DIR/*/scene.json (name order) instead
  SyntheticConfig synthetic;      // the generator
  CorrectionConfig correction;    // rho threshold and the oracle's correction
  ResampleProxy proxy = ResampleProxy::Stretch;  // stand-in for the resampler on the resample branch
  bool mujoco = true;             // MuJoCo run_probe (physics metrics); false: the oracle drop
  double metrics_time = 5.0;      // evaluation settle (s; paper: 5)
};

// Per scene k (index order): its scores, or the error that stopped it ("" when none).
struct SynthBenchResult {
  int num_scenes = 0;
  std::vector<SceneEvaluation> scenes;
  std::vector<std::string> errors;
  std::vector<PhysicsEvaluation> physics_before, physics_after;  // MuJoCo: 5 s settle of input / output
  std::vector<HeadlineMetrics> headline_before, headline_after;  // MuJoCo: the paper's metrics
  int disabled = 0;  // physics-disabled objects over all scenes
  int reverted = 0;  // objects reverted in the final settle
};

// "stretch", "drop", "keep".
const char* resample_proxy_name(ResampleProxy p);
// Generates (or reads) and evaluates the scenes on o.threads threads; a scene that fails is recorded
// in errors (and logged), not thrown. Progress on stderr every 10 scenes.
SynthBenchResult run_synth_bench(const SynthBenchOptions& o);
// The benchmark's table (what synth_bench prints).
std::string synth_bench_table(const SynthBenchOptions& o, const SynthBenchResult& r);

}  // namespace simu::physics
