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
#include "resample/lift.h"

int main(int argc, char** argv) {
  CLI::App app{"lift: SAM 3D Objects Stage 1 (shape + pose) on the objects of one photo -> meshes, 64^3 occupancy, "
               "poses in SAM 3D's and the scene convention, scene.json for the probe"};
  simu::resample::LiftFiles files;
  std::string out_dir, precision = "auto";
  bool random_weights = false, overwrite = false;
  uint64_t seed = 0;
  simu::resample::ResamplerConfig rcfg;
  rcfg.embedder_config = std::string(SIMU_SOURCE_DIR) + "/configs/cond_embedder_sam3d_stage1.yaml";
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
  app.add_option("--samples", rcfg.num_samples, "shapes drawn per object")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--seed", seed, "sampling seed")->capture_default_str();
  app.add_option("--device", rcfg.device, "auto | cpu | cuda | cuda:N")->capture_default_str();
  app.add_option("--precision", precision,
                 "auto | fp16 | bf16 | fp32 (auto: fp16 autocast on CUDA as released, fp32 on CPU)")
      ->capture_default_str();
  app.add_option("--steps", rcfg.steps, "Stage-1 sampling steps (released inference: 25)")->capture_default_str();
  app.add_option("--generator-config", rcfg.generator_config, "Stage-1 generator config")->capture_default_str();
  app.add_option("--generator-weights", rcfg.generator_weights, "generator safetensors (converted ss_generator.ckpt)");
  app.add_option("--decoder-config", rcfg.decoder_config, "sparse-structure decoder config")->capture_default_str();
  app.add_option("--decoder-weights", rcfg.decoder_weights, "decoder safetensors (converted ss_decoder.ckpt)");
  app.add_option("--embedder-config", rcfg.embedder_config, "condition embedder config")->capture_default_str();
  app.add_option("--embedder-weights", rcfg.embedder_weights,
                 "condition embedder safetensors (the converted ss_generator.safetensors holds it)");
  app.add_option("--adapter", rcfg.adapter_dir, "PEFT LoRA adapter directory (optional)");
  app.add_flag("--random-weights", random_weights, "allow missing weight files: random init (smoke runs, benchmarks)");
  simu::cli::CommonOptions common;
  simu::cli::add_common_options(app, common);
  return simu::cli::run(app, argc, argv, [&] {
    simu::cli::apply_common_options(common);
    if (!common.sets.empty())
      simu::fail_hint("use the --*-config files and flags", "lift reads no config file: --set {} would be ignored",
                      common.sets.front());
    const auto t_start = std::chrono::steady_clock::now();
    // Weights first (cheap), then every input file, then the models.
    const std::string banner = simu::resample::check_lift_weights(rcfg, random_weights);
    if (!banner.empty()) {
      const std::string bar(std::min<size_t>(banner.size(), 100), '!');
      fmt::print(stderr, "{}\n{}\n{}\n", bar, banner, bar);
    }
    simu::resample::apply_precision(rcfg, precision);
    rcfg.random_weights = random_weights;
    simu::resample::check_output_dir(out_dir, overwrite);
    auto inputs = simu::resample::load_lift_inputs(files);
    fmt::print("{}: {}x{}, {} object(s)\n", files.image, inputs.rgb.size(2), inputs.rgb.size(1), inputs.objects.size());
    simu::resample::Resampler resampler(rcfg);
    simu::resample::LiftOptions opt;
    opt.seed = seed;
    const auto result = simu::resample::lift_objects(resampler, inputs, opt);
    simu::resample::LiftWriteOptions w;
    w.out_dir = out_dir;
    w.overwrite = overwrite;
    w.image_path = files.image;
    w.depth_path = files.pointmap.empty() ? files.depth : files.pointmap;
    w.banner = banner;
    w.run_info = simu::resample::lift_run_info(resampler, opt, precision, random_weights);
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
