// bench_reconstruct: the reconstruct front end on a synthetic camera scene (synthetic_camera.h: a floor,
// two walls, a table with objects on it, objects on the floor beside it, occlusions, hanging objects;
// default 24 free + 2 hanging, every one in view) against its ground truth. The photo stays in memory
// (synthetic_inputs.h: no image file is read, so builds without OpenCV run it); --write-photo also
// writes it as the `reconstruct` program's input files.
//   before = the "lifted" poses with SAM 3D-like errors (scale +-10..25%, 1..5% of the distance along
//            the ray, <= 2 degrees), composed and simulated as they are (no alignment, tabletop, snap);
//   after  = the full front end (alignment, planes, tabletop, re-extraction and floor snap, walls for
//            hanging objects) then the probe.
// Prints per-object scale / translation errors, plane normal errors, the probe's headline metrics
// (2D IoU / ABO and fh / fo variants, 3D AABB IoU / ABO against the true boxes, stability,
// penetration ratio, D_mean, E_pk) and the seconds per step.
//   bench_reconstruct                         bring your own lift (ground-truth meshes + errors), CPU
//   bench_reconstruct --lift --device cuda --random-weights
//                                             every object lifted by the Stage-1 port at the released
//                                             dimensions (random weights: timing only), then the same steps
//   bench_reconstruct --lift-timing --device cuda --random-weights
//                                             the time per scene with random weights: every object lifted
//                                             by the port in one batched call (timed), then the steps on the
//                                             ground-truth meshes (random weights decode noise, whose size,
//                                             not the pipeline's, would set the CPU steps' time)
#include <fmt/format.h>

#include <chrono>
#include <filesystem>
#include <memory>

#include "common/cli.h"
#include "common/error.h"
#include "common/fs.h"
#include "pipeline/reconstruct/run.h"
#include "pipeline/reconstruct/synthetic_camera.h"
#include "pipeline/reconstruct/synthetic_inputs.h"
#include "pipeline/resample/lift.h"
#include "pipeline/resample/model_options.h"

namespace sr = simu::reconstruct;
namespace sp = simu::physics;
namespace rs = simu::resample;
using json = nlohmann::json;

namespace {
double since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Scale / translation errors of the composed scene's objects against the truth.
std::string pose_errors(const sr::CameraScene& s, const sr::ReconstructResult& r) {
  double se = 0, te = 0, se_max = 0, te_max = 0;
  int n = 0, within = 0;
  for (const auto& o : s.objects)
    for (const auto& so : r.scene.objects) {
      if (so.id != o.id) continue;
      const double e_s = std::abs(so.scale.maxCoeff() / o.gt_scale.maxCoeff() - 1), e_t = (so.t - o.gt_t).norm();
      se += e_s, te += e_t, se_max = std::max(se_max, e_s), te_max = std::max(te_max, e_t);
      within += e_s < 0.03 && e_t < 0.01;
      ++n;
    }
  return fmt::format("{:.2f}% / {:.2f}% | {:.1f} / {:.1f} mm | {} of {}", 100 * se / std::max(1, n), 100 * se_max,
                     1000 * te / std::max(1, n), 1000 * te_max, within, n);
}

// Plane errors of a result against the truth.
void print_planes(const sr::CameraScene& s, const sr::ReconstructResult& r) {
  const auto& P = r.planes;
  fmt::print("planes: up {:.3f} deg from the truth (from {}; first pass from {}); floor normal {:.3f} deg, offset {:.1f} mm "
             "after the snap ({:+.1f} mm)",
             sr::angle_deg(P.up, s.up), P.up_source, r.planes_first.up_source,
             P.floor ? sr::angle_deg(P.floor->plane.normal, s.floor.plane.normal) : -1.0,
             P.floor ? 1000 * std::abs(s.floor.plane.distance(P.floor->plane.point)) : -1.0, 1000 * r.floor_snap);
  for (const auto& w : P.walls) {
    const auto& t = w.id == "left_wall" ? s.left_wall : s.back_wall;
    fmt::print("; {} {:.3f} deg", w.id, sr::angle_deg(w.plane.normal, t.plane.normal));
  }
  if (r.mesh_up.norm() > 0) fmt::print("; the fitted meshes' up {:.3f} deg", sr::angle_deg(r.mesh_up, s.up));
  fmt::print("\n");
  for (const auto& o : r.objects)
    if (!o.wall.empty()) fmt::print("  hanging {} -> wall {}\n", o.id, o.wall);
}
}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"bench_reconstruct: the reconstruct front end on a 26-object synthetic camera scene, before / after"};
  int objects = 24, hanging = 2, width = 640, height = 480, attempts = 400;
  uint64_t seed = 6;  // 24 free + 2 hanging placed, none fully hidden (seeds 6 and 12 of 1..12 are)
  std::string out = "/tmp/bench_reconstruct";
  bool lift = false, lift_timing = false, no_probe = false, write_photo = false, no_floor_objects = false, no_before = false;
  rs::ModelOptions model;
  app.add_option("--objects", objects, "free objects (on the table and the floor beside it)")->capture_default_str();
  app.add_option("--hanging", hanging, "hanging objects on the back wall (0..2)")->capture_default_str();
  app.add_option("--placement-attempts", attempts, "the generator's placement tries per object")->capture_default_str();
  app.add_flag("--no-floor-objects", no_floor_objects, "objects on the table only");
  app.add_option("--width", width, "image width")->capture_default_str();
  app.add_option("--height", height, "image height")->capture_default_str();
  app.add_option("--seed", seed, "scene seed")->capture_default_str();
  app.add_option("--out", out, "work directory (replaced)")->capture_default_str();
  app.add_flag("--lift", lift, "lift every object with the Stage-1 port instead of bringing the ground-truth meshes");
  app.add_flag("--lift-timing", lift_timing,
               "lift every object with the port (timed), then run the steps on the ground-truth meshes (random weights)");
  app.add_flag("--no-probe", no_probe, "skip the physics probe");
  app.add_flag("--no-before", no_before, "skip the 'before' run (the lifted poses simulated as they are)");
  app.add_flag("--write-photo", write_photo, "also write the photo as reconstruct's input files (needs OpenCV)");
  rs::ModelOptionFlags flags;
  flags.seed = false;  // --seed is the scene's
  rs::add_model_options(app, model, flags);
  return simu::cli::run(app, argc, argv, [&] {
    namespace sfs = std::filesystem;
    sr::CameraSceneConfig cfg;
    cfg.generator.min_objects = cfg.generator.max_objects = objects;
    cfg.generator.min_hanging = cfg.generator.max_hanging = hanging;
    cfg.generator.placement_attempts = attempts;
    cfg.generator.floor_supports = !no_floor_objects;
    cfg.generator.width = width;
    cfg.generator.height = height;
    cfg.generator.fx = 0.875 * width;
    auto t0 = std::chrono::steady_clock::now();
    const sr::CameraScene s = sr::generate_camera_scene(cfg, seed, "bench");
    simu::fs::remove_tree(out);  // not std::filesystem::remove_all (common/fs.h says why)
    const std::string photo = out + "/photo";
    if (write_photo) sr::write_camera_scene(s, photo);
    else sr::write_camera_scene_lift(s, photo);
    const sr::ReconstructInputs inputs = sr::camera_scene_inputs(s, photo, !lift);
    const double t_gen = since(t0);
    int n_free = 0, n_hang = 0, hidden = 0;
    for (auto& o : s.objects) {
      if (o.is_base) continue;
      ++(o.dof == sp::PoseDof::Free ? n_free : n_hang);
      hidden += o.mask.count() == 0;
    }
    fmt::print("scene: {}x{}, {} objects ({} free of {} asked, {} hanging) + {} base(s), {} fully hidden; generated in "
               "{:.2f} s\n",
               width, height, n_free + n_hang, n_free, objects, n_hang, s.objects.size() - n_free - n_hang, hidden, t_gen);
    std::fflush(stdout);  // the scene line before the long steps
    std::unique_ptr<rs::Resampler> resampler;
    double t_models = 0;
    SIMU_CHECK(!(lift && lift_timing), "bench_reconstruct: --lift and --lift-timing exclude each other");
    if (lift || lift_timing) {
      const std::string banner = rs::finish_model_options(model);
      if (!banner.empty()) fmt::print(stderr, "*** {} ***\n", banner);
      t0 = std::chrono::steady_clock::now();
      resampler = std::make_unique<rs::Resampler>(model.config);
      t_models = since(t0);
      fmt::print("models loaded on {} in {:.2f} s\n", resampler->device().str(), t_models);
    }
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
      opt.lift.seed = 0;
      return sr::reconstruct(inputs, opt, resampler.get(), dir);
    };
    // --lift-timing: the port lifts every object in one batched call, as reconstruct does; the steps below
    // then run on the ground-truth meshes.
    double t_lift = 0;
    if (lift_timing) {
      const sr::ReconstructInputs all = sr::camera_scene_inputs(s, photo, false);
      rs::LiftInputs objects = all.lift;  // the objects and the table; floor and walls are planes, not lifted
      objects.objects.clear();
      for (const auto& o : all.lift.objects)
        for (const auto& spec : all.specs)
          if (spec.mask_id == o.id && spec.role == "object") objects.objects.push_back(o);
      rs::LiftOptions lo;
      lo.seed = 0;
      t0 = std::chrono::steady_clock::now();
      const rs::LiftResult lr = rs::lift_objects(*resampler, objects, lo);
      t_lift = since(t0);
      const auto& T = lr.seconds;
      fmt::print("lift: {} objects in one call, {:.2f} s ({} not ok): preprocess {:.2f}, embed {:.2f}, sample {:.2f}, decode "
                 "{:.2f}, mesh {:.2f}, pose {:.2f} s\n",
                 lr.objects.size(), t_lift, lr.failed(), T.preprocess, T.embed, T.sample, T.decode, T.mesh, T.pose);
      std::fflush(stdout);
    }
    const auto before = no_before ? sr::ReconstructResult{} : run_one(false, out + "/before");
    const auto after = run_one(true, out + "/after");
    for (const auto& o : after.objects)
      for (const auto& k : o.skipped) fmt::print("  skipped {}: {}\n", o.id, k);
    fmt::print("\n| | scale error mean / max | translation error mean / max | within 3% / 1 cm |\n|---|---|---|---|\n"
               "| lifted poses (before) | {} |\n| after alignment | {} |\n\n",
               pose_errors(s, before), pose_errors(s, after));
    print_planes(s, after);
    if (!no_probe && after.probe) {
      auto row = [](const char* name, const sp::HeadlineMetrics& m) {
        fmt::print("| {} | {:.3f} | {:.3f} | {:.3f} | {:.3f} | {:.3f} | {:.3f} | {:.1f} | {:.1f} | {:.2f} | {:.3g} |\n", name,
                   m.mask.iou, m.mask.abo, m.mask.iou_fhfo(), m.mask.abo_fhfo(), m.box.iou, m.box.abo, m.physics.stability,
                   m.physics.penetration_ratio, 1000 * m.physics.mean_displacement, m.physics.peak_energy);
      };
      fmt::print("\n| probe output of | 2D IoU | 2D ABO | IoU fh/fo | ABO fh/fo | 3D IoU | 3D ABO | stab % | pen % | D_mean mm | "
                 "E_pk J |\n|---|---|---|---|---|---|---|---|---|---|---|\n");
      if (before.probe) row("lifted poses (before)", before.probe->after);
      row("reconstruct (after)", after.probe->after);
      const auto& ph = after.probe->after.physics;
      fmt::print("(after: {} objects evaluated, {} stability-counted, {} physics-disabled)\n", ph.evaluated_count,
                 ph.stability_count, ph.disabled_count);
    }
    fmt::print("\nseconds per step (after run): {}\n", after.timings.dump());
    if (lift)
      fmt::print("total per scene with the port ({} objects): {:.2f} s (+ {:.2f} s loading the models once)\n",
                 n_free + n_hang, after.timings.value("total", 0.0), t_models);
    if (lift_timing)
      fmt::print("total per scene ({} objects): lift {:.2f} s + steps {:.2f} s = {:.2f} s (+ {:.2f} s loading the models once)\n",
                 n_free + n_hang, t_lift, after.timings.value("total", 0.0), t_lift + after.timings.value("total", 0.0),
                 t_models);
    return 0;
  });
}
