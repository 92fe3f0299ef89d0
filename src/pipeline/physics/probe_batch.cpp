// run_probe over many scenes for the probe program (see probe_batch.h).
#include "pipeline/physics/probe_batch.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <atomic>
#include <filesystem>
#include <map>
#include <mutex>
#include <thread>

#include "common/error.h"
#include "common/log.h"
#include "common/parallel.h"

namespace simu::physics {

namespace stdfs = std::filesystem;

std::vector<std::string> probe_output_dirs(const std::vector<std::string>& scenes, const std::string& out) {
  SIMU_CHECK(!scenes.empty(), "no scene given");
  if (scenes.size() == 1) return {out};
  // The same file twice would write one folder twice: refused.
  std::map<std::string, std::string> seen;
  for (const auto& p : scenes) {
    const std::string key = stdfs::weakly_canonical(stdfs::absolute(p)).string();
    const auto it = seen.find(key);
    if (it != seen.end())
      fail_hint("give each scene once", "--scenes: {} and {} are the same file; both would write into one folder",
                it->second, p);
    seen[key] = p;
  }
  // Name = file stem, prefixed with as many parent folder names as it takes to tell the inputs apart.
  const size_t n = scenes.size();
  std::vector<std::vector<std::string>> parts(n);  // stem, parent, grandparent, ...
  for (size_t i = 0; i < n; ++i) {
    stdfs::path p = stdfs::absolute(scenes[i]).lexically_normal();
    parts[i].push_back(p.stem().string());
    for (p = p.parent_path(); !p.empty() && p != p.root_path(); p = p.parent_path()) parts[i].push_back(p.filename().string());
  }
  std::vector<size_t> depth(n, 1);
  std::vector<std::string> names(n);
  for (int round = 0; round < 64; ++round) {
    for (size_t i = 0; i < n; ++i) {
      std::string name;
      for (size_t d = std::min(depth[i], parts[i].size()); d-- > 0;) name += (name.empty() ? "" : "_") + parts[i][d];
      names[i] = name;
    }
    std::map<std::string, std::vector<size_t>> groups;
    for (size_t i = 0; i < n; ++i) groups[names[i]].push_back(i);
    bool clash = false;
    for (const auto& [name, idx] : groups)
      if (idx.size() > 1)
        for (size_t i : idx)
          if (depth[i] < parts[i].size()) ++depth[i], clash = true;
    if (!clash) break;
  }
  std::map<std::string, int> used;
  std::vector<std::string> dirs;
  for (size_t i = 0; i < n; ++i) {
    std::string name = names[i];
    if (used[name]++) name += "_" + std::to_string(i);  // still equal (e.g. links): numbered
    dirs.push_back(out + "/" + name);
  }
  return dirs;
}

std::string probe_summary(const ProbeResult& r) {
  std::string s = fmt::format("  {:<16} {:<9} {:>6} {:>12} {:>12}  {}\n", "object", "branch", "rho", "moved before",
                              "moved after", "flags");
  const bool before = r.input_evaluation.ran;
  for (size_t i = 0; i < r.diagnostics.size(); ++i) {
    const auto& d = r.diagnostics[i];
    auto moved = [](const SettleRecord& rec, bool ran) {
      return !ran || rec.physics_disabled ? std::string("-") : fmt::format("{:.1f} mm", 1000 * rec.displacement);
    };
    const std::string rho = d.branch == ProbeBranch::Disabled ? "-" : fmt::format("{:.3f}", d.diagnosis.rho);
    std::string branch = to_string(d.branch);
    s += fmt::format("  {:<16} {:<9} {:>6} {:>12} {:>12}  {}\n", r.scene.objects[i].id, branch, rho,
                     moved(i < r.input_evaluation.objects.size() ? r.input_evaluation.objects[i] : SettleRecord{}, before),
                     moved(d.evaluation, r.evaluation.ran), d.flags.empty() ? "-" : fmt::format("{}", fmt::join(d.flags, ",")));
    if (d.branch == ProbeBranch::Resample) {
      std::string what = d.resampled ? "    replaced by a resampled shape" : "    NOT replaced";
      if (!d.resampled && !d.message.empty()) what += " (" + d.message + ")";
      s += what + "\n";
      for (size_t k = 0; k < d.candidates.size(); ++k) {
        const auto& c = d.candidates[k];
        s += fmt::format("      candidate #{}: {}{}\n", k,
                         c.ok ? fmt::format("passed, moved {:.1f} mm", 1000 * c.displacement) : "failed: " + c.message,
                         int(k) == d.chosen_candidate && d.resampled ? "  <- kept" : "");
      }
    }
    if (d.branch == ProbeBranch::Stretch || d.branch == ProbeBranch::Resample) {
      const auto& a = d.diagnosis.obb_pre.extents;
      const auto& b = d.obb_final.extents;
      s += fmt::format("    OBB extents {:.3f} {:.3f} {:.3f} -> {:.3f} {:.3f} {:.3f} m\n", a.x(), a.y(), a.z(), b.x(), b.y(),
                       b.z());
    }
  }
  return s;
}

int run_probe_batch(const std::vector<std::string>& scenes, const std::string& out, const ProbeConfig& cfg,
                    const ResampleFactory& resample, const ProbeBatchOptions& options) {
  const std::vector<std::string> dirs = probe_output_dirs(scenes, out);
  // Refuse before any work when an output would be overwritten.
  if (!cfg.overwrite)
    for (const auto& d : dirs)
      if (stdfs::exists(d))
        fail_hint("pass --overwrite to replace it, or choose another --out", "output folder {} already exists", d);
  const bool many = scenes.size() > 1;
  std::mutex print_mu;
  std::atomic<int> failed{0};
  parallel_for_each(static_cast<int64_t>(scenes.size()), options.threads, [&](int64_t k) {
    const std::string& path = scenes[k];
    const std::string& dir = dirs[k];
    try {
      const Scene scene = load_scene(path);
      auto progress = [&](int done, int total, const std::string& id, const std::string& status) {
        if (options.quiet) return;
        std::lock_guard<std::mutex> lock(print_mu);
        fmt::print("{}[{}/{}] {}: {}\n", many ? path + " " : "", done, total, id, status);
      };
      const ResampleFn fn = resample ? resample(scene) : ResampleFn{};
      const ProbeResult r = run_probe(scene, cfg, dir, fn, progress);
      int flagged = 0;
      for (const auto& d : r.diagnostics) flagged += d.flags.empty() ? 0 : 1;
      std::lock_guard<std::mutex> lock(print_mu);
      fmt::print("{}: {} objects ({} flagged), probe {:.2f} s, final {:.2f} s, evaluation {:.2f} s -> {}\n", path,
                 scene.objects.size(), flagged, r.seconds_probe, r.seconds_final, r.seconds_metrics, dir);
      fmt::print("{}", probe_summary(r));
      fmt::print("{}", format_headline(r.before, r.after, cfg.metrics_settle_time));
      for (const auto& p : r.pictures) fmt::print("  picture: {}\n", p);
    } catch (const std::exception& e) {
      ++failed;
      std::lock_guard<std::mutex> lock(print_mu);
      log::error("{}: {}", path, e.what());
    }
  });
  return failed;
}

std::string probe_config_help(const ProbeConfig& defaults) {
  std::string s = "Config keys (configs/probe.yaml; override with --set key=value), default and meaning:\n";
  for (const auto& k : defaults.describe()) s += fmt::format("  {:<34} {:<12} {}\n", k.key, k.value, k.doc);
  return s;
}

}  // namespace simu::physics
