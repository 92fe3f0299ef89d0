// eval_lift's pose refinement by the SimuScene alignment (eval_align.h).
#include "pipeline/reconstruct/eval_align.h"

#include <fmt/format.h>

#include <cmath>
#include <limits>

namespace simu::reconstruct {

namespace {

// The world shape-world point map [H, W, 3] (OpenCV camera frame) -> PointMap; invalid pixels NaN.
PointMap to_points(const world::PointMap& pm) {
  PointMap out;
  out.width = pm.width;
  out.height = pm.height;
  const size_t n = size_t(pm.width) * size_t(pm.height);
  out.p.resize(n);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (size_t i = 0; i < n; ++i)
    out.p[i] = pm.valid(i) ? Vec3(pm.xyz[3 * i], pm.xyz[3 * i + 1], pm.xyz[3 * i + 2]) : Vec3(nan, nan, nan);
  return out;
}

Mask to_mask(const physics::BinaryMask& m) {
  Mask out(m.width, m.height);
  for (size_t i = 0; i < m.data.size(); ++i) out.data[i] = m.data[i] ? 1 : 0;
  return out;
}

// The prediction in the camera frame (OpenCV, the point map's) as the alignment's input; "" or why not.
std::string align_input(const physics::PlacedShape& pred, const resample::RefineInput& in, const PointMap& pm,
                        AlignInput& ai) {
  const physics::Camera& cam = *in.camera;
  if (in.pointmap->width != cam.width || in.pointmap->height != cam.height || in.modal->width != cam.width ||
      in.modal->height != cam.height)
    return fmt::format("{}: point map {}x{} or mask {}x{} is not the camera's {}x{}", in.id, in.pointmap->width,
                       in.pointmap->height, in.modal->width, in.modal->height, cam.width, cam.height);
  ai.id = in.id;
  ai.canonical = pred.canonical.V;
  ai.faces = pred.canonical.F;
  ai.s_init = pred.scale.maxCoeff();
  ai.shape = pred.scale / ai.s_init;
  // Camera frame: p_cam = R_wc^T (p_world - t_wc).
  ai.R_init = cam.R_world_cam.transpose() * pred.R;
  ai.t_init = cam.R_world_cam.transpose() * (pred.t - cam.t_world_cam);
  ai.mask = to_mask(*in.modal);
  ai.observed = masked_points(pm, ai.mask, in.id);
  ai.K = Pinhole{cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height};
  ai.depth = &pm;
  return "";
}

// The translation-scale alignment of one prediction: fills ai (from pm) and r, sets pred's scale and
// translation. Returns "" when aligned, else why not (pred unchanged).
std::string align_prediction(physics::PlacedShape& pred, const resample::RefineInput& in, const PointMap& pm,
                             const AlignConfig& config, AlignInput& ai, AlignResult& r) {
  if (std::string why = align_input(pred, in, pm, ai); !why.empty()) return why;
  r = align_translation_scale(ai, config);
  if (!r.ok) return r.message.empty() ? in.id + ": not aligned" : r.message;
  pred.scale = r.s * ai.shape;
  pred.t = in.camera->R_world_cam * r.t + in.camera->t_world_cam;
  return "";
}

}  // namespace

resample::PoseRefiner alignment_refiner(const AlignConfig& config) {
  return [config](physics::PlacedShape& pred, const resample::RefineInput& in) -> std::string {
    const PointMap pm = to_points(*in.pointmap);
    AlignInput ai;
    AlignResult r;
    return align_prediction(pred, in, pm, config, ai, r);
  };
}

resample::PoseRefiner icp_refiner(const AlignConfig& align, const IcpConfig& icp) {
  return [align, icp](physics::PlacedShape& pred, const resample::RefineInput& in) -> std::string {
    const physics::Camera& cam = *in.camera;
    const PointMap pm = to_points(*in.pointmap);
    AlignInput ai;
    AlignResult r;
    if (std::string why = align_prediction(pred, in, pm, align, ai, r); !why.empty()) return why;
    // The rotation refined from the aligned pose; up = -gravity in the camera frame.
    ai.s_init = r.s;
    ai.t_init = r.t;
    const Vec3 up = -(cam.R_world_cam.transpose() * in.gravity);
    const IcpResult q = refine_rotation_icp(ai, up, icp);
    if (!q.changed) return q.message.empty() ? in.id + ": icp kept the aligned pose" : q.message;
    pred.R = cam.R_world_cam * q.R;
    pred.scale = q.s * ai.shape;
    pred.t = cam.R_world_cam * q.t + cam.t_world_cam;
    return "";
  };
}

resample::PoseScorer render_compare_scorer(const IcpConfig& icp) {
  return [icp](const physics::PlacedShape& pred, const resample::RefineInput& in) -> double {
    const PointMap pm = to_points(*in.pointmap);
    AlignInput ai;
    if (!align_input(pred, in, pm, ai).empty()) return std::numeric_limits<double>::infinity();
    return pose_score(ai, ai.R_init, ai.s_init, ai.t_init, icp);
  };
}

}  // namespace simu::reconstruct
