// build_pairs: builds the FM-DPO pair cache (HDF5, docs/pair_cache.md) that train_fmdpo reads from a
// JSON-lines manifest of image pairs (occlusion-completion and clean-preservation), running the
// condition embedder and Stage-1 sampling on both sides of every pair in this process.
//   build_pairs --manifest pairs.jsonl --out pairs.h5 --embedder-config ... --generator-weights ...
#include <csignal>

#include <atomic>
#include <filesystem>

#include "common/cli.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "common/progress.h"
#include "pipeline/resample/default_model.h"
#include "pipeline/resample/pair_builder.h"

#include <nlohmann/json.hpp>

namespace {
std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop = true; }

// The summary: pairs, bytes per pair on disk, the skipped records.
void print_report(const std::string& manifest, const std::string& out, const simu::resample::PairBuildReport& report) {
  fmt::print("{}: {} pairs ({} written now, {} already there), {} bad record(s) skipped, {} records in {:.1f} s{}\n",
             out, report.cache_size, report.written, report.skipped_existing, report.issues.size(),
             report.records, report.seconds, report.interrupted ? " (interrupted: run again to continue)" : "");
  if (report.cache_size > 0) {
    const auto b = simu::data::storage_bytes(out);
    fmt::print("{}: {} bytes per pair on disk ({:.2f} MB: latents {:.0f}, condition {:.0f}, other {:.0f})\n", out,
               b.latents + b.condition + b.other, (b.latents + b.condition + b.other) / 1e6, b.latents, b.condition,
               b.other);
  }
  for (const auto& issue : report.issues)
    fmt::print("  {}:{}: {}{}\n", manifest, issue.line, issue.id.empty() ? "" : "'" + issue.id + "': ",
               issue.message);
  // The filter, per kind: judged, kept, dropped, mean IoU of both sides.
  for (auto kind : {simu::data::PairKind::OcclusionCompletion, simu::data::PairKind::CleanPreservation}) {
    int64_t n = 0, kept = 0;
    double pos = 0, neg = 0;
    for (const auto& r : report.filtered)
      if (r.kind == kind) ++n, kept += r.kept, pos += r.iou_pos, neg += r.iou_neg;
    if (n == 0) continue;
    fmt::print("filter {}: {} judged, {} kept, {} dropped (x+ not closer to the ground truth); mean IoU x+ {:.3f}, x- {:.3f}\n",
               kind == simu::data::PairKind::OcclusionCompletion ? "occlusion_completion" : "clean_preservation", n, kept,
               n - kept, pos / n, neg / n);
  }
}

// --report: the same as JSON (written atomically).
void write_report_json(const std::string& path, const std::string& manifest, const simu::resample::PairBuilderConfig& cfg,
                       const simu::resample::PairBuildReport& report) {
  nlohmann::json j = {{"manifest", manifest}, {"out", cfg.out}, {"records", report.records}, {"written", report.written},
                      {"skipped_existing", report.skipped_existing}, {"cache_size", report.cache_size},
                      {"interrupted", report.interrupted}, {"seconds", report.seconds}, {"filter_gt", cfg.filter_gt}, {"preferred", cfg.preferred},
                      {"seed", cfg.seed}};
  j["issues"] = nlohmann::json::array();
  for (const auto& i : report.issues) j["issues"].push_back({{"line", i.line}, {"id", i.id}, {"message", i.message}});
  j["filtered"] = nlohmann::json::array();
  for (const auto& r : report.filtered)
    j["filtered"].push_back({{"id", r.id},
                             {"kind", r.kind == simu::data::PairKind::OcclusionCompletion ? "occlusion_completion" : "clean_preservation"},
                             {"iou_pos", r.iou_pos}, {"iou_neg", r.iou_neg}, {"kept", r.kept}});
  simu::fs::atomic_write(path, j.dump(2) + "\n");
}
}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Build an FM-DPO pair cache from a manifest of image pairs: condition embedder + Stage-1 sampling on "
               "both sides, condition c = (I, M, I_M', D) stored as tokens or as the embedder's inputs. Manifest and layout: "
               "docs/pair_cache.md"};
  std::string manifest, dtype = "f16";
  simu::resample::PairBuilderConfig cfg;
  auto& rc = cfg.resampler;
  bool overwrite = false;
  std::string preprocess_preset;  // "" = the model's
  app.add_option("--manifest", manifest, "JSON lines, one pair per line (keys in docs/pair_cache.md)")->required();
  app.add_option("--out", cfg.out, "pair cache (.h5); an existing one is extended (resume)")->required();
  app.add_flag("--overwrite", overwrite, "replace an existing --out instead of skipping the pairs it holds");
  app.add_option("--generator-config", rc.generator_config, "Stage-1 generator config")->capture_default_str();
  app.add_option("--generator-weights", rc.generator_weights, "generator safetensors (checkpoints/README.md)");
  app.add_option("--generator-set", rc.generator_overrides, "generator config override a.b=v (repeatable)");
  app.add_option("--embedder-config", rc.embedder_config,
                 "condition embedder config (required with --generator-weights; none given: the shipped miniature)");
  app.add_option("--embedder-weights", rc.embedder_weights, "condition embedder safetensors");
  app.add_flag("--random-weights", rc.random_weights,
               "allow missing --*-weights: random init (torch seed 0) with a RANDOM WEIGHTS banner (tests, benchmarks)");
  app.add_option("--precision", rc.precision, "fp16 | bf16 | fp32 | auto (fp16 on CUDA as released, fp32 on CPU)")
      ->capture_default_str();
  app.add_option("--adapter", rc.adapter_dir, "PEFT LoRA adapter on the generator (default: the base model)");
  app.add_option("--decoder-config", rc.decoder_config, "sparse-structure decoder config (used by --filter-gt)")
      ->capture_default_str();
  app.add_option("--decoder-weights", rc.decoder_weights, "decoder safetensors (--filter-gt)");
  app.add_flag("--filter-gt", cfg.filter_gt,
               "keep a pair only when x+ is closer than x- to the record's gt_occupancy (decoded occupancy IoU; "
               "the paper's filter; world pairs writes gt_occupancy)");
  std::string preferred = "sample";
  app.add_option("--preferred", preferred,
                 "x+ of every pair: sample (the paper: Stage 1 on the preferred input) or gt-latent (the encoder's "
                 "posterior mean of the record's gt_occupancy: the ground truth's latent, labelled so in the cache's "
                 "created_by; only x- is sampled)")
      ->capture_default_str()
      ->check(CLI::IsMember({"sample", "gt-latent"}));
  app.add_option("--encoder-config", cfg.encoder_config,
                 "sparse-structure encoder config (--preferred gt-latent; default: the shipped miniature's)");
  app.add_option("--encoder-weights", cfg.encoder_weights, "encoder safetensors (--preferred gt-latent)");
  std::string report_path;
  app.add_option("--report", report_path, "also write the run's report as JSON: counts, skipped records, the filter's "
                                          "per-pair IoUs");
  app.add_option("--steps", rc.steps, "Stage-1 sampling steps (official inference: 25)")->capture_default_str();
  app.add_option("--cfg-strength", rc.cfg_strength, "classifier-free guidance strength (official inference: 7)")
      ->capture_default_str();
  app.add_option("--device", rc.device, "auto | cpu | cuda | cuda:N")->capture_default_str();
  app.add_option("--preprocess", preprocess_preset,
                 "Stage-1 preprocessing: released (the released pipeline.yaml) | default (data/preprocess.h) | "
                 "FILE.yaml; empty = the model's (the shipped miniature's own sizes, else released)");
  app.add_option("--batch", cfg.batch, "pairs per batched embedder + sampling call")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_option("--seed", cfg.seed, "noise seed (each pair's noise comes from the seed and its id)")
      ->capture_default_str();
  app.add_option("--dtype", dtype, "storage dtype of latents and condition tokens (inputs mode: latents only): f16 or f32")
      ->capture_default_str();
  app.add_option("--cond-mode", cfg.cond_mode,
                 "tokens: store the embedder's condition tokens; inputs: store its six preprocessed inputs (train_fmdpo "
                 "then runs the embedder in the step; several times smaller at the released sizes)")
      ->capture_default_str()
      ->check(CLI::IsMember({"tokens", "inputs"}));
  app.add_option("--inputs-storage", cfg.inputs_storage,
                 "inputs mode: exact (float32 images and point maps, bit-exact) or compact (uint8 images, float16 point "
                 "maps; about 3x smaller, not bit-exact)")
      ->capture_default_str()
      ->check(CLI::IsMember({"exact", "compact"}));
  app.add_option("--commit-every", cfg.commit_every, "pairs between commits of --out (0: only at the end)")
      ->capture_default_str();
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    if (dtype == "f16" || dtype == "float16")
      cfg.dtype = torch::kFloat16;
    else if (dtype == "f32" || dtype == "float32")
      cfg.dtype = torch::kFloat32;
    else
      simu::fail("--dtype must be f16 or f32, got '{}'", dtype);
    cfg.resume = !overwrite;
    // No weights at all: the shipped miniature (pipeline/resample/default_model.h), unless --random-weights.
    simu::resample::apply_shipped_model(rc);
    SIMU_CHECK(!rc.embedder_config.empty(), "build_pairs: --embedder-config is required (the pairs' conditions)");
    cfg.preprocess = simu::resample::preprocess_choice(preprocess_preset, rc);
    cfg.preferred = preferred == "gt-latent" ? "gt_latent" : "sample";
    if (cfg.preferred == "gt_latent" && cfg.encoder_config.empty() && cfg.encoder_weights.empty() &&
        rc.generator_weights.rfind(simu::resample::shipped_model_dir(), 0) == 0) {
      // The shipped miniature's own encoder (the one its Stage 1 was trained on).
      const auto m = simu::resample::ModelFolder::load(simu::resample::shipped_model_dir());
      cfg.encoder_config = m.encoder_config, cfg.encoder_weights = m.encoder_weights;
    }
    // Ctrl-C / SIGTERM: finish the current batch, commit, exit.
    std::signal(SIGINT, on_signal);
    std::signal(SIGTERM, on_signal);
    simu::Progress progress{"build_pairs", "records"};
    const auto report = simu::resample::build_pairs(manifest, cfg, std::ref(progress), &g_stop);
    print_report(manifest, cfg.out, report);
    if (!report_path.empty()) write_report_json(report_path, manifest, cfg, report);
    return report.interrupted ? 130 : 0;
  });
}
