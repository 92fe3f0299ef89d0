// lift: SAM 3D Objects Stage 1 on a photo's objects (docs/lift.md). Reads the image, the masks and a
// point map or depth + K, lifts every object in one batched pass (released preprocessing, embedder,
// 25-step CFG sampling, decoder, marching cubes, pose) and writes meshes, occupancy, poses and a
// scene.json the probe reads. Exit 1 when any object failed (the others are written).
#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cstdio>

#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "data/depth_io.h"
#include "pipeline/resample/lift.h"
#include "pipeline/resample/model_options.h"

int main(int argc, char** argv) {
  CLI::App app{"lift: SAM 3D Objects Stage 1 (shape + pose) on the objects of one photo -> meshes, 64^3 occupancy, "
               "poses in SAM 3D's and the scene convention, scene.json for the probe"};
  simu::resample::LiftFiles files;
  std::string out_dir;
  bool overwrite = false;
  simu::resample::ModelOptions model;
  app.add_option("--image", files.image, "RGB(A) image")->required();
  app.add_option("--masks", files.masks,
                 "one label PNG (0 = background, k = object k), or one PNG per object (repeatable), or a directory "
                 "of PNGs")
      ->required();
  app.add_option("--mask-kind", files.mask_kind, "auto (one file = label image) | label | per-object")
      ->capture_default_str();
  auto* pm = app.add_option("--pointmap", files.pointmap, "point map .npy [H, W, 3], OpenCV camera (MoGe), inf/NaN invalid");
  auto* dp = app.add_option("--depth", files.depth, "depth: .npy (float m | uint16 mm), .png (16-bit mm), .exr (float m)");
  pm->excludes(dp);
  app.add_option("--intrinsics", files.intrinsics,
                 "K JSON: {fx, fy, cx, cy} or a 3x3 matrix (required with --depth; fitted to --pointmap when absent)");
  app.add_option("--out", out_dir, "output directory (refused when it exists, unless --overwrite)")->required();
  app.add_flag("--overwrite", overwrite, "replace an existing output directory (atomically)");
  simu::resample::add_model_options(app, model);
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    if (!common.sets.empty())
      simu::fail_hint("use the --*-config files and flags", "lift reads no config file: --set {} would be ignored",
                      common.sets.front());
    const auto t_start = std::chrono::steady_clock::now();
    // Weights first (cheap), then every input file, then the models.
    const std::string banner = simu::resample::finish_model_options(model);
    if (!banner.empty()) {
      const std::string bar(std::min<size_t>(banner.size(), 100), '!');
      fmt::print(stderr, "{}\n{}\n{}\n", bar, banner, bar);
    }
    if (!model.shipped_note.empty()) fmt::print("{}\n", model.shipped_note);
    simu::resample::check_output_dir(out_dir, overwrite);
    auto inputs = simu::resample::load_lift_inputs(files);
    fmt::print("{}: {}x{}, {} object(s)\n", files.image, inputs.rgb.size(2), inputs.rgb.size(1), inputs.objects.size());
    simu::resample::Resampler resampler(model.config);
    simu::resample::LiftOptions opt;
    opt.seed = model.seed;
    const auto result = simu::resample::lift_objects(resampler, inputs, opt);
    simu::resample::LiftWriteOptions w;
    w.out_dir = out_dir;
    w.overwrite = overwrite;
    w.image_path = files.image;
    w.depth_path = files.pointmap.empty() ? files.depth : files.pointmap;
    w.banner = banner;
    w.run_info = simu::resample::lift_run_info(resampler, opt, model.precision, model.random_weights);
    simu::resample::write_lift_outputs(result, inputs, w, simu::resample::occupancy_resolution(resampler));
    // Summary: one line per object, the stage times, where the files are.
    for (const auto& o : result.objects) {
      if (o.ok)
        fmt::print("  {}: ok, {} sample(s), scene t = [{:.3f}, {:.3f}, {:.3f}] m, scale {:.3f}\n", o.id, o.samples.size(),
                   o.scene_poses[0].t.x(), o.scene_poses[0].t.y(), o.scene_poses[0].t.z(), o.scene_poses[0].scale.x());
      else
        fmt::print("  {}: FAILED: {}\n", o.id, o.error);
    }
    const auto& s = result.seconds;
    fmt::print("lifted {} of {} object(s) on {} in {:.2f} s: preprocess {:.2f}, embed {:.2f}, sample {:.2f}, decode {:.2f}, "
               "mesh {:.2f}, pose {:.3f} s -> {}\n",
               result.objects.size() - result.failed(), result.objects.size(), resampler.device().str(),
               std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count(), s.preprocess, s.embed,
               s.sample, s.decode, s.mesh, s.pose, out_dir);
    if (!banner.empty()) fmt::print(stderr, "{}\n", banner);
    return result.failed() > 0 ? 1 : 0;
  });
}
