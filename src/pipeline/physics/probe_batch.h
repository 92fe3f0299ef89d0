// The probe program's work as a library call: output folders per input scene, the scenes run in
// parallel with one shared resampler, and the printed per-object summary, headline metrics and
// pictures. apps/probe.cpp only parses arguments and calls this.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "pipeline/physics/probe.h"

namespace simu::physics {

// Output folder of each input scene: one scene -> out; several -> out/<file stem>, prefixed where stems
// collide with as many parent folder names as tell them apart (every committed scene is scene.json:
// out/synth_0000_scene, ...). Throws simu::Error naming both inputs when the same file is given twice.
std::vector<std::string> probe_output_dirs(const std::vector<std::string>& scenes, const std::string& out);

// Makes the resample function of one scene (the resampler lives outside the physics library);
// nullptr or an empty function: no resampling (the hand-off is written).
using ResampleFactory = std::function<ResampleFn(const Scene&)>;

struct ProbeBatchOptions {
  int threads = 1;     // scenes in parallel
  bool quiet = false;  // no per-object progress lines
};

// Runs the probe on every scene into its output folder (probe_output_dirs). Refuses before any work
// when an output folder exists and cfg.overwrite is false. A failing scene is reported and the others
// go on. Prints per scene: the per-object summary, the headline metrics, the pictures. Returns the
// number of scenes that failed.
int run_probe_batch(const std::vector<std::string>& scenes, const std::string& out, const ProbeConfig& cfg,
                    const ResampleFactory& resample = nullptr, const ProbeBatchOptions& options = {});

// Per-object summary of a run: branch, rho, displacement in the 5 s settle before (input) and after
// (final scene), flags; resample candidates and whether one replaced the object.
std::string probe_summary(const ProbeResult& r);

// The --help text listing every config key with its default and documentation.
std::string probe_config_help(const ProbeConfig& defaults = {});

}  // namespace simu::physics
