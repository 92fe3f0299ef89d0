// synth_bench: generates synthetic scenes with known ground truth and injected monocular errors (or
// reads written ones with --from), measures each free object's displacement with the MuJoCo probe
// (or the ideal "oracle": drop to the known support), runs the paper's stretch-or-resample decision
// and correction, and prints the decision accuracy per injected error type, the overlap metrics
// before (the input reconstruction) / after correction and, with the MuJoCo probe, the physics
// metrics before (the scene as read, settled 5 s without correction) and after (the probe's corrected
// scene, settled 5 s). With the MuJoCo probe every "after" figure comes from the probe's output: the
// overlap metrics score its corrected scene (settled poses, corrected scales, the meshes it used),
// the physics metrics the evaluation settle that starts from that same scene. With the oracle the
// "after" objects are each corrected alone from the known support (no simulation).
#include "common/cli.h"
#include "common/config.h"
#include "common/log.h"
#include "common/parallel.h"
#include "common/timing.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/synth_bench.h"
#include "pipeline/physics/synthetic.h"

#include <unistd.h>

#include <fmt/format.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <map>
#include <mutex>
#include <thread>

using namespace simu::physics;

int main(int argc, char** argv) {
  CLI::App app{"Synthetic benchmark of the gravity diagnostics: decision accuracy and metrics before/after"};
  int num_scenes = 20;
  uint64_t seed = 1;
  int threads = 1;
  std::string layout;
  std::string write_dir;
  std::string config_path;
  double threshold = -1;
  std::string proxy_name = "stretch";
  std::string probe_name = "mujoco";
  std::string from_dir;
  double metrics_time = 5.0;
  app.add_option("-n,--scenes", num_scenes, "number of scenes to generate")->check(CLI::PositiveNumber);
  app.add_option("--seed", seed, "first seed (scene k uses seed + k)");
  app.add_option("--layout", layout, "tabletop | shelf | mixed (default: config, else mixed)");
  app.add_option("--threads", threads, "scenes evaluated in parallel")->check(CLI::PositiveNumber);
  app.add_option("--write", write_dir, "also write each scene (scene.json, meshes, masks) under this folder");
  app.add_option("--config", config_path, "YAML/JSON with `synthetic:` (generator) and `correction:` sections");
  app.add_option("--threshold", threshold, "rho threshold for resampling (default: config, else the paper's 0.15)");
  app.add_option("--resample-proxy", proxy_name,
                 "stand-in for the resampler on the resample branch: stretch (the input mesh stretched to fill B_str, placed "
                 "by the probe), drop (no resampler: the probe keeps the input mesh where the diagnostic left it), keep "
                 "(oracle only: left as reconstructed)");
  app.add_option("--probe", probe_name,
                 "displacement source: mujoco (run_probe on the written scene; physics metrics) or oracle (drop to the "
                 "known support; overlap metrics only)")->capture_default_str();
  app.add_option("--from", from_dir,
                 "evaluate the written scenes in this folder (each DIR/*/scene.json, e.g. tests/testdata/scenes) instead of "
                 "generating");
  app.add_option("--metrics-time", metrics_time, "evaluation settle for the physics metrics (s; paper: 5)")
      ->capture_default_str();
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    SyntheticConfig syn;
    CorrectionConfig corr;
    if (!config_path.empty() || !common.sets.empty()) {
      YAML::Node node = config_path.empty() ? YAML::Node(YAML::NodeType::Map) : simu::config::load_file(config_path);
      for (const auto& a : common.sets) simu::config::apply_override(node, a, config_path);
      simu::config::Reader r(node, config_path.empty() ? "--set" : config_path);
      if (r.has("synthetic")) {
        auto c = r.child("synthetic");
        syn = SyntheticConfig::from(c);
      }
      if (r.has("correction")) {
        auto c = r.child("correction");
        corr = CorrectionConfig::from(c);
      }
      r.finish();
    }
    if (!layout.empty()) syn.layout = layout;
    else if (config_path.empty()) syn.layout = "mixed";
    if (threshold >= 0) corr.resample_threshold = threshold;
    const auto proxy = parse_resample_proxy(proxy_name);
    SIMU_CHECK(proxy, "--resample-proxy: got '{}', expected stretch, drop or keep", proxy_name);
    SIMU_CHECK(probe_name == "oracle" || probe_name == "mujoco", "--probe: got '{}', expected oracle or mujoco", probe_name);
    SIMU_CHECK(!(probe_name == "mujoco" && *proxy == ResampleProxy::Keep),
               "--resample-proxy keep needs --probe oracle (the probe's final settle moves every object)");
    SynthBenchOptions o;
    o.num_scenes = num_scenes;
    o.seed = seed;
    o.threads = threads;
    o.write_dir = write_dir;
    o.from_dir = from_dir;
    o.synthetic = syn;
    o.correction = corr;
    o.proxy = *proxy;
    o.mujoco = probe_name == "mujoco";
    o.metrics_time = metrics_time;
    const SynthBenchResult res = run_synth_bench(o);
    fmt::print("{}", synth_bench_table(o, res));
    const int failed = static_cast<int>(std::count_if(res.errors.begin(), res.errors.end(), [](const std::string& e) { return !e.empty(); }));
    if (failed) fmt::print("{} scene(s) failed (see warnings)\n", failed);
    return failed == res.num_scenes ? 1 : 0;
  });
}
