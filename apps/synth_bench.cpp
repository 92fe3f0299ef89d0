// synth_bench: generates synthetic scenes with known ground truth and injected monocular errors,
// measures each free object's gravity displacement (the ideal "oracle" probe: drop to the known
// support), runs the paper's stretch-or-resample decision and correction, and prints the decision
// accuracy per injected error type and the overlap metrics before / after correction.
#include "common/cli.h"
#include "common/config.h"
#include "common/log.h"
#include "pipeline/probe.h"
#include "pipeline/synthetic.h"

#include <unistd.h>

#include <fmt/format.h>

#include <atomic>
#include <chrono>
#include <filesystem>
#include <map>
#include <mutex>
#include <thread>

using namespace simu::pipeline;

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
  std::string probe_name = "oracle";
  app.add_option("-n,--scenes", num_scenes, "number of scenes to generate")->check(CLI::PositiveNumber);
  app.add_option("--seed", seed, "first seed (scene k uses seed + k)");
  app.add_option("--layout", layout, "tabletop | shelf | mixed (default: config, else mixed)");
  app.add_option("--threads", threads, "scenes evaluated in parallel")->check(CLI::PositiveNumber);
  app.add_option("--write", write_dir, "also write each scene (scene.json, meshes, masks) under this folder");
  app.add_option("--config", config_path, "YAML/JSON with `synthetic:` (generator) and `correction:` sections");
  app.add_option("--threshold", threshold, "rho threshold for resampling (default: config, else the paper's 0.15)");
  app.add_option("--resample-proxy", proxy_name,
                 "stand-in for the resampler on the resample branch: stretch (fill B_str), drop (layout-only), keep");
  app.add_option("--probe", probe_name,
                 "displacement source: oracle (drop to the known support) or mujoco (run_probe on the written scene)");
  simu::cli::CommonOptions common;
  simu::cli::add_common_options(app, common);
  return simu::cli::run(app, argc, argv, [&] {
    simu::cli::apply_common_options(common);
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
    std::atomic<int> disabled{0};

    // Evaluate the scenes (in parallel), collecting per-scene results in order.
    std::vector<SceneEvaluation> results(num_scenes);
    std::vector<std::string> errors(num_scenes);
    std::atomic<int> next{0}, done{0};
    std::mutex print_mutex;
    const auto t0 = std::chrono::steady_clock::now();
    auto worker = [&] {
      for (int k; (k = next++) < num_scenes;) {
        try {
          const std::string name = fmt::format("synth_{:04d}", k);
          const SyntheticScene s = generate_scene(syn, seed + k, name);
          std::string dir = write_dir.empty() ? "" : (std::filesystem::path(write_dir) / name).string();
          std::vector<Displacement> disp;
          if (probe_name == "mujoco") {
            // The physics probe measures dt_pen / dt_grv on the written scene (no outputs, no resampler).
            if (dir.empty())
              dir = (std::filesystem::temp_directory_path() / fmt::format("synth_bench_{}", ::getpid()) / name).string();
            write_scene_dir(s, dir);
            ProbeConfig pc;
            pc.write_outputs = false;
            pc.rho_threshold = corr.resample_threshold;
            const ProbeResult pr = run_probe(load_scene(dir + "/scene.json"), pc, "");
            for (const Diagnostics& d : pr.diagnostics) {
              disp.push_back({d.dt_pen, d.dt_grv});
              disabled += d.physics_disabled;
            }
          } else if (!dir.empty()) {
            write_scene_dir(s, dir);
          }
          results[k] = evaluate_scene(s, corr, disp, *proxy);
        } catch (const std::exception& e) {
          errors[k] = e.what();
        }
        std::lock_guard<std::mutex> lock(print_mutex);
        const int d = ++done;
        const double el = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        if (d == num_scenes || d % 10 == 0)
          fmt::print(stderr, "[{}/{}] scenes evaluated, {:.1f} s\n", d, num_scenes, el);
      }
    };
    std::vector<std::thread> pool;
    for (int i = 0; i < std::min(threads, num_scenes); ++i) pool.emplace_back(worker);
    for (auto& t : pool) t.join();

    // Decision accuracy per injected error type.
    std::map<std::string, std::array<int, 3>> per;  // error -> {n, correct, resampled}
    int n = 0, correct = 0;
    double gap_before = 0, gap_after = 0;
    int failed = 0;
    for (int k = 0; k < num_scenes; ++k) {
      if (!errors[k].empty()) {
        ++failed;
        simu::log::warn("scene {}: {}", k, errors[k]);
        continue;
      }
      for (const ObjectOutcome& o : results[k].objects) {
        auto& a = per[to_string(o.error)];
        ++a[0], ++n;
        a[1] += o.got == o.expected, correct += o.got == o.expected;
        a[2] += o.got == Branch::Resample;
        gap_before += o.support_gap_before, gap_after += o.support_gap_after;
      }
    }
    fmt::print("Decision (rho >= {:.2f} -> resample) vs injected error; expected: bottom_cut -> resample, others -> stretch\n",
               corr.resample_threshold);
    fmt::print("{:<12} {:>6} {:>9} {:>10}\n", "error", "n", "accuracy", "resampled");
    for (const auto& [e, a] : per)
      fmt::print("{:<12} {:>6} {:>8.1f}% {:>9.1f}%\n", e, a[0], a[0] ? 100.0 * a[1] / a[0] : 0.0,
                 a[0] ? 100.0 * a[2] / a[0] : 0.0);
    fmt::print("{:<12} {:>6} {:>8.1f}%\n", "all", n, n ? 100.0 * correct / n : 0.0);

    // Mean overlap metrics before / after over the scenes.
    auto mean = [&](auto get) {
      double s = 0;
      int c = 0;
      for (int k = 0; k < num_scenes; ++k)
        if (errors[k].empty()) s += get(results[k]), ++c;
      return c ? s / c : 0.0;
    };
    fmt::print("\nMetric (mean over {} scenes)       before    after\n", num_scenes - failed);
    fmt::print("2D IoU                          {:8.4f} {:8.4f}\n", mean([](auto& r) { return r.mask_before.iou; }),
               mean([](auto& r) { return r.mask_after.iou; }));
    fmt::print("2D ABO                          {:8.4f} {:8.4f}\n", mean([](auto& r) { return r.mask_before.abo; }),
               mean([](auto& r) { return r.mask_after.abo; }));
    fmt::print("3D AABB IoU                     {:8.4f} {:8.4f}\n", mean([](auto& r) { return r.box_before.iou; }),
               mean([](auto& r) { return r.box_after.iou; }));
    fmt::print("3D AABB ABO                     {:8.4f} {:8.4f}\n", mean([](auto& r) { return r.box_before.abo; }),
               mean([](auto& r) { return r.box_after.abo; }));
    fmt::print("support gap (mm, free objects)  {:8.2f} {:8.2f}\n", n ? 1000 * gap_before / n : 0.0,
               n ? 1000 * gap_after / n : 0.0);
    fmt::print("resample branch stand-in: {}\n", proxy_name);
    if (probe_name == "mujoco")
      fmt::print("probe: MuJoCo run_probe (dt_pen, dt_grv); physics-disabled objects: {}\n", disabled.load());
    else
      fmt::print("probe: oracle drop to the known support (MuJoCo: --probe mujoco)\n");
    if (failed) fmt::print("{} scene(s) failed (see warnings)\n", failed);
    return failed == num_scenes ? 1 : 0;
  });
}
