// eval_lift: renders objects in shape-world scenes, lifts them with Stage 1 (released preprocessing,
// embedder, sampling, decoding, pose) and scores them against the ground truth in the world frame:
// voxel IoU, F-score at 1 / 2 cm, Chamfer, rotation error modulo symmetry, translation and scale errors,
// per object and per visibility bucket; with --compare-adapter, base and base + adapter on the same
// objects and noise with bootstrap intervals of the deltas (docs/eval_lift.md).
#include <fmt/format.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>

#include <unistd.h>

#include "common/cli.h"
#include "common/config.h"
#include "common/error.h"
#include "common/fs.h"
#include "pipeline/reconstruct/eval_align.h"
#include "pipeline/resample/eval_lift.h"
#include "pipeline/resample/lift.h"
#include "pipeline/resample/model_options.h"

int main(int argc, char** argv) {
  CLI::App app{"eval_lift: lift shape-world objects (or a folder of meshes placed in world scenes) and score shape "
               "and pose against the ground truth in the world frame -> OUT/summary.json, pictures"};
  simu::resample::EvalLiftOptions opt;
  std::string visible = "0-100", shard = "0/1", compare_adapter, out_dir, config_path, align = "none", select = "render-compare";
  bool overwrite = false, no_pictures = false;
  simu::resample::ModelOptions model;
  auto* world = app.add_option("--world", opt.world, "objects from the shape world: test | val | train | heldout (the "
                                                     "held-out family, placed in test scenes)")
                    ->group("Objects");
  auto* objects = app.add_option("--objects", opt.objects_dir, "a folder of OBJ / PLY / STL / GLB meshes in any units, "
                                                               "each placed at rest in a test-split world scene")
                      ->group("Objects");
  world->excludes(objects);
  app.add_option("--visible", visible, "visible fraction range LO-HI, fractions (0.4-0.7) or percent (40-70)")
      ->capture_default_str()
      ->group("Objects");
  app.add_option("--count", opt.count, "objects to evaluate (0: 20 from --world, every mesh once from --objects)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber)
      ->group("Objects");
  app.add_option("--seed", opt.seed, "scenes, point-map corruption, sampling noise and the bootstrap")
      ->capture_default_str()
      ->group("Objects");
  app.add_option("--shard", shard, "I/N: lift and score only shard I of N of the run's objects (whole scenes, dealt "
                                    "round robin; the same objects, inputs and noise as the unsharded run); merge the "
                                    "shards with scripts/merge_eval_shards.py")
      ->capture_default_str()
      ->group("Objects");
  app.add_option("--object-size", opt.object_size, "--objects: longest side in metres (0: the file's units guessed "
                                                   "among m / cm / mm / inch so it lands in 2-60 cm)")
      ->capture_default_str()
      ->group("Objects");
  app.add_option("--config", config_path, "YAML with `scene:` (world::SceneConfig) and `corruption:` "
                                          "(world::CorruptionConfig) keys; --set edits it")
      ->group("Objects");
  app.add_option("--depth", opt.depth, "point map fed to the lift: clean | corrupted | both (side by side)")
      ->capture_default_str()
      ->group("Evaluation");
  app.add_option("--compare-adapter", compare_adapter, "also lift with base + this PEFT adapter on the same objects and "
                                                       "noise; deltas with 95% bootstrap intervals")
      ->group("Evaluation");
  app.add_option("--bootstrap", opt.bootstrap_resamples, "bootstrap resamples of the deltas")
      ->capture_default_str()
      ->check(CLI::PositiveNumber)
      ->group("Evaluation");
  app.add_option("--surface-samples", opt.metrics.samples, "surface points per mesh for F-score and Chamfer")
      ->capture_default_str()
      ->check(CLI::PositiveNumber)
      ->group("Evaluation");
  app.add_option("--out", out_dir, "output folder: summary.json, pictures/ (refused when it exists, unless --overwrite)")
      ->required()
      ->group("Evaluation");
  app.add_flag("--overwrite", overwrite, "replace an existing output folder")->group("Evaluation");
  app.add_option("--threads", opt.threads, "metric and alignment threads (0: every core; the lift runs on torch's "
                                          "threads, OMP_NUM_THREADS)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber)
      ->group("Evaluation");
  app.add_flag("--no-pictures", no_pictures, "skip the per-object pictures")->group("Evaluation");
  app.add_flag("--amodal-crop", opt.amodal_crop,
               "crop from the object's amodal mask (the ground truth's: an ideal OBB-guided crop, the resampling input "
               "the FM-DPO pairs are made for) instead of its modal mask")
      ->group("Evaluation");
  app.add_option("--align", align, "pose refinement before scoring: none (the lift's pose) | simuscene (the "
                                    "translation-scale alignment to the point map that `reconstruct` runs, "
                                    "docs/reconstruct.md) | icp (simuscene, then the rotation refined: turns about "
                                    "the vertical axis, trimmed ICP to the masked points, the best render-and-compare "
                                    "score kept; docs/eval_lift.md)")
      ->capture_default_str()
      ->check(CLI::IsMember({"none", "simuscene", "icp"}))
      ->group("Evaluation");
  app.add_option("--select", select, "which of an object's --samples is scored: first (the first usable) | "
                                      "render-compare (each refined by --align, the lowest render-and-compare score "
                                      "against the point map and the mask kept, as reconstruct's first lift does; "
                                      "docs/eval_lift.md)")
      ->capture_default_str()
      ->check(CLI::IsMember({"first", "render-compare"}))
      ->group("Evaluation");
  // Testing only (hidden): each prediction replaced by its ground truth, no model run; every metric is
  // then at its ideal value (the CI check of the metric path).
  app.add_flag("--gt-as-prediction", opt.gt_as_prediction, "")->group("");
  app.add_option("--shape-grid", opt.shape_grid,
                 "grid side of the shape IoU: 0 = each model's own decoder grid; a divisor S of the decoder grid "
                 "R pools the sample's voxels to S^3 (any occupied fine voxel marks its coarse one) against the "
                 "truth at S^3, so that models of different R compare on one grid (docs/eval_lift.md)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber)
      ->group("Evaluation");
  app.add_option("--oracle", opt.oracle, "diagnostic upper bounds, not model results: none | grid (no model runs: "
                                         "the truth's occupancy at the model's grid side, meshed as decoder outputs "
                                         "are, at the true pose) | pose (the model's shape at the true pose); "
                                         "--align still runs after it (docs/eval_lift.md)")
      ->default_str("none")
      ->check(CLI::IsMember({"none", "grid", "pose"}))
      ->group("Evaluation");
  simu::resample::ModelOptionFlags flags;
  flags.seed = false;  // --seed above drives the noise too
  // As reconstruct's first lift: kFirstLiftSamples shapes per object, the best kept (--select).
  model.config.num_samples = simu::resample::kFirstLiftSamples;
  simu::resample::add_model_options(app, model, flags);
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    std::tie(opt.visible_lo, opt.visible_hi) = simu::resample::parse_visible_range(visible);
    std::tie(opt.shard_index, opt.shard_count) = simu::resample::parse_shard(shard);
    opt.pictures = !no_pictures;
    opt.refine_name = align;
    if (align == "simuscene") opt.refine = simu::reconstruct::alignment_refiner({});
    if (align == "icp") opt.refine = simu::reconstruct::icp_refiner({}, {});
    opt.select_name = select;
    if (select == "render-compare") opt.select = simu::reconstruct::render_compare_scorer({});
    simu::resample::validate_eval_options(opt);  // before the models load
    if (!config_path.empty() || !common.sets.empty()) {
      YAML::Node node = config_path.empty() ? YAML::Node(YAML::NodeType::Map) : simu::config::load_file(config_path);
      for (const auto& s : common.sets) simu::config::apply_override(node, s, config_path.empty() ? "--set" : config_path);
      simu::config::Reader r(node, config_path.empty() ? "--set" : config_path);
      auto scene = r.child("scene");
      opt.scene = simu::world::SceneConfig::from(scene);
      auto corruption = r.child("corruption");
      opt.corruption = simu::world::CorruptionConfig::from(corruption);
      r.finish();
    }
    const auto t0 = std::chrono::steady_clock::now();
    std::string banner;
    if (!opt.gt_as_prediction) {
      banner = simu::resample::finish_model_options(model);
      if (!banner.empty()) {
        const std::string bar(std::min<size_t>(banner.size(), 100), '!');
        fmt::print(stderr, "{}\n{}\n{}\n", bar, banner, bar);
      }
    }
    if (!compare_adapter.empty())
      SIMU_CHECK(std::filesystem::is_directory(compare_adapter), "--compare-adapter {}: not a folder", compare_adapter);
    // Everything is written into a temporary folder beside --out, put in place at the end.
    simu::fs::check_overwrite(out_dir, overwrite, "--out");
    const std::string tmp = out_dir + ".tmp-" + std::to_string(::getpid());
    simu::fs::remove_tree(tmp);
    std::filesystem::create_directories(tmp);
    // The models: base (+ --adapter) and, to compare, the same with --compare-adapter.
    std::unique_ptr<simu::resample::Resampler> base, cmp;
    nlohmann::json run_info;
    if (!opt.gt_as_prediction) {
      // Modules left at random init (--random-weights) are drawn from --seed, the same for both models: runs
      // repeat, and the two models differ by the adapter only.
      torch::manual_seed(opt.seed);
      base = std::make_unique<simu::resample::Resampler>(model.config);
      if (!compare_adapter.empty()) {
        auto c = model.config;
        c.adapter_dir = compare_adapter;
        torch::manual_seed(opt.seed);
        cmp = std::make_unique<simu::resample::Resampler>(c);
      }
      simu::resample::LiftOptions lo;
      lo.seed = opt.seed;
      run_info = simu::resample::lift_run_info(*base, lo, model.precision, model.random_weights);
      if (!banner.empty()) run_info["banner"] = banner;
    }
    const auto result = simu::resample::run_eval_lift(opt, {base.get(), cmp.get()}, tmp);
    const auto summary =
        simu::resample::eval_summary(result, opt, {model.config.adapter_dir, compare_adapter}, run_info);
    simu::fs::atomic_write(tmp + "/summary.json", summary.dump(2) + "\n");
    simu::fs::replace_dir(tmp, out_dir);
    fmt::print("{}", simu::resample::format_summary_table(summary));
    int failed = 0;
    for (const auto& row : result.rows)
      if (!row.ok) {
        ++failed;
        fmt::print(stderr, "  {} ({}, {}): FAILED: {}\n", result.objects[row.object].id, row.depth, row.model, row.error);
      }
    fmt::print("\n{} object(s) in {} scene(s), {} lift(s) failed, {:.1f} s (lift {:.1f} s, metrics {:.1f} s) -> "
               "{}/summary.json\n",
               result.objects.size(), result.scenes, failed,
               std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(), result.seconds_lift,
               result.seconds_metrics, out_dir);
    if (!banner.empty()) fmt::print(stderr, "{}\n", banner);
    return 0;
  });
}
