// reconstruct: from a photo's masks and depth to a simulation-ready scene in one process
// (docs/reconstruct.md). Lifts the objects without their own mesh with the Stage-1 port, aligns scale
// and translation to the depth, fits floor and walls (Manhattan rectification), refines tables, composes
// the pre-simulation scene (world = the OpenCV camera, gravity = -up) and runs the physics probe with
// in-process resampling. Exit 1 when any object was skipped (the others are reconstructed).
// --gt (a shape-world scene's gt.json) adds each object's world-frame IoU against the ground truth before
// and after the probe's correction to the report and prints it as a table (reconstruct/gt_compare.h).
#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <optional>
#include <memory>

#include "common/cli.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "pipeline/resample/lift.h"
#include "pipeline/resample/model_options.h"
#include "pipeline/physics/probe_batch.h"
#include "pipeline/reconstruct/gt_compare.h"
#include "pipeline/reconstruct/run.h"

int main(int argc, char** argv) {
  CLI::App app{"reconstruct: photo (image, masks + sidecar, depth + K or point map) -> aligned objects, floor and walls, "
               "tabletop refinement -> the physics probe (settle, resampling, MJCF, report, pictures)"};
  simu::reconstruct::ReconstructFiles files;
  std::string out_dir, probe_config, gt_path;
  bool overwrite = false, no_align = false, no_tabletop = false, no_probe = false, no_model = false,
       no_coacd = false;
  simu::resample::ModelOptions model;
  app.add_option("--image", files.lift.image, "RGB(A) image")->required();
  app.add_option("--masks", files.lift.masks, "one label PNG, or one PNG per object (repeatable), or a directory of PNGs")
      ->required();
  app.add_option("--mask-kind", files.lift.mask_kind, "auto | label | per-object")->capture_default_str();
  app.add_option("--objects", files.sidecar,
                 "sidecar JSON: per mask its id, label, role (object|floor|wall), dof (free|point|line), pins, base, "
                 "optional mesh + pose (bring your own lift) and refined_pose (docs/reconstruct.md)");
  auto* pm = app.add_option("--pointmap", files.lift.pointmap, "point map .npy [H, W, 3], OpenCV camera, inf/NaN invalid");
  auto* dp = app.add_option("--depth", files.lift.depth, "depth: .npy (float m | uint16 mm), .png (16-bit mm), .exr (float m)");
  pm->excludes(dp);
  app.add_option("--intrinsics", files.lift.intrinsics, "K JSON (required with --depth; fitted to --pointmap when absent)");
  app.add_option("--out", out_dir, "output directory (refused when it exists, unless --overwrite)")->required();
  app.add_flag("--overwrite", overwrite, "replace an existing output directory");
  app.add_flag("--no-align", no_align, "skip the translation-scale alignment");
  bool align_resampled = false;
  app.add_flag("--align-resampled", align_resampled,
               "not in the paper: fit each resampled candidate's scale to its object's depth (the alignment, from the "
               "target OBB's centre) instead of keeping the model's own scale");
  app.add_flag("--no-tabletop", no_tabletop, "skip the tabletop refinement");
  app.add_flag("--no-probe", no_probe, "stop after writing the pre-simulation scene (input/scene.json)");
  app.add_flag("--no-model", no_model, "load no model: every object must bring its own mesh; the probe writes the resampling hand-off");
  app.add_option("--probe-config", probe_config, "probe config YAML (configs/probe.yaml; default built-in)");
  app.add_flag("--no-coacd", no_coacd, "one convex hull per mesh in the probe");
  app.add_option("--gt", gt_path, "ground truth of a shape-world scene (world scenes' gt.json): per object the world-frame "
                 "IoU before and after the probe's correction, in the report (gt_iou) and as a table");
  simu::resample::add_model_options(app, model);
  int lift_samples = simu::resample::kFirstLiftSamples;
  app.add_option("--lift-samples", lift_samples,
                 "shapes drawn per object in the first lift; with more than one, each is aligned and the one the depth "
                 "and mask agree with most is kept (render-and-compare, docs/reconstruct.md). 0: --samples (which "
                 "sets the probe's resampling candidates)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber)
      ->group("Model");
  bool base_resampling = false;
  app.add_flag("--base-resampling", base_resampling,
               "with the shipped miniature: the probe resamples with the base model, not its FM-DPO adapter (the "
               "first lift always runs the base model)")
      ->group("Model");
  simu::cli::CommonOptions common;
  app.footer(simu::physics::probe_config_help());
  return simu::cli::run(app, argc, argv, common, [&] {
    simu::reconstruct::ReconstructOptions opt;
    std::vector<std::string> sets = common.sets;
    if (no_coacd) sets.push_back("collision.use_coacd=false");
    opt.probe = simu::physics::ProbeConfig::load(probe_config, sets);
    if (opt.probe.collision.cache_dir.empty()) {
      if (const char* env = std::getenv("SIMU_HULL_CACHE")) opt.probe.collision.cache_dir = env;
      else if (const char* home = std::getenv("HOME")) opt.probe.collision.cache_dir = std::string(home) + "/.cache/simuscene/hulls";
    }
    opt.do_align = !no_align;
    opt.align_resampled = align_resampled;
    opt.do_tabletop = !no_tabletop;
    opt.run_probe = !no_probe;
    opt.overwrite = overwrite;
    opt.lift.seed = model.seed;
    opt.lift.samples = lift_samples;
    simu::resample::check_output_dir(out_dir, overwrite);
    // The ground truth is read before any model loads (a bad file stops the run early).
    std::optional<simu::reconstruct::WorldGt> gt;
    if (!gt_path.empty()) gt = simu::reconstruct::load_world_gt(gt_path);
    // ... and gives the probe its boxes (the 3D AABB IoU / ABO of the headline metrics, camera frame).
    if (gt) opt.gt_boxes = simu::reconstruct::gt_boxes_in_camera(*gt);
    std::unique_ptr<simu::resample::Resampler> resampler;
    std::string banner;
    if (!no_model) {
      model.config.shipped_resample_adapter = !base_resampling;
      banner = simu::resample::finish_model_options(model);
      // The shipped miniature learned the shape world's canonical frame, -y up (docs/world.md), not
      // SAM 3D's +z: the lifted meshes' up (the floor fit's fallback and its check) uses it.
      if (!model.shipped_note.empty()) opt.lift_up_axis = "-y";
      if (!banner.empty()) fmt::print(stderr, "\n*** {} ***\n\n", banner);
      resampler = std::make_unique<simu::resample::Resampler>(model.config);
    }
    const auto res = simu::reconstruct::reconstruct(files, opt, resampler.get(), out_dir);
    int skipped = 0;
    for (const auto& o : res.objects) {
      if (!o.skipped.empty()) ++skipped;
      fmt::print("  {:<20} {:<7} {}{}{}\n", o.id, o.role, o.used ? "used" : "SKIPPED", o.steps.empty() ? "" : ": ",
                 fmt::join(o.steps, ", "));
      for (const auto& s : o.skipped) fmt::print("      skipped {}\n", s);
    }
    for (const auto& m : res.messages) fmt::print("  note: {}\n", m);
    fmt::print("up [{:.3f} {:.3f} {:.3f}] from {}; gravity = -up; world = the OpenCV camera\n", res.planes.up.x(),
               res.planes.up.y(), res.planes.up.z(), res.planes.up_source);
    fmt::print("seconds: {}\n-> {}/reconstruct_report.json, {}/input/scene.json{}\n", res.timings.dump(), out_dir, out_dir,
               opt.run_probe ? ", " + out_dir + "/probe/ (scene.xml, report.json)" : "");
    // Against the ground truth: the pre-simulation scene (before) and the probe's final scene (after).
    if (gt) {
      namespace sp = simu::physics;
      const std::string probe_dir = out_dir + "/probe";
      const bool probed = opt.run_probe && std::filesystem::exists(probe_dir + "/scene.json");
      const sp::Scene before = sp::load_scene(out_dir + "/input/scene.json");
      const sp::Scene after = probed ? sp::load_scene(probe_dir + "/scene.json") : sp::Scene{};
      nlohmann::json probe_report;
      if (probed) probe_report = nlohmann::json::parse(std::ifstream(probe_dir + "/report.json"));
      const auto outcomes = simu::reconstruct::probe_outcomes(probe_report);
      const auto rows = simu::reconstruct::compare_with_gt(before, after, outcomes, *gt);
      const std::string report_path = out_dir + "/reconstruct_report.json";
      nlohmann::json report = nlohmann::json::parse(std::ifstream(report_path));
      report["gt_iou"] = simu::reconstruct::gt_rows_json(rows, gt_path);
      // The same after the probe's 5 s evaluation settles: the scenes its headline metrics score.
      if (probed) {
        const auto settled = simu::reconstruct::compare_with_gt(
            simu::reconstruct::settled_scene(before, probe_report, /*input=*/true),
            simu::reconstruct::settled_scene(after, probe_report, /*input=*/false), outcomes, *gt);
        report["gt_iou_settled"] = simu::reconstruct::gt_rows_json(settled, gt_path);
        report["gt_iou_settled"]["frame"] = "as gt_iou, each scene after the probe's 5 s evaluation settle "
                                            "(report.json evaluation_input_pose / evaluation_pose)";
      }
      simu::fs::atomic_write(report_path, report.dump(2) + "\n");
      fmt::print("\nworld-frame 3D IoU against the ground truth ({}): before = lifted and aligned (input/scene.json), "
                 "after = the probe's final scene (probe/scene.json)\n{}", gt_path,
                 simu::reconstruct::format_gt_table(rows));
    }
    if (!banner.empty()) fmt::print(stderr, "{}\n", banner);
    return skipped > 0 ? 1 : 0;
  });
}
