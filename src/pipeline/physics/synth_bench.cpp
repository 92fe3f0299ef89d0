#include "pipeline/physics/synth_bench.h"

#include <unistd.h>

#include <fmt/format.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <filesystem>
#include <iterator>
#include <map>
#include <mutex>

#include "common/error.h"
#include "common/log.h"
#include "common/parallel.h"
#include "common/timing.h"

namespace simu::physics {

const char* resample_proxy_name(ResampleProxy p) {
  switch (p) {
    case ResampleProxy::Stretch: return "stretch";
    case ResampleProxy::Drop: return "drop";
    case ResampleProxy::Keep: return "keep";
  }
  return "?";
}

SynthBenchResult run_synth_bench(const SynthBenchOptions& o) {
  std::atomic<int> disabled{0}, reverted{0};
  int num_scenes = o.num_scenes;
  // Written scenes to evaluate (--from), in name order.
  std::vector<std::string> from_scenes;
  if (!o.from_dir.empty()) {
    SIMU_CHECK(std::filesystem::is_directory(o.from_dir), "--from: {} is not a folder", o.from_dir);
    for (const auto& e : std::filesystem::directory_iterator(o.from_dir))
      if (std::filesystem::exists(e.path() / "scene.json")) from_scenes.push_back((e.path() / "scene.json").string());
    std::sort(from_scenes.begin(), from_scenes.end());
    SIMU_CHECK(!from_scenes.empty(), "--from: no */scene.json under {}", o.from_dir);
    num_scenes = static_cast<int>(from_scenes.size());
  }
  SynthBenchResult res;
  res.num_scenes = num_scenes;
  res.physics_before.resize(num_scenes);
  res.physics_after.resize(num_scenes);
  res.headline_before.resize(num_scenes);
  res.headline_after.resize(num_scenes);
  // Evaluate the scenes (in parallel), collecting per-scene results in order.
  res.scenes.resize(num_scenes);
  res.errors.resize(num_scenes);
  std::atomic<int> done{0};
  std::mutex print_mutex;
  const auto t0 = simu::Clock::now();
  simu::parallel_for_each(num_scenes, o.threads, [&](int64_t k) {
    try {
      const std::string name = fmt::format("synth_{:04d}", k);
      const bool from = !from_scenes.empty();
      const SyntheticScene s = from ? load_synthetic_scene(from_scenes[k]) : generate_scene(o.synthetic, o.seed + k, name);
      std::string dir = o.write_dir.empty() ? "" : (std::filesystem::path(o.write_dir) / name).string();
      if (o.mujoco) {
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
        pc.rho_threshold = o.correction.resample_threshold;
        pc.metrics_settle_time = o.metrics_time;
        const Scene input = load_scene(scene_file);
        // Before: the reconstruction as read, settled without any correction (run_probe's
        // evaluate_input). After: the probe's corrected scene (settled poses, corrected scales and
        // meshes; the resample branch through the proxy, or left where the diagnostic put it with
        // "drop"), and the evaluation settle that starts from it.
        pc.evaluate_input = true;
        const ResampleFn resampler = o.proxy == ResampleProxy::Stretch ? stretch_resampler(s, o.correction) : nullptr;
        const ProbeResult pr = run_probe(input, pc, "", resampler);
        res.physics_before[k] = pr.input_evaluation;
        res.physics_after[k] = pr.evaluation;
        res.headline_before[k] = pr.before;
        res.headline_after[k] = pr.after;
        for (const Diagnostics& d : pr.diagnostics) {
          disabled += d.physics_disabled;
          reverted += d.reverted;
        }
        res.scenes[k] = evaluate_probe_output(s, pr);
      } else {
        if (!dir.empty()) write_scene_dir(s, dir);
        res.scenes[k] = evaluate_scene(s, o.correction, {}, o.proxy);
      }
    } catch (const std::exception& e) {
      res.errors[k] = e.what();
    }
    std::lock_guard<std::mutex> lock(print_mutex);
    const int d = ++done;
    const double el = simu::seconds_since(t0);
    if (d == num_scenes || d % 10 == 0)
      fmt::print(stderr, "[{}/{}] scenes evaluated, {:.1f} s\n", d, num_scenes, el);
  });
  res.disabled = disabled.load();
  res.reverted = reverted.load();
  for (int k = 0; k < num_scenes; ++k)
    if (!res.errors[k].empty()) simu::log::warn("scene {}: {}", k, res.errors[k]);
  return res;
}

namespace {

using Out = std::back_insert_iterator<std::string>;

// Decision accuracy per injected error type; returns the free objects counted.
int decision_rows(Out it, std::string& out, const SynthBenchOptions& o, const SynthBenchResult& r, double* gap_before,
                  double* gap_after) {
  std::map<std::string, std::array<int, 3>> per;  // error -> {n, correct, resampled}
  int n = 0, correct = 0, undecided = 0;
  for (int k = 0; k < r.num_scenes; ++k) {
    if (!r.errors[k].empty()) continue;
    for (const ObjectOutcome& ob : r.scenes[k].objects) {
      auto& a = per[to_string(ob.error)];
      ++a[0], ++n;
      const bool right = ob.decided && ob.got == ob.expected;
      a[1] += right, correct += right;
      undecided += !ob.decided;
      a[2] += ob.got == Branch::Resample;
      *gap_before += ob.support_gap_before, *gap_after += ob.support_gap_after;
    }
  }
  fmt::format_to(it, "Decision (rho >= {:.2f} -> resample) vs injected error; expected: bottom_cut -> resample, others -> stretch\n",
                 o.correction.resample_threshold);
  fmt::format_to(it, "{:<12} {:>6} {:>9} {:>10}\n", "error", "n", "accuracy", "resampled");
  for (const auto& [e, a] : per)
    fmt::format_to(it, "{:<12} {:>6} {:>8.1f}% {:>9.1f}%\n", e, a[0], a[0] ? 100.0 * a[1] / a[0] : 0.0,
                   a[0] ? 100.0 * a[2] / a[0] : 0.0);
  fmt::format_to(it, "{:<12} {:>6} {:>8.1f}%   ({} / {} correct", "all", n, n ? 100.0 * correct / n : 0.0, correct, n);
  out += undecided ? fmt::format("; {} without a decision, counted wrong)\n", undecided) : std::string(")\n");
  return n;
}

// Mean overlap metrics before / after over the scenes that ran.
void overlap_rows(Out it, const SynthBenchOptions& o, const SynthBenchResult& r, int n, double gap_before,
                  double gap_after) {
  int ok = 0;
  for (const auto& e : r.errors) ok += e.empty();
  auto mean = [&](auto get) {
    double s = 0;
    int c = 0;
    for (int k = 0; k < r.num_scenes; ++k)
      if (r.errors[k].empty()) s += get(r.scenes[k]), ++c;
    return c ? s / c : 0.0;
  };
  fmt::format_to(it, "\nMetric (mean over {} scenes)       before    after   (before: input; after: {})\n", ok,
                 o.mujoco ? "the probe's corrected scene" : "oracle correction of each object alone");
  fmt::format_to(it, "2D IoU                          {:8.4f} {:8.4f}\n", mean([](auto& s) { return s.mask_before.iou; }),
                 mean([](auto& s) { return s.mask_after.iou; }));
  fmt::format_to(it, "2D ABO                          {:8.4f} {:8.4f}\n", mean([](auto& s) { return s.mask_before.abo; }),
                 mean([](auto& s) { return s.mask_after.abo; }));
  fmt::format_to(it, "3D AABB IoU                     {:8.4f} {:8.4f}\n", mean([](auto& s) { return s.box_before.iou; }),
                 mean([](auto& s) { return s.box_after.iou; }));
  fmt::format_to(it, "3D AABB ABO                     {:8.4f} {:8.4f}\n", mean([](auto& s) { return s.box_before.abo; }),
                 mean([](auto& s) { return s.box_after.abo; }));
  fmt::format_to(it, "support gap (mm, free objects)  {:8.2f} {:8.2f}\n", n ? 1000 * gap_before / n : 0.0,
                 n ? 1000 * gap_after / n : 0.0);
}

// Physics metrics (MuJoCo): records pooled over the scenes; peak energy: mean of the scene peaks.
void physics_rows(Out it, const SynthBenchOptions& o, const SynthBenchResult& r) {
  std::vector<SettleRecord> before, after;
  double peak_before = 0, peak_after = 0;
  int scenes_ok = 0;
  for (int k = 0; k < r.num_scenes; ++k) {
    if (!r.errors[k].empty()) continue;
    ++scenes_ok;
    before.insert(before.end(), r.physics_before[k].objects.begin(), r.physics_before[k].objects.end());
    after.insert(after.end(), r.physics_after[k].objects.begin(), r.physics_after[k].objects.end());
    peak_before += r.physics_before[k].scene_peak_energy, peak_after += r.physics_after[k].scene_peak_energy;
  }
  const PhysicsMetrics mb = physics_metrics(before), ma = physics_metrics(after);
  fmt::format_to(it, "Physics after a {:.0f} s settle (pooled objects; before: as read, after: probe output)\n", o.metrics_time);
  fmt::format_to(it, "stability (%, free, <5 cm)      {:8.1f} {:8.1f}   (n = {} / {})\n", mb.stability, ma.stability,
                 mb.stability_count, ma.stability_count);
  fmt::format_to(it, "penetration ratio (%, >2 mm)    {:8.1f} {:8.1f}\n", mb.penetration_ratio, ma.penetration_ratio);
  fmt::format_to(it, "initially penetrating (%)       {:8.1f} {:8.1f}\n", mb.initial_penetration_ratio,
                 ma.initial_penetration_ratio);
  fmt::format_to(it, "mean displacement (mm)          {:8.2f} {:8.2f}   (n = {} / {})\n", 1000 * mb.mean_displacement,
                 1000 * ma.mean_displacement, mb.evaluated_count, ma.evaluated_count);
  fmt::format_to(it, "peak energy (J, mean of scenes) {:8.4f} {:8.4f}\n", scenes_ok ? peak_before / scenes_ok : 0.0,
                 scenes_ok ? peak_after / scenes_ok : 0.0);
  fmt::format_to(it, "physics-disabled objects        {:8d} {:8d}\n", mb.disabled_count, ma.disabled_count);
}

// The paper's table: overlap after the settle (strict variants zero penetrating/unstable objects).
void headline_rows(Out it, const SynthBenchOptions& o, const SynthBenchResult& r) {
  auto hmean = [&](const std::vector<HeadlineMetrics>& h, auto get) {
    double sum = 0;
    int c = 0;
    for (int k = 0; k < r.num_scenes; ++k)
      if (r.errors[k].empty() && h[k].computed) sum += get(h[k]), ++c;
    return c ? sum / c : 0.0;
  };
  fmt::format_to(it, "\nHeadline metrics after a {:.0f} s settle (mean over scenes; before: input settled the same way)\n",
                 o.metrics_time);
  fmt::format_to(it, "{:<32} {:>8} {:>8}\n", "metric", "before", "after");
  auto hrow = [&](const char* name, auto get) {
    fmt::format_to(it, "{:<32} {:8.4f} {:8.4f}\n", name, hmean(r.headline_before, get), hmean(r.headline_after, get));
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

}  // namespace

std::string synth_bench_table(const SynthBenchOptions& o, const SynthBenchResult& r) {
  std::string out;
  auto it = std::back_inserter(out);
  double gap_before = 0, gap_after = 0;
  const int n = decision_rows(it, out, o, r, &gap_before, &gap_after);
  overlap_rows(it, o, r, n, gap_before, gap_after);
  if (o.mujoco) {
    physics_rows(it, o, r);
    headline_rows(it, o, r);
  }
  fmt::format_to(it, "resample branch stand-in: {}\n", resample_proxy_name(o.proxy));
  if (o.mujoco)
    fmt::format_to(it, "probe: MuJoCo run_probe; physics-disabled objects: {} (scored at their input pose, invalid), "
                   "reverted in the final settle: {} (scored at their pre-settle pose)\n",
                   r.disabled, r.reverted);
  else
    fmt::format_to(it, "probe: oracle drop to the known support (physics metrics: --probe mujoco)\n");
  return out;
}

}  // namespace simu::physics
