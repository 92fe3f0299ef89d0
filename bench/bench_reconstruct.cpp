// bench_reconstruct: the reconstruct front end on a synthetic camera scene (synthetic_camera.h; default
// 24 objects on the table + 2 hanging, as many as the generator fits) against its ground truth.
//   before = the "lifted" poses with SAM 3D-like errors (scale +-10..25%, 1..5% of the distance along
//            the ray, <= 2 degrees), composed and simulated as they are (--no-align --no-tabletop);
//   after  = the full front end (alignment, planes, tabletop, floor snap) then the probe.
// Prints per-object scale / translation errors, plane normal errors, the probe's headline metrics
// (2D IoU / ABO and fh / fo variants, 3D AABB IoU / ABO against the true boxes, stability,
// penetration ratio, D_mean, E_pk) and the seconds per step.
//   bench_reconstruct                         bring your own lift (ground-truth meshes + errors), CPU
//   bench_reconstruct --lift --device cuda --random-weights
//                                             every object lifted by the Stage-1 port at the released
//                                             dimensions (random weights: timing only), then the same steps
#include <fmt/format.h>

#include <chrono>
#include <memory>
#include <filesystem>
#include <fstream>

#include "common/cli.h"
#include "common/error.h"
#include "resample/lift.h"
#include "reconstruct/run.h"
#include "reconstruct/synthetic_camera.h"

namespace sr = simu::reconstruct;
namespace sp = simu::physics;
namespace rs = simu::resample;
using json = nlohmann::json;

int main(int argc, char** argv) {
  CLI::App app{"bench_reconstruct: the reconstruct front end on a 26-object synthetic camera scene, before / after"};
  int objects = 24, hanging = 2, width = 640, height = 480;
  uint64_t seed = 1;
  std::string out = "/tmp/bench_reconstruct", precision = "auto";
  bool lift = false, random_weights = false, no_probe = false;
  rs::ResamplerConfig rcfg;
  rcfg.embedder_config = std::string(SIMU_SOURCE_DIR) + "/configs/cond_embedder_sam3d_stage1.yaml";
  app.add_option("--objects", objects, "free objects asked of the generator (it places what fits)")->capture_default_str();
  app.add_option("--hanging", hanging, "hanging objects (0..2 placed)")->capture_default_str();
  app.add_option("--width", width, "image width")->capture_default_str();
  app.add_option("--height", height, "image height")->capture_default_str();
  app.add_option("--seed", seed, "scene seed")->capture_default_str();
  app.add_option("--out", out, "work directory (replaced)")->capture_default_str();
  app.add_flag("--lift", lift, "lift every object with the Stage-1 port instead of bringing the ground-truth meshes");
  app.add_flag("--no-probe", no_probe, "skip the physics probe");
  app.add_option("--device", rcfg.device, "auto | cpu | cuda")->capture_default_str();
  app.add_option("--precision", precision, "auto | fp16 | bf16 | fp32")->capture_default_str();
  app.add_option("--steps", rcfg.steps, "Stage-1 sampling steps")->capture_default_str();
  app.add_option("--generator-config", rcfg.generator_config, "Stage-1 generator config")->capture_default_str();
  app.add_option("--generator-weights", rcfg.generator_weights, "generator safetensors");
  app.add_option("--decoder-config", rcfg.decoder_config, "decoder config")->capture_default_str();
  app.add_option("--decoder-weights", rcfg.decoder_weights, "decoder safetensors");
  app.add_option("--embedder-config", rcfg.embedder_config, "condition embedder config")->capture_default_str();
  app.add_option("--embedder-weights", rcfg.embedder_weights, "condition embedder safetensors");
  app.add_flag("--random-weights", random_weights, "random init for missing weights (timing only)");
  return simu::cli::run(app, argc, argv, [&] {
    namespace sfs = std::filesystem;
    sr::CameraSceneConfig cfg;
    cfg.generator.min_objects = cfg.generator.max_objects = objects;
    cfg.generator.max_hanging = hanging;
    cfg.generator.width = width;
    cfg.generator.height = height;
    cfg.generator.fx = 0.875 * width;
    auto t0 = std::chrono::steady_clock::now();
    const sr::CameraScene s = sr::generate_camera_scene(cfg, seed, "bench");
    sfs::remove_all(out);
    sr::write_camera_scene(s, out + "/photo");
    const double t_gen = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (lift) {  // drop the meshes: every object through the port
      json side = json::parse(std::ifstream(out + "/photo/objects.json"));
      for (auto& e : side["objects"]) e.erase("mesh"), e.erase("pose");
      std::ofstream(out + "/photo/objects.json") << side.dump(2);
    }
    int n_free = 0, n_hang = 0;
    for (auto& o : s.objects)
      if (!o.is_base) ++(o.dof == sp::PoseDof::Free ? n_free : n_hang);
    fmt::print("scene: {}x{}, {} objects ({} free, {} hanging) + {} base(s); generated and written in {:.2f} s\n", width,
               height, n_free + n_hang, n_free, n_hang, s.objects.size() - n_free - n_hang, t_gen);
    std::unique_ptr<rs::Resampler> resampler;
    if (lift) {
      const std::string banner = rs::check_lift_weights(rcfg, random_weights);
      if (!banner.empty()) fmt::print(stderr, "*** {} ***\n", banner);
      rs::apply_precision(rcfg, precision);
      rcfg.random_weights = random_weights;
      t0 = std::chrono::steady_clock::now();
      resampler = std::make_unique<rs::Resampler>(rcfg);
      fmt::print("models loaded on {} in {:.2f} s\n", resampler->device().str(),
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    }
    sr::ReconstructFiles files;
    files.lift.image = out + "/photo/image.png";
    files.lift.masks = {out + "/photo/labels.png"};
    files.lift.depth = out + "/photo/depth.png";
    files.lift.intrinsics = out + "/photo/K.json";
    files.sidecar = out + "/photo/objects.json";
    std::map<std::string, sp::Box3> boxes;
    for (auto& o : s.objects) {
      const sr::Points W = sr::place(o.canonical, o.gt_scale, o.gt_R, o.gt_t);
      boxes[o.id] = sp::Box3{W.colwise().minCoeff().transpose(), W.colwise().maxCoeff().transpose()};
    }
    auto run_one = [&](bool full, const std::string& dir) {
      sr::ReconstructOptions opt;
      opt.do_align = opt.do_tabletop = opt.do_floor_snap = full;
      opt.run_probe = !no_probe;
      opt.probe.collision.use_coacd = false;
      opt.gt_boxes = boxes;
      return sr::reconstruct(files, opt, resampler.get(), dir);
    };
    const auto before = run_one(false, out + "/before");
    const auto after = run_one(true, out + "/after");
    // Per-object pose errors against the truth (objects in both runs).
    auto errors = [&](const sr::ReconstructResult& r) {
      double se = 0, te = 0, se_max = 0, te_max = 0;
      int n = 0, within = 0;
      for (const auto& o : s.objects) {
        for (const auto& so : r.scene.objects) {
          if (so.id != o.id) continue;
          const double e_s = std::abs(so.scale.maxCoeff() / o.gt_scale.maxCoeff() - 1), e_t = (so.t - o.gt_t).norm();
          se += e_s, te += e_t, se_max = std::max(se_max, e_s), te_max = std::max(te_max, e_t);
          within += e_s < 0.03 && e_t < 0.01;
          ++n;
        }
      }
      return fmt::format("scale err mean {:.2f}% max {:.2f}%, translation err mean {:.1f} mm max {:.1f} mm, "
                         "{} of {} within 3% / 1 cm",
                         100 * se / std::max(1, n), 100 * se_max, 1000 * te / std::max(1, n), 1000 * te_max, within, n);
    };
    fmt::print("\n| | objects (scale, translation) |\n|---|---|\n| before | {} |\n| after | {} |\n", errors(before),
               errors(after));
    const auto& P = after.planes;
    fmt::print("\nplanes: up {:.3f} deg from the truth (from {}); floor normal {:.3f} deg, offset {:.1f} mm after the snap",
               sr::angle_deg(P.up, s.up), P.up_source,
               P.floor ? sr::angle_deg(P.floor->plane.normal, s.floor.plane.normal) : -1.0,
               P.floor ? 1000 * std::abs(s.floor.plane.distance(P.floor->plane.point)) : -1.0);
    for (const auto& w : P.walls) {
      const auto& t = w.id == "back_wall" ? s.back_wall : s.left_wall;
      fmt::print("; {} {:.3f} deg", w.id, sr::angle_deg(w.plane.normal, t.plane.normal));
    }
    fmt::print("\n");
    if (!no_probe && before.probe && after.probe) {
      auto row = [](const char* name, const sp::HeadlineMetrics& m) {
        fmt::print("| {} | {:.3f} | {:.3f} | {:.3f} | {:.3f} | {:.3f} | {:.3f} | {:.1f} | {:.1f} | {:.4f} | {:.4f} |\n", name,
                   m.mask.iou, m.mask.abo, m.mask.iou_fhfo(), m.mask.abo_fhfo(), m.box.iou, m.box.abo, m.physics.stability,
                   m.physics.penetration_ratio, m.physics.mean_displacement, m.physics.peak_energy);
      };
      fmt::print("\n| probe output of | 2D IoU | 2D ABO | IoU fh/fo | ABO fh/fo | 3D IoU | 3D ABO | stab % | pen % | D_mean m | E_pk J |\n"
                 "|---|---|---|---|---|---|---|---|---|---|---|\n");
      row("lifted poses (before)", before.probe->after);
      row("reconstruct (after)", after.probe->after);
    }
    fmt::print("\nseconds per step (after run): {}\n", after.timings.dump());
    if (lift)
      fmt::print("total per scene with the port ({} objects): {:.2f} s\n", n_free + n_hang,
                 after.timings.value("total", 0.0));
    return 0;
  });
}
