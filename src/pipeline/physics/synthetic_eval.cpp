// Benchmark support for synthetic scenes: the oracle displacement, before / after scoring, the probe's
// output objects, the stretch stand-in for the resampler.
#include "pipeline/physics/synthetic.h"


#include "common/error.h"
#include "common/fs.h"
#include "pipeline/physics/camera.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/metrics.h"
#include "pipeline/physics/overlay.h"
#include "pipeline/physics/probe.h"

#include <Eigen/Geometry>

#include <cmath>
#include <filesystem>
#include <fmt/format.h>
#include <limits>
#include <sstream>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#endif

namespace simu::physics {

namespace {
// Places a canonical mesh in the world: x = R (s .* v) + t.
Mesh place(const Mesh& m, const Vec3& s, const Mat3& R, const Vec3& t) { return transform_mesh(m, R * s.asDiagonal(), t); }
}  // namespace

std::optional<ResampleProxy> parse_resample_proxy(const std::string& s) {
  if (s == "stretch") return ResampleProxy::Stretch;
  if (s == "drop") return ResampleProxy::Drop;
  if (s == "keep") return ResampleProxy::Keep;
  return std::nullopt;
}

Displacement oracle_displacement(const SyntheticScene& s, const SyntheticObject& o) {
  const Mesh w = place(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t);
  const Vec3 g = s.gravity.normalized();
  // Gap along gravity between the lowest point (max g.x) and the support plane y = support_y.
  const double lowest = (w.V * g).maxCoeff();
  const double support = g.dot(Vec3(0, o.support_y, 0));
  const double d = support - lowest;
  Displacement out;
  if (d > 0) out.dt_grv = d * g;
  else out.dt_pen = d * g;
  return out;
}

SceneEvaluation evaluate_corrected(const SyntheticScene& s, const std::vector<CorrectedObject>& after_objs) {
  SIMU_CHECK(after_objs.size() == s.objects.size(), "evaluate_corrected: {} corrected objects for {} scene objects",
             after_objs.size(), s.objects.size());
  SceneEvaluation ev;
  const Vec3 g = s.gravity.normalized();
  std::vector<Mesh> before, after;
  std::vector<Box3> gt_boxes;
  std::vector<BinaryMask> gt_masks;
  std::vector<MetricCategory> cats;
  std::vector<bool> valid_after;
  for (size_t i = 0; i < s.objects.size(); ++i) {
    const SyntheticObject& o = s.objects[i];
    const CorrectedObject& c = after_objs[i];
    before.push_back(place(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t));
    after.push_back(place(c.mesh.V.rows() > 0 ? c.mesh : o.pred_mesh, c.scale, c.R, c.t));
    gt_boxes.push_back(o.gt_box);
    gt_masks.push_back(o.modal_mask);
    cats.push_back(metric_category(o.dof));
    valid_after.push_back(c.valid);
    if (o.dof != PoseDof::Free) continue;
    // Free objects: the decision against the injected error and the support gaps.
    ObjectOutcome oc;
    oc.id = o.id, oc.error = o.error, oc.expected = expected_branch(o.error);
    oc.got = c.branch, oc.decided = c.decided, oc.rho = c.rho, oc.eta = c.eta, oc.flags = c.flags;
    const double support = g.dot(Vec3(0, o.support_y, 0));
    oc.support_gap_before = std::abs((before.back().V * g).maxCoeff() - support);
    oc.support_gap_after = std::abs((after.back().V * g).maxCoeff() - support);
    ev.objects.push_back(oc);
  }
  // Overlap metrics: the objects rendered jointly with the bases placed after them as occluders
  // (their masks are not scored).
  std::vector<Mesh> bases;
  for (const auto& b : s.bases) bases.push_back(place(b.mesh, b.scale, b.R, b.t));
  auto score = [&](const std::vector<Mesh>& objs, const std::vector<bool>& valid, OverlapMetrics* mask,
                   OverlapMetrics* box) {
    std::vector<const Mesh*> ptrs;
    for (const auto& m : objs) ptrs.push_back(&m);
    for (const auto& b : bases) ptrs.push_back(&b);
    const LabelImage img = render_labels(s.camera, ptrs);
    std::vector<std::vector<double>> iou(objs.size(), std::vector<double>(objs.size(), 0.0));
    for (size_t j = 0; j < objs.size(); ++j) {
      const BinaryMask pj = img.mask_of(int(j));
      for (size_t i = 0; i < objs.size(); ++i) iou[i][j] = mask_iou(gt_masks[i], pj);
    }
    *mask = overlap_metrics(iou, valid, cats);
    ptrs.resize(objs.size());
    *box = box_metrics(ptrs, gt_boxes, valid, cats);
  };
  score(before, std::vector<bool>(before.size(), true), &ev.mask_before, &ev.box_before);
  score(after, valid_after, &ev.mask_after, &ev.box_after);
  return ev;
}

SceneEvaluation evaluate_scene(const SyntheticScene& s, const CorrectionConfig& config,
                               const std::vector<Displacement>& displacements, ResampleProxy proxy) {
  const Vec3 g = s.gravity.normalized();
  std::vector<CorrectedObject> after;
  for (size_t i = 0; i < s.objects.size(); ++i) {
    const SyntheticObject& o = s.objects[i];
    CorrectedObject c;
    c.mesh = o.pred_mesh, c.scale = o.pred_scale, c.R = o.pred_R, c.t = o.pred_t;
    if (o.dof == PoseDof::Free) {
      // Diagnose with the measured (or oracle) displacement and apply the chosen correction.
      const Displacement d = i < displacements.size() ? displacements[i] : oracle_displacement(s, o);
      const Obb obb = object_obb(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t, g);
      const Diagnosis dg = diagnose(obb, g, d.dt_pen, d.dt_grv, config);
      c.branch = dg.branch, c.rho = dg.rho, c.eta = dg.eta;
      if (dg.branch == Branch::Stretch || proxy == ResampleProxy::Stretch) {
        const StretchResult r = gravity_axis_stretch(o.pred_mesh.V, o.pred_scale, o.pred_R, o.pred_t, o.pred_R, dg, config);
        c.mesh.V = r.canonical;
        c.scale = r.scale, c.R = r.R, c.t = r.t;
      } else if (proxy == ResampleProxy::Drop) {
        c.t = o.pred_t + d.dt_pen + d.dt_grv;
      }
    }
    after.push_back(std::move(c));
  }
  return evaluate_corrected(s, after);
}

std::vector<CorrectedObject> probe_output_objects(const SyntheticScene& s, const ProbeResult& r) {
  SIMU_CHECK(r.scene.objects.size() == s.objects.size() && r.diagnostics.size() == s.objects.size(),
             "probe_output_objects: the probe result has {} objects ({} diagnostics), the synthetic scene {}",
             r.scene.objects.size(), r.diagnostics.size(), s.objects.size());
  std::vector<CorrectedObject> out;
  for (size_t i = 0; i < s.objects.size(); ++i) {
    const SyntheticObject& o = s.objects[i];
    const SceneObject& so = r.scene.objects[i];
    const Diagnostics& d = r.diagnostics[i];
    SIMU_CHECK(so.id == o.id, "probe_output_objects: object {} is '{}' in the probe result, '{}' in the scene", i,
               so.id, o.id);
    CorrectedObject c;
    const bool has_mesh = i < r.meshes.size() && r.meshes[i].V.rows() > 0;
    if (has_mesh) {
      // The corrected scene as the probe writes it: final pose and scale, the mesh it used.
      c.mesh = r.meshes[i];
      c.scale = so.scale, c.R = so.R, c.t = so.t;
    } else {
      // No usable mesh: the probe left the object out; the input reconstruction where it was.
      c.mesh = o.pred_mesh;
      c.scale = o.pred_scale, c.R = o.pred_R, c.t = o.pred_t;
    }
    c.valid = has_mesh && !d.physics_disabled;
    c.rho = d.diagnosis.rho, c.eta = d.diagnosis.eta;
    c.decided = d.branch == ProbeBranch::Stretch || d.branch == ProbeBranch::Resample;
    c.branch = d.branch == ProbeBranch::Resample ? Branch::Resample : Branch::Stretch;
    c.flags = d.flags;
    out.push_back(std::move(c));
  }
  return out;
}

SceneEvaluation evaluate_probe_output(const SyntheticScene& s, const ProbeResult& r) {
  return evaluate_corrected(s, probe_output_objects(s, r));
}

ResampleFn stretch_resampler(const SyntheticScene& s, const CorrectionConfig& config) {
  return [&s, config](const std::vector<ProbeResampleRequest>& requests) {
    const Vec3 g = s.gravity.normalized();
    std::vector<ProbeResampleResult> results;
    for (const ProbeResampleRequest& q : requests) {
      ProbeResampleResult res;
      try {
        SIMU_CHECK(q.object_index >= 0 && size_t(q.object_index) < s.objects.size(), "object index {} out of range",
                   q.object_index);
        const SyntheticObject& o = s.objects[q.object_index];
        // The input object's OBB and the stretch that turns it into the target B_str (same axes; only
        // the side along gravity differs).
        const Obb obb = object_obb(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t, g);
        const GravityAxis ax = gravity_axis(obb, g);
        const double eta = q.target_obb.extents(ax.index) / ax.length - 1.0;
        const Diagnosis dg = diagnose(obb, g, Vec3::Zero(), eta * ax.length * g, config);
        const StretchResult st = gravity_axis_stretch(o.pred_mesh.V, o.pred_scale, o.pred_R, o.pred_t, o.pred_R, dg, config);
        res.mesh = o.pred_mesh;
        res.mesh.V = st.canonical;
        res.R = st.R;
        res.scale = st.scale;
        res.ok = true;
        res.message = fmt::format("stretch proxy (eta {:.3f})", eta);
      } catch (const std::exception& e) {
        res.ok = false;
        res.message = std::string("stretch proxy: ") + e.what();
      }
      results.push_back(std::move(res));
    }
    return results;
  };
}

}  // namespace simu::physics
