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
#include "physics/probe.h"
#include "physics/synthetic.h"

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
                 "evaluate the written scenes in this folder (each DIR/*/scene.json, e.g. tests/data/scenes) instead of "
                 "generating");
  app.add_option("--metrics-time", metrics_time, "evaluation settle for the physics metrics (s; paper: 5)")
      ->capture_default_str();
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
    SIMU_CHECK(!(probe_name == "mujoco" && *proxy == ResampleProxy::Keep),
               "--resample-proxy keep needs --probe oracle (the probe's final settle moves every object)");
    std::atomic<int> disabled{0}, reverted{0};
    // Written scenes to evaluate (--from), in name order.
    std::vector<std::string> from_scenes;
    if (!from_dir.empty()) {
      SIMU_CHECK(std::filesystem::is_directory(from_dir), "--from: {} is not a folder", from_dir);
      for (const auto& e : std::filesystem::directory_iterator(from_dir))
        if (std::filesystem::exists(e.path() / "scene.json")) from_scenes.push_back((e.path() / "scene.json").string());
      std::sort(from_scenes.begin(), from_scenes.end());
      SIMU_CHECK(!from_scenes.empty(), "--from: no */scene.json under {}", from_dir);
      num_scenes = static_cast<int>(from_scenes.size());
    }
    // Physics records (before / after) and scene peak energies per scene (MuJoCo probe).
    std::vector<PhysicsEvaluation> phys_before(num_scenes), phys_after(num_scenes);
    // The paper's headline metrics per scene after the 5 s settle (MuJoCo probe).
    std::vector<HeadlineMetrics> head_before(num_scenes), head_after(num_scenes);

    // Evaluate the scenes (in parallel), collecting per-scene results in order.
    std::vector<SceneEvaluation> results(num_scenes);
    std::vector<std::string> errors(num_scenes);
    std::atomic<int> done{0};
    std::mutex print_mutex;
    const auto t0 = simu::Clock::now();
    simu::parallel_for_each(num_scenes, threads, [&](int64_t k) {
      try {
        const std::string name = fmt::format("synth_{:04d}", k);
        const bool from = !from_scenes.empty();
        const SyntheticScene s = from ? load_synthetic_scene(from_scenes[k]) : generate_scene(syn, seed + k, name);
        std::string dir = write_dir.empty() ? "" : (std::filesystem::path(write_dir) / name).string();
        if (probe_name == "mujoco") {
          // The physics probe on the written scene (no files written); its corrected scene is scored.
          std::string scene_file = from ? from_scenes[k] : "";
          if (!from) {
            if (dir.empty())
              dir = (std::filesystem::temp_directory_path() / fmt::format("synth_bench_{}", ::getpid()) / name).string();
            write_scene_dir(s, dir);
            scene_file = dir + "/scene.json";
          }
          ProbeConfig pc;
          pc.write_outputs = false;
          pc.rho_threshold = corr.resample_threshold;
          pc.metrics_settle_time = metrics_time;
          const Scene input = load_scene(scene_file);
          // Before: the reconstruction as read, settled without any correction (run_probe's
          // evaluate_input). After: the probe's corrected scene (settled poses, corrected scales and
          // meshes; the resample branch through the proxy, or left where the diagnostic put it with
          // "drop"), and the evaluation settle that starts from it.
          pc.evaluate_input = true;
          const ResampleFn resampler = *proxy == ResampleProxy::Stretch ? stretch_resampler(s, corr) : nullptr;
          const ProbeResult pr = run_probe(input, pc, "", resampler);
          phys_before[k] = pr.input_evaluation;
          phys_after[k] = pr.evaluation;
          head_before[k] = pr.before;
          head_after[k] = pr.after;
          for (const Diagnostics& d : pr.diagnostics) {
            disabled += d.physics_disabled;
            reverted += d.reverted;
          }
          results[k] = evaluate_probe_output(s, pr);
        } else {
          if (!dir.empty()) write_scene_dir(s, dir);
          results[k] = evaluate_scene(s, corr, {}, *proxy);
        }
      } catch (const std::exception& e) {
        errors[k] = e.what();
      }
      std::lock_guard<std::mutex> lock(print_mutex);
      const int d = ++done;
      const double el = simu::seconds_since(t0);
      if (d == num_scenes || d % 10 == 0)
        fmt::print(stderr, "[{}/{}] scenes evaluated, {:.1f} s\n", d, num_scenes, el);
    });

    // Decision accuracy per injected error type.
    std::map<std::string, std::array<int, 3>> per;  // error -> {n, correct, resampled}
    int n = 0, correct = 0;
    double gap_before = 0, gap_after = 0;
    int failed = 0, undecided = 0;
    for (int k = 0; k < num_scenes; ++k) {
      if (!errors[k].empty()) {
        ++failed;
        simu::log::warn("scene {}: {}", k, errors[k]);
        continue;
      }
      for (const ObjectOutcome& o : results[k].objects) {
        auto& a = per[to_string(o.error)];
        ++a[0], ++n;
        const bool right = o.decided && o.got == o.expected;
        a[1] += right, correct += right;
        undecided += !o.decided;
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
    fmt::print("{:<12} {:>6} {:>8.1f}%   ({} / {} correct", "all", n, n ? 100.0 * correct / n : 0.0, correct, n);
    fmt::print(undecided ? fmt::format("; {} without a decision, counted wrong)\n", undecided) : std::string(")\n"));

    // Mean overlap metrics before / after over the scenes.
    auto mean = [&](auto get) {
      double s = 0;
      int c = 0;
      for (int k = 0; k < num_scenes; ++k)
        if (errors[k].empty()) s += get(results[k]), ++c;
      return c ? s / c : 0.0;
    };
    fmt::print("\nMetric (mean over {} scenes)       before    after   (before: input; after: {})\n", num_scenes - failed,
               probe_name == "mujoco" ? "the probe's corrected scene" : "oracle correction of each object alone");
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
    // Physics metrics (MuJoCo): records pooled over the scenes; peak energy: mean of the scene peaks.
    if (probe_name == "mujoco") {
      std::vector<SettleRecord> before, after;
      double peak_before = 0, peak_after = 0;
      int scenes_ok = 0;
      for (int k = 0; k < num_scenes; ++k) {
        if (!errors[k].empty()) continue;
        ++scenes_ok;
        before.insert(before.end(), phys_before[k].objects.begin(), phys_before[k].objects.end());
        after.insert(after.end(), phys_after[k].objects.begin(), phys_after[k].objects.end());
        peak_before += phys_before[k].scene_peak_energy, peak_after += phys_after[k].scene_peak_energy;
      }
      const PhysicsMetrics mb = physics_metrics(before), ma = physics_metrics(after);
      fmt::print("Physics after a {:.0f} s settle (pooled objects; before: as read, after: probe output)\n", metrics_time);
      fmt::print("stability (%, free, <5 cm)      {:8.1f} {:8.1f}   (n = {} / {})\n", mb.stability, ma.stability,
                 mb.stability_count, ma.stability_count);
      fmt::print("penetration ratio (%, >2 mm)    {:8.1f} {:8.1f}\n", mb.penetration_ratio, ma.penetration_ratio);
      fmt::print("initially penetrating (%)       {:8.1f} {:8.1f}\n", mb.initial_penetration_ratio,
                 ma.initial_penetration_ratio);
      fmt::print("mean displacement (mm)          {:8.2f} {:8.2f}   (n = {} / {})\n", 1000 * mb.mean_displacement,
                 1000 * ma.mean_displacement, mb.evaluated_count, ma.evaluated_count);
      fmt::print("peak energy (J, mean of scenes) {:8.4f} {:8.4f}\n", scenes_ok ? peak_before / scenes_ok : 0.0,
                 scenes_ok ? peak_after / scenes_ok : 0.0);
      fmt::print("physics-disabled objects        {:8d} {:8d}\n", mb.disabled_count, ma.disabled_count);
      // The paper's table: overlap after the settle (strict variants zero penetrating/unstable objects).
      auto hmean = [&](const std::vector<HeadlineMetrics>& h, auto get) {
        double sum = 0;
        int c = 0;
        for (int k = 0; k < num_scenes; ++k)
          if (errors[k].empty() && h[k].computed) sum += get(h[k]), ++c;
        return c ? sum / c : 0.0;
      };
      fmt::print("\nHeadline metrics after a {:.0f} s settle (mean over scenes; before: input settled the same way)\n",
                 metrics_time);
      fmt::print("{:<32} {:>8} {:>8}\n", "metric", "before", "after");
      auto hrow = [&](const char* name, auto get) {
        fmt::print("{:<32} {:8.4f} {:8.4f}\n", name, hmean(head_before, get), hmean(head_after, get));
      };
      hrow("ABO (2D)", [](const HeadlineMetrics& h) { return h.mask.abo; });
      hrow("ABO_fh/fo (2D, strict)", [](const HeadlineMetrics& h) { return h.mask.abo_fhfo(); });
      hrow("IoU (2D)", [](const HeadlineMetrics& h) { return h.mask.iou; });
      hrow("IoU_fh/fo (2D, strict)", [](const HeadlineMetrics& h) { return h.mask.iou_fhfo(); });
      hrow("3D ABO (AABB)", [](const HeadlineMetrics& h) { return h.box.abo; });
      hrow("3D ABO_fh/fo", [](const HeadlineMetrics& h) { return h.box.abo_fhfo(); });
      hrow("3D IoU (AABB)", [](const HeadlineMetrics& h) { return h.box.iou; });
      hrow("3D IoU_fh/fo", [](const HeadlineMetrics& h) { return h.box.iou_fhfo(); });
      hrow("stability (%)", [](const HeadlineMetrics& h) { return h.physics.stability; });
      hrow("penetration ratio (%)", [](const HeadlineMetrics& h) { return h.physics.penetration_ratio; });
      hrow("D_mean (mm)", [](const HeadlineMetrics& h) { return 1000 * h.physics.mean_displacement; });
      hrow("E_pk (J)", [](const HeadlineMetrics& h) { return h.physics.peak_energy; });
    }
    fmt::print("resample branch stand-in: {}\n", proxy_name);
    if (probe_name == "mujoco")
      fmt::print("probe: MuJoCo run_probe; physics-disabled objects: {} (scored at their input pose, invalid), "
                 "reverted in the final settle: {} (scored at their pre-settle pose)\n",
                 disabled.load(), reverted.load());
    else
      fmt::print("probe: oracle drop to the known support (physics metrics: --probe mujoco)\n");
    if (failed) fmt::print("{} scene(s) failed (see warnings)\n", failed);
    return failed == num_scenes ? 1 : 0;
  });
}
