// probe: runs the physics-in-the-loop probe on one or many scene files (docs/scene_format.md) and
// writes the corrected scene, its meshes, a standalone MJCF scene.xml and report.json per scene.
#include <fmt/format.h>

#include <atomic>
#include <memory>
#include <cstdlib>
#include <filesystem>
#include <mutex>
#include <thread>

#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "pipeline/probe.h"
#include "pipeline/probe_resampler.h"

namespace {

// One line per corrected object: branch and what changed (report.json holds the details).
void print_changes(const simu::pipeline::ProbeResult& r) {
  using namespace simu::pipeline;
  for (size_t i = 0; i < r.diagnostics.size(); ++i) {
    const auto& d = r.diagnostics[i];
    if (d.branch != ProbeBranch::Resample && d.branch != ProbeBranch::Stretch) continue;
    const auto& a = d.obb_pre.extents;
    const auto& b = d.obb_final.extents;
    std::string what = to_string(d.branch);
    if (d.branch == ProbeBranch::Resample) {
      what += d.resampled ? " -> replaced by the decoded mesh" : " -> NOT replaced (" + d.message + ")";
      if (d.chosen_candidate >= 0) {
        what += fmt::format(", best of {} candidates: #{}", d.candidates.size(), d.chosen_candidate);
        for (size_t k = 0; k < d.candidates.size(); ++k)
          what += d.candidates[k].ok ? fmt::format(" [{}: moved {:.3f} m]", k, d.candidates[k].displacement)
                                     : fmt::format(" [{}: failed]", k);
      }
    }
    fmt::print("  {}: {}; OBB extents {:.3f} {:.3f} {:.3f} -> {:.3f} {:.3f} {:.3f} m, centre moved {:.3f} m, "
               "final settle {:.3f} m{}\n",
               r.scene.objects[i].id, what, a.x(), a.y(), a.z(), b.x(), b.y(), b.z(),
               (d.obb_final.center - d.obb_pre.center).norm(), d.settle_displacement, d.reverted ? " (reverted)" : "");
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Physics probe: penetration resolution, gravity diagnostics, stretch-or-resample decision and final "
               "settle of a reconstructed scene (MuJoCo)"};
  std::string scene_path, out_dir;
  std::vector<std::string> scenes;
  int threads = 1;
  double rho = 0.15, settle = 2.0, bound = 0.25;
  bool no_coacd = false, quiet = false;
  std::string cache_dir;
  app.add_option("--scene", scene_path, "scene file (JSON)");
  app.add_option("--scenes", scenes, "several scene files (outputs go to OUT/<file stem>/)");
  app.add_option("--out", out_dir, "output directory")->required();
  app.add_option("--threads", threads, "scenes processed in parallel")->check(CLI::PositiveNumber);
  app.add_option("--rho-threshold", rho, "rho >= this selects resampling (paper: 0.15)");
  app.add_option("--settle-time", settle, "final joint settle T_settle (s)");
  app.add_option("--divergence-bound", bound, "objects moving more in the final settle are reverted (m)");
  app.add_option("--cache-dir", cache_dir, "collision hull cache (default: $SIMU_HULL_CACHE or ~/.cache/simuscene/hulls)");
  app.add_flag("--no-coacd", no_coacd, "one convex hull per mesh instead of CoACD's decomposition");
  app.add_flag("--quiet", quiet, "no per-object progress lines");
  // In-process resampling (SAM 3D Stage 1 + optional LoRA adapter), loaded once for every scene.
  simu::pipeline::ResamplerConfig rcfg;
  bool resample = false;
  uint64_t seed = 0;
  std::string preprocess_preset = "released";
  app.add_flag("--resample", resample, "resample objects with rho >= threshold in-process (else write the hand-off)");
  app.add_option("--generator-config", rcfg.generator_config, "Stage-1 generator config")->capture_default_str();
  app.add_option("--generator-weights", rcfg.generator_weights, "generator safetensors (checkpoints/README.md)");
  app.add_option("--decoder-config", rcfg.decoder_config, "sparse-structure decoder config")->capture_default_str();
  app.add_option("--decoder-weights", rcfg.decoder_weights, "decoder safetensors");
  app.add_option("--embedder-config", rcfg.embedder_config, "condition embedder config");
  app.add_option("--embedder-weights", rcfg.embedder_weights, "condition embedder safetensors");
  app.add_option("--adapter", rcfg.adapter_dir, "PEFT LoRA adapter directory");
  app.add_option("--num-samples", rcfg.num_samples, "shapes drawn per object")->capture_default_str();
  app.add_option("--steps", rcfg.steps, "Stage-1 sampling steps (official inference: 25)")->capture_default_str();
  app.add_option("--precision", rcfg.precision, "fp16 | bf16 | fp32 | auto (fp16 on CUDA as released, fp32 on CPU)")
      ->capture_default_str();
  app.add_flag("--random-weights", rcfg.random_weights,
               "allow missing --*-weights: random init with a RANDOM WEIGHTS banner (demos, benchmarks)");
  app.add_option("--device", rcfg.device, "auto | cpu | cuda | cuda:N")->capture_default_str();
  app.add_option("--seed", seed, "sampling seed")->capture_default_str();
  app.add_option("--preprocess", preprocess_preset,
                 "Stage-1 preprocessing preset: released (the released pipeline.yaml) | default (data/preprocess.h)")
      ->capture_default_str()
      ->check(CLI::IsMember({"released", "default"}));
  simu::cli::CommonOptions common;
  simu::cli::add_common_options(app, common);
  return simu::cli::run(app, argc, argv, [&] {
    simu::cli::apply_common_options(common);
    if (!scene_path.empty()) scenes.insert(scenes.begin(), scene_path);
    if (scenes.empty()) simu::fail_hint("pass --scene FILE or --scenes A B ...", "no scene given");
    simu::pipeline::ProbeConfig cfg;
    cfg.rho_threshold = rho;
    cfg.final_settle_time = settle;
    cfg.divergence_bound = bound;
    cfg.collision.use_coacd = !no_coacd;
    if (cache_dir.empty()) {
      if (const char* env = std::getenv("SIMU_HULL_CACHE")) cache_dir = env;
      else if (const char* home = std::getenv("HOME")) cache_dir = std::string(home) + "/.cache/simuscene/hulls";
    }
    cfg.collision.cache_dir = cache_dir;
    std::unique_ptr<simu::pipeline::Resampler> resampler;
    if (resample) {
      if (rcfg.embedder_config.empty())
        simu::fail_hint("pass --embedder-config (and --embedder-weights)", "--resample needs the condition embedder");
      resampler = std::make_unique<simu::pipeline::Resampler>(rcfg);
      simu::log::info("resampler loaded on {} ({}){}", resampler->device().str(),
                      simu::models::precision_name(resampler->precision()),
                      resampler->has_adapter() ? " with adapter " + rcfg.adapter_dir : "");
      if (!resampler->random_weights_banner().empty())
        fmt::print(stderr, "\n*** {} ***\n\n", resampler->random_weights_banner());
    }
    std::mutex model_mu;  // one model, scenes in threads: resampling calls take turns
    const bool many = scenes.size() > 1;
    std::mutex print_mu;
    std::atomic<size_t> next{0};
    std::atomic<int> failed{0};
    // Each worker takes the next scene; a failing scene is reported and the others go on.
    auto worker = [&] {
      for (size_t k = next++; k < scenes.size(); k = next++) {
        const std::string& path = scenes[k];
        const std::string out = many ? out_dir + "/" + std::filesystem::path(path).stem().string() : out_dir;
        try {
          const auto scene = simu::pipeline::load_scene(path);
          auto progress = [&](int done, int total, const std::string& id, const std::string& status) {
            if (quiet) return;
            std::lock_guard<std::mutex> lock(print_mu);
            fmt::print("{}[{}/{}] {}: {}\n", many ? path + " " : "", done, total, id, status);
          };
          simu::pipeline::ResampleFn fn;
          if (resampler) {
            simu::pipeline::ProbeResamplerOptions ropt;
            ropt.seed = seed;
            ropt.preprocess = simu::data::PreprocessConfig::preset_named(preprocess_preset);
            auto inner = simu::pipeline::make_probe_resample_fn(*resampler, scene, ropt);
            fn = [inner, &model_mu](const std::vector<simu::pipeline::ProbeResampleRequest>& rq) {
              std::lock_guard<std::mutex> lock(model_mu);
              return inner(rq);
            };
          }
          const auto r = simu::pipeline::run_probe(scene, cfg, out, fn, progress);
          int flagged = 0;
          for (const auto& d : r.diagnostics) flagged += d.flags.empty() ? 0 : 1;
          std::lock_guard<std::mutex> lock(print_mu);
          fmt::print("{}: {} objects ({} flagged), probe {:.2f} s, final {:.2f} s -> {}\n", path, scene.objects.size(),
                     flagged, r.seconds_probe, r.seconds_final, out);
          print_changes(r);
        } catch (const std::exception& e) {
          ++failed;
          std::lock_guard<std::mutex> lock(print_mu);
          simu::log::error("{}: {}", path, e.what());
        }
      }
    };
    std::vector<std::thread> pool;
    const int nt = std::min<int>(threads, static_cast<int>(scenes.size()));
    for (int t = 0; t < nt; ++t) pool.emplace_back(worker);
    for (auto& t : pool) t.join();
    return failed > 0 ? 1 : 0;
  });
}
