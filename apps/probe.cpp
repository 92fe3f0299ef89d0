// probe: runs the physics-in-the-loop probe on one or many scene files (docs/scene_format.md) and
// writes the corrected scene, its meshes, a standalone MJCF scene.xml, report.json and pictures per
// scene. The physics and metric settings come from a typed config (configs/probe.yaml, --set).
#include <fmt/format.h>

#include <cstdint>
#include <cstdlib>
#include <memory>
#include <mutex>

#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/probe_batch.h"
#include "pipeline/resample/default_model.h"
#include "pipeline/resample/probe_resampler.h"

int main(int argc, char** argv) {
  CLI::App app{"Physics probe: penetration resolution, gravity diagnostics, stretch-or-resample decision, final "
               "settle and the paper's metrics of a reconstructed scene (MuJoCo)"};
  std::string config_path, scene_path, out_dir, cache_dir;
  std::vector<std::string> scenes;
  int threads = 1;
  bool no_coacd = false, quiet = false, overwrite = false;
  app.add_option("--config", config_path, "probe config (YAML), e.g. configs/probe.yaml (default: built-in, listed below)");
  app.add_option("--scene", scene_path, "scene file (JSON)");
  app.add_option("--scenes", scenes, "several scene files (outputs go to OUT/<file stem>, OUT/<folder>_<stem> where stems repeat)");
  app.add_option("--out", out_dir, "output directory")->required();
  app.add_flag("--overwrite", overwrite, "replace an existing output directory (else refused)");
  app.add_option("--threads", threads, "scenes processed in parallel")->check(CLI::PositiveNumber)->capture_default_str();
  app.add_option("--cache-dir", cache_dir, "collision hull cache (= --set collision.cache_dir=DIR)");
  app.add_flag("--no-coacd", no_coacd, "one convex hull per mesh (= --set collision.use_coacd=false)");
  app.add_flag("--quiet", quiet, "no per-object progress lines");
  // In-process resampling (SAM 3D Stage 1 + optional LoRA adapter), loaded once for every scene.
  simu::resample::ResamplerConfig rcfg;
  bool resample = false;
  uint64_t seed = 0;
  std::string preprocess_preset;  // "" = the model's
  app.add_flag("--resample", resample, "resample objects with rho >= threshold in-process (else write the hand-off)");
  app.add_option("--generator-config", rcfg.generator_config, "Stage-1 generator config")->capture_default_str();
  app.add_option("--generator-weights", rcfg.generator_weights, "generator safetensors (checkpoints/README.md)");
  app.add_option("--decoder-config", rcfg.decoder_config, "sparse-structure decoder config")->capture_default_str();
  app.add_option("--decoder-weights", rcfg.decoder_weights, "decoder safetensors");
  app.add_option("--embedder-config", rcfg.embedder_config, "condition embedder config");
  app.add_option("--embedder-weights", rcfg.embedder_weights, "condition embedder safetensors");
  app.add_option("--adapter", rcfg.adapter_dir, "PEFT LoRA adapter directory (default with the shipped miniature: "
                                              "its FM-DPO resampling adapter)");
  bool base_resampling = false;
  app.add_flag("--base-resampling", base_resampling,
               "with the shipped miniature: resample with the base model, not its FM-DPO adapter");
  app.add_option("--num-samples", rcfg.num_samples, "shapes drawn per object")->capture_default_str();
  app.add_option("--steps", rcfg.steps, "Stage-1 sampling steps (official inference: 25)")->capture_default_str();
  app.add_option("--precision", rcfg.precision, "fp16 | bf16 | fp32 | auto (fp16 on CUDA as released, fp32 on CPU)")
      ->capture_default_str();
  app.add_flag("--random-weights", rcfg.random_weights,
               "allow missing --*-weights: random init (torch seed 0) with a RANDOM WEIGHTS banner (demos, benchmarks)");
  app.add_option("--device", rcfg.device, "auto | cpu | cuda | cuda:N")->capture_default_str();
  app.add_option("--seed", seed, "sampling seed")->capture_default_str();
  app.add_option("--preprocess", preprocess_preset,
                 "Stage-1 preprocessing: released (the released pipeline.yaml) | default (data/preprocess.h) | "
                 "FILE.yaml; empty = the model's (the shipped miniature's own sizes, else released)");
  simu::cli::CommonOptions common;
  app.footer(simu::physics::probe_config_help());
  return simu::cli::run(app, argc, argv, common, [&] {
    if (!scene_path.empty()) scenes.insert(scenes.begin(), scene_path);
    if (scenes.empty()) simu::fail_hint("pass --scene FILE or --scenes A B ...", "no scene given");
    std::vector<std::string> sets = common.sets;
    if (no_coacd) sets.push_back("collision.use_coacd=false");
    if (!cache_dir.empty()) sets.push_back("collision.cache_dir=" + cache_dir);
    auto cfg = simu::physics::ProbeConfig::load(config_path, sets);
    cfg.overwrite = overwrite;
    if (cfg.collision.cache_dir.empty()) {
      if (const char* env = std::getenv("SIMU_HULL_CACHE")) cfg.collision.cache_dir = env;
      else if (const char* home = std::getenv("HOME")) cfg.collision.cache_dir = std::string(home) + "/.cache/simuscene/hulls";
    }
    std::unique_ptr<simu::resample::Resampler> resampler;
    simu::data::PreprocessConfig preprocess;
    if (resample) {
      // No weights at all: the shipped miniature (pipeline/resample/default_model.h), unless --random-weights.
      rcfg.shipped_resample_adapter = !base_resampling;
      simu::resample::apply_shipped_model(rcfg);
      preprocess = simu::resample::preprocess_choice(preprocess_preset, rcfg);
      if (rcfg.embedder_config.empty())
        simu::fail_hint("pass --embedder-config (and --embedder-weights)", "--resample needs the condition embedder");
      resampler = std::make_unique<simu::resample::Resampler>(rcfg);
      simu::log::info("resampler loaded on {} ({}){}", resampler->device().str(),
                      simu::models::precision_name(resampler->precision()),
                      resampler->has_adapter() ? " with adapter " + rcfg.adapter_dir : "");
      if (!resampler->random_weights_banner().empty())
        fmt::print(stderr, "\n*** {} ***\n\n", resampler->random_weights_banner());
    }
    std::mutex model_mu;  // one model, scenes in threads: resampling calls take turns
    simu::physics::ResampleFactory factory;
    if (resampler) {
      factory = [&](const simu::physics::Scene& scene) -> simu::physics::ResampleFn {
        simu::resample::ProbeResamplerOptions ropt;
        ropt.seed = seed;
        ropt.preprocess = preprocess;
        auto inner = simu::resample::make_probe_resample_fn(*resampler, scene, ropt);
        return [inner, &model_mu](const std::vector<simu::physics::ProbeResampleRequest>& rq) {
          std::lock_guard<std::mutex> lock(model_mu);
          return inner(rq);
        };
      };
    }
    simu::physics::ProbeBatchOptions opt;
    opt.threads = threads;
    opt.quiet = quiet;
    return simu::physics::run_probe_batch(scenes, out_dir, cfg, factory, opt) > 0 ? 1 : 0;
  });
}
