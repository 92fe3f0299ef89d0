// Reporting of a probe run: report.json and its parts, the headline metrics and their table, the
// overlay, and every output file written through a staging folder (probe.h, probe_world.h).
#include "pipeline/physics/probe_world.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/overlay.h"
#include "pipeline/physics/pictures.h"
#include "pipeline/physics/raster.h"

namespace simu::physics {

namespace stdfs = std::filesystem;
using nlohmann::json;
using namespace probe_detail;

namespace {

json vec_j(const Vec3& v) { return json::array({v[0], v[1], v[2]}); }
json mat_j(const Mat3& m) {
  return json::array({json::array({m(0, 0), m(0, 1), m(0, 2)}), json::array({m(1, 0), m(1, 1), m(1, 2)}),
                      json::array({m(2, 0), m(2, 1), m(2, 2)})});
}
json box_j(const Obb& b) { return {{"center", vec_j(b.center)}, {"axes", mat_j(b.axes)}, {"extents", vec_j(b.extents)}}; }
double angle_of(const Mat3& R) { return std::acos(std::clamp((R.trace() - 1.0) / 2.0, -1.0, 1.0)); }

// The overlay PNG (overlay.h) of a probe run: modal masks (or the rendered visible masks of the
// corrected objects), OBBs before / targeted, auxiliary crop masks of the resample requests.
void write_overlay(const ProbeResult& res, const std::vector<Obj>& objs, const std::string& path) {
  const Scene& scene = res.scene;
  const size_t n = scene.objects.size();
  // Visible masks of the corrected scene (for objects without a modal mask file).
  std::vector<Mesh> world(n);
  std::vector<const Mesh*> ptrs(n, nullptr);
  for (size_t i = 0; i < n; ++i)
    if (objs[i].usable) {
      world[i] = transform_mesh(objs[i].canonical, objs[i].R * objs[i].s.asDiagonal(), objs[i].t);
      ptrs[i] = &world[i];
    }
  const LabelImage labels = render_labels(scene.camera, ptrs);
  std::vector<BinaryMask> masks(n), aux(n);
  std::vector<OverlayItem> items(n);
  for (size_t i = 0; i < n; ++i) {
    const SceneObject& so = scene.objects[i];
    const Diagnostics& d = res.diagnostics[i];
    OverlayItem& it = items[i];
    it.label = so.id + " " + to_string(d.branch);
    try {
      if (!so.mask_path.empty() && stdfs::exists(so.mask_path)) masks[i] = read_mask(so.mask_path);
    } catch (const std::exception& e) {
      log::warn("overlay: {}", e.what());
    }
    if (masks[i].width != scene.camera.width || masks[i].height != scene.camera.height) masks[i] = labels.mask_of(int(i));
    it.mask = &masks[i];
    if (d.diagnosis.obb_pre.extents.minCoeff() > 0) it.obb = d.diagnosis.obb_pre;
    if ((d.branch == ProbeBranch::Stretch || d.branch == ProbeBranch::Resample) && d.obb_target.extents.minCoeff() > 0)
      it.obb_target = d.obb_target;
  }
  for (const ProbeResampleRequest& r : res.resample_requests) {
    if (r.object_index < 0 || r.object_index >= int(n) || r.aux_mask.empty()) continue;
    BinaryMask& m = aux[r.object_index];
#ifdef SIMU_HAVE_OPENCV
    m = BinaryMask(r.aux_mask.cols, r.aux_mask.rows);
    for (int y = 0; y < m.height; ++y)
      for (int x = 0; x < m.width; ++x) m.at(y, x) = r.aux_mask.at<uint8_t>(y, x) ? 1 : 0;
#else
    m = BinaryMask(r.aux_mask.width, r.aux_mask.height);
    for (size_t k = 0; k < m.data.size(); ++k) m.data[k] = r.aux_mask.data[k] ? 1 : 0;
#endif
    items[r.object_index].aux_mask = &m;
  }
  write_overlay_png(path, scene.camera, scene.image_path, items);
}

// Writes every output of a probe run into `dir` (which exists and is empty): meshes, scene.json
// (mesh paths relative, valid once dir is moved to final_dir), scene.xml (checked by compiling it from
// disk with MuJoCo 2.2; without its visual meshes when they do not compile), hand-off, report, pictures.
void write_outputs_into(ProbeResult& res, const std::vector<Obj>& objs, const std::string& dir,
                        const std::string& final_dir) {
  Scene& scene = res.scene;
  const size_t n = scene.objects.size();
  stdfs::create_directories(dir + "/meshes");
  for (size_t i = 0; i < n; ++i) {
    if (!objs[i].usable) continue;
    const std::string name = "meshes/" + safe_name(scene.objects[i].id) + ".obj";
    try {
      write_mesh(objs[i].canonical, dir + "/" + name);
      scene.objects[i].mesh_path = (stdfs::absolute(final_dir) / name).lexically_normal().string();
    } catch (const std::exception& e) {
      add_flag(res.diagnostics[i], "write_failed", e.what());
    }
  }
  fs::atomic_write(dir + "/scene.json", scene_to_json(scene, stdfs::absolute(final_dir).string()).dump(2) + "\n");
  if (!res.mjcf.empty()) {
    fs::atomic_write(dir + "/scene.xml", res.mjcf);
    try {
      std::lock_guard<std::mutex> lock(compile_mutex());
      load_mjcf_file(dir + "/scene.xml");
    } catch (const std::exception& e) {
      // A visual mesh MuJoCo cannot compile must not cost the user the scene: drop the visual geoms.
      log::warn("scene.xml with visual meshes does not compile ({}); written without them", e.what());
      std::string xml = res.mjcf;
      for (size_t p; (p = xml.find("/visual\"")) != std::string::npos;) {
        const size_t start = xml.rfind('\n', p), end = xml.find('\n', p);
        xml.erase(start, end - start);
      }
      res.mjcf = xml;
      fs::atomic_write(dir + "/scene.xml", res.mjcf);
    }
  }
  // Resample hand-off files (masks and target OBB).
  for (const auto& r : res.resample_requests) {
    const std::string rdir = dir + "/resample/" + safe_name(r.object_id);
    stdfs::create_directories(rdir);
    json j = {{"object_index", r.object_index}, {"object_id", r.object_id}, {"image", r.image_path},
              {"mask", r.mask_path}, {"target_obb", box_j(r.target_obb)},
              {"translation", vec_j(r.target_obb.center)}};
#ifdef SIMU_HAVE_OPENCV
    if (!r.aux_mask.empty()) {
      cv::imwrite(rdir + "/aux_mask.png", r.aux_mask);
      j["aux_mask"] = "aux_mask.png";
    }
#endif
    fs::atomic_write(rdir + "/request.json", j.dump(2) + "\n");
  }
  fs::atomic_write(dir + "/report.json", report_json(res).dump(2) + "\n");
  // Pictures for a person to look at (need OpenCV's PNG codec and a camera).
#ifdef SIMU_HAVE_OPENCV
  if (scene.camera.valid()) {
    try {
      write_overlay(res, objs, dir + "/overlay.png");
    } catch (const std::exception& e) {
      log::warn("overlay.png not written: {}", e.what());
    }
    try {
      for (const auto& f : write_probe_pictures(res, dir))
        res.pictures.push_back((stdfs::path(final_dir) / stdfs::path(f).filename()).string());
    } catch (const std::exception& e) {
      log::warn("pictures not written: {}", e.what());
    }
  } else {
    log::info("pictures skipped: the scene has no valid camera");
  }
#else
  log::info("pictures skipped: built without OpenCV (SIMU_WITH_OPENCV=OFF)");
#endif
}

}  // namespace

void probe_detail::write_outputs(ProbeResult& res, const std::vector<Obj>& objs, const std::string& out_dir,
                                 const ProbeConfig& cfg) {
  const stdfs::path final_dir = stdfs::absolute(out_dir).lexically_normal();
  const stdfs::path parent = final_dir.parent_path();
  const std::string base = final_dir.filename().string();
  stdfs::create_directories(parent);
  // Staging folders of writers that died (their pid is gone) are removed.
  const std::string prefix = "." + base + ".staging-";
  for (const auto& e : stdfs::directory_iterator(parent)) {
    const std::string name = e.path().filename().string();
    if (name.rfind(prefix, 0) != 0) continue;
    const std::string pid = name.substr(prefix.size());
    if (!pid.empty() && pid.find_first_not_of("0123456789") == std::string::npos &&
        !stdfs::exists("/proc/" + pid)) fs::remove_tree(e.path().string());
  }
  if (stdfs::exists(final_dir) && !cfg.overwrite)
    fail_hint("pass --overwrite (probe) or choose another --out", "output folder {} already exists; not overwritten",
              final_dir.string());
  const std::string staging = (parent / (prefix + std::to_string(::getpid()))).string();
  fs::remove_tree(staging);
  try {
    write_outputs_into(res, objs, staging, final_dir.string());
    if (stdfs::exists(final_dir)) {
      // Replace: swap atomically where the filesystem can, else move the old one aside first.
      if (!fs::atomic_exchange(staging, final_dir.string())) {
        const std::string old = (parent / ("." + base + ".old-" + std::to_string(::getpid()))).string();
        fs::atomic_rename(final_dir.string(), old);
        fs::atomic_rename(staging, final_dir.string());
        fs::remove_tree(old);
      } else {
        fs::remove_tree(staging);  // now holds the previous output
      }
    } else {
      fs::atomic_rename(staging, final_dir.string());
    }
  } catch (...) {
    try { fs::remove_tree(staging); } catch (...) {}
    throw;
  }
  // The corrected scene's mesh paths point into the final folder.
}

nlohmann::json report_json(const ProbeResult& r) {
  json objs = json::array();
  for (size_t i = 0; i < r.diagnostics.size(); ++i) {
    const auto& d = r.diagnostics[i];
    json e;
    e["id"] = r.scene.objects[i].id;
    e["dof"] = to_string(r.scene.objects[i].dof);
    e["order"] = d.order;
    e["branch"] = to_string(d.branch);
    e["physics_disabled"] = d.physics_disabled;
    e["flags"] = d.flags;
    e["message"] = d.message;
    e["dt_pen"] = vec_j(d.dt_pen);
    e["pen_iterations"] = d.pen_iterations;
    e["pen_max_depth"] = d.pen_max_depth;
    e["dt_grv"] = vec_j(d.dt_grv);
    e["dR_grv"] = mat_j(d.dR_grv);
    e["dR_grv_deg"] = angle_of(d.dR_grv) * 180.0 / M_PI;
    e["sim_time"] = d.sim_time;
    const Diagnosis& dg = d.diagnosis;
    e["rho"] = dg.rho;
    e["eta"] = dg.eta;
    e["ell"] = dg.axis.length;
    e["u_grv"] = vec_j(dg.axis.length > 0 ? dg.axis.u : Vec3::Zero());  // zero: not diagnosed
    e["obb_pre"] = box_j(dg.obb_pre);
    if (d.branch == ProbeBranch::Stretch || d.branch == ProbeBranch::Resample) e["obb_target"] = box_j(d.obb_target);
    if (!d.pins_world.empty()) {
      e["pins"] = json::array();
      for (size_t k = 0; k < d.pins_world.size(); ++k)
        e["pins"].push_back({{"object", vec_j(d.pins_world[k])}, {"wall", vec_j(d.wall_points[k])}});
      e["wall"] = d.wall_id;
    }
    e["t_pre"] = vec_j(d.t_pre);
    e["dt_final_pen"] = vec_j(d.dt_final_pen);
    e["settle_displacement"] = d.settle_displacement;
    e["reverted"] = d.reverted;
    e["final_settle"] = settle_json(d.final_settle);
    e["evaluation"] = settle_json(d.evaluation);
    if (r.input_evaluation.ran && i < r.input_evaluation.objects.size())
      e["evaluation_input"] = settle_json(r.input_evaluation.objects[i]);  // the input scene, settled the same way
    // Where the evaluation settles left the object (the poses the headline metrics score).
    if (r.evaluation.ran && i < r.evaluation.t.size())
      e["evaluation_pose"] = {{"R", mat_j(r.evaluation.R[i])}, {"t", vec_j(r.evaluation.t[i])}};
    if (r.input_evaluation.ran && i < r.input_evaluation.t.size())
      e["evaluation_input_pose"] = {{"R", mat_j(r.input_evaluation.R[i])}, {"t", vec_j(r.input_evaluation.t[i])}};
    // What changed: OBB extents before / after, displacement of the OBB centre.
    e["change"] = {{"obb_extents_before", vec_j(dg.obb_pre.extents)},
                   {"obb_extents_after", vec_j(d.obb_final.extents)},
                   {"displacement", (d.obb_final.center - dg.obb_pre.center).norm()}};
    if (d.branch == ProbeBranch::Resample) {
      json rs = {{"resampled", d.resampled}, {"message", d.resample_message}};
      if (d.resampled)
        rs["placed"] = {{"t", vec_j(d.t_resampled)}, {"R", mat_j(d.R_resampled)}, {"scale", vec_j(d.s_resampled)}};
      if (d.has_crop_box) rs["crop_box"] = d.crop_box;
      if (!d.candidates.empty()) {
        rs["chosen_candidate"] = d.chosen_candidate;
        rs["candidates"] = json::array();
        for (size_t k = 0; k < d.candidates.size(); ++k) {
          const auto& cd = d.candidates[k];
          rs["candidates"].push_back({{"label", cd.label}, {"ok", cd.ok}, {"displacement", cd.displacement},
                                      {"rotation_deg", cd.rotation_deg}, {"penetration", cd.penetration}, {"message", cd.message},
                                      {"chosen", static_cast<int>(k) == d.chosen_candidate}});
        }
      }
      e["resample"] = rs;
    }
    objs.push_back(e);
  }
  json metrics = metrics_json(r.evaluation.metrics);
  metrics["settle_time"] = r.evaluation.simulated_time;
  metrics["solver_reset"] = r.evaluation.solver_reset;
  if (!r.evaluation.message.empty()) metrics["message"] = r.evaluation.message;
  json headline = {{"after", headline_json(r.after)}};
  if (r.before.computed) headline["before"] = headline_json(r.before);
  return {{"objects", objs},
          {"order", r.order},
          {"metrics", metrics},
          {"headline", headline},
          {"seconds",
           {{"probe", r.seconds_probe}, {"resample", r.seconds_resample}, {"final", r.seconds_final}, {"metrics", r.seconds_metrics}}}};
}

HeadlineMetrics headline_metrics(const Scene& scene, const std::vector<const Mesh*>& world,
                                 const PhysicsEvaluation& settle, const MetricsConfig& config) {
  HeadlineMetrics h;
  const size_t n = scene.objects.size();
  SIMU_CHECK(world.size() == n && settle.objects.size() == n, "headline_metrics: {} objects, {} meshes, {} records", n,
             world.size(), settle.objects.size());
  h.physics = physics_metrics(settle.objects, config, settle.ran ? settle.scene_peak_energy : -1);
  // Objects with ground truth first (identity pairs i <-> i), the others only as predictions.
  auto scored = [&](const std::vector<int>& with, const auto& iou_of) {
    std::vector<int> order = with;
    for (size_t i = 0; i < n; ++i)
      if (std::find(with.begin(), with.end(), int(i)) == with.end()) order.push_back(int(i));
    std::vector<bool> valid;
    std::vector<MetricCategory> cat;
    for (int j : order) {
      valid.push_back(world[j] != nullptr && is_valid(settle.objects[j], config));
      cat.push_back(metric_category(scene.objects[j].dof));
    }
    std::vector<std::vector<double>> iou(with.size(), std::vector<double>(order.size(), 0.0));
    for (size_t a = 0; a < with.size(); ++a)
      for (size_t b = 0; b < order.size(); ++b) iou[a][b] = iou_of(with[a], order[b]);
    return overlap_metrics(iou, valid, cat);
  };
  // 2D: visible masks of the jointly rendered meshes against the input masks.
  std::vector<BinaryMask> gt(n);
  std::vector<int> with_mask, with_box;
  for (size_t i = 0; i < n; ++i) {
    const auto& so = scene.objects[i];
    if (so.gt_box) with_box.push_back(int(i));
    if (so.mask_path.empty() || !scene.camera.valid()) continue;
    try {
      gt[i] = read_mask(so.mask_path);
      if (gt[i].width == scene.camera.width && gt[i].height == scene.camera.height) with_mask.push_back(int(i));
    } catch (const std::exception& e) {
      log::debug("headline metrics: {}", e.what());
    }
  }
  if (!with_mask.empty()) {
    const LabelImage img = render_labels(scene.camera, world);
    std::vector<BinaryMask> pred(n);
    for (size_t j = 0; j < n; ++j) pred[j] = img.mask_of(int(j));
    h.mask = scored(with_mask, [&](int i, int j) { return mask_iou(gt[i], pred[j]); });
    h.has_masks = true;
  }
  if (!with_box.empty()) {
    h.box = scored(with_box, [&](int i, int j) {
      return world[j] && world[j]->V.rows() ? box_iou(*scene.objects[i].gt_box, world_aabb(*world[j])) : 0.0;
    });
    h.has_boxes = true;
  }
  h.computed = true;
  return h;
}

std::string format_headline(const HeadlineMetrics& b, const HeadlineMetrics& a, double settle_time) {
  std::string s = fmt::format("{:<34} {:>9} {:>9}\n", fmt::format("metric (after a {:g} s settle)", settle_time),
                              b.computed ? "before" : "", "after");
  auto row = [&](const std::string& name, bool have_b, double vb, bool have_a, double va, const char* f) {
    const std::string sb = b.computed && have_b ? fmt::format(fmt::runtime(f), vb) : "n/a";
    const std::string sa = have_a ? fmt::format(fmt::runtime(f), va) : "n/a";
    s += fmt::format("{:<34} {:>9} {:>9}\n", name, sb, sa);
  };
  row("ABO (2D)", b.has_masks, b.mask.abo, a.has_masks, a.mask.abo, "{:.4f}");
  row("ABO_fh/fo (2D, strict)", b.has_masks, b.mask.abo_fhfo(), a.has_masks, a.mask.abo_fhfo(), "{:.4f}");
  row("IoU (2D)", b.has_masks, b.mask.iou, a.has_masks, a.mask.iou, "{:.4f}");
  row("IoU_fh/fo (2D, strict)", b.has_masks, b.mask.iou_fhfo(), a.has_masks, a.mask.iou_fhfo(), "{:.4f}");
  if (a.has_boxes || b.has_boxes) {
    row("3D ABO (AABB)", b.has_boxes, b.box.abo, a.has_boxes, a.box.abo, "{:.4f}");
    row("3D ABO_fh/fo", b.has_boxes, b.box.abo_fhfo(), a.has_boxes, a.box.abo_fhfo(), "{:.4f}");
    row("3D IoU (AABB)", b.has_boxes, b.box.iou, a.has_boxes, a.box.iou, "{:.4f}");
    row("3D IoU_fh/fo", b.has_boxes, b.box.iou_fhfo(), a.has_boxes, a.box.iou_fhfo(), "{:.4f}");
  }
  row("stability (%, free, < 5 cm)", true, b.physics.stability, true, a.physics.stability, "{:.1f}");
  row("penetration ratio (%, > 2 mm)", true, b.physics.penetration_ratio, true, a.physics.penetration_ratio, "{:.1f}");
  row("D_mean (mm)", true, 1000 * b.physics.mean_displacement, true, 1000 * a.physics.mean_displacement, "{:.2f}");
  row("E_pk (J)", true, b.physics.peak_energy, true, a.physics.peak_energy, "{:.4g}");
  return s;
}

nlohmann::json headline_json(const HeadlineMetrics& m) {
  auto ov = [](const OverlapMetrics& o) {
    return json{{"abo", o.abo}, {"abo_fh", o.abo_fh}, {"abo_fo", o.abo_fo}, {"abo_fhfo", o.abo_fhfo()}, {"iou", o.iou},
                {"iou_fh", o.iou_fh}, {"iou_fo", o.iou_fo}, {"iou_fhfo", o.iou_fhfo()}, {"n_gt", o.n_gt},
                {"n_fh", o.n_fh}, {"n_fo", o.n_fo}};
  };
  json j = {{"physics", metrics_json(m.physics)}};
  if (m.has_masks) j["mask_2d"] = ov(m.mask);
  if (m.has_boxes) j["box_3d"] = ov(m.box);
  return j;
}

nlohmann::json settle_json(const SettleRecord& r) {
  const char* cat = r.category == MetricCategory::Free ? "free" : r.category == MetricCategory::Hanging ? "hanging" : "fixed";
  return {{"category", cat},
          {"physics_disabled", r.physics_disabled},
          {"displacement", r.displacement},
          {"initial_penetration", r.initial_penetration},
          {"initially_penetrating", r.initially_penetrating},
          {"final_penetration", r.max_penetration},
          {"peak_kinetic_energy", r.peak_kinetic_energy}};
}

nlohmann::json metrics_json(const PhysicsMetrics& m) {
  return {{"stability", m.stability},
          {"stability_count", m.stability_count},
          {"penetration_ratio", m.penetration_ratio},
          {"initial_penetration_ratio", m.initial_penetration_ratio},
          {"evaluated_count", m.evaluated_count},
          {"disabled_count", m.disabled_count},
          {"mean_displacement", m.mean_displacement},
          {"peak_energy", m.peak_energy}};
}

}  // namespace simu::physics
