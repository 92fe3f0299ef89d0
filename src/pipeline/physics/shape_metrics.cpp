// World-frame 3D metrics of a predicted object against its ground truth.
#include "pipeline/physics/shape_metrics.h"

#include <algorithm>
#include <cmath>

#include "common/error.h"
#include "common/random.h"
#include "pipeline/physics/solid_voxels.h"
#include "pipeline/physics/surface_distance.h"

namespace simu::physics {

Mesh PlacedShape::scaled() const { return transform_mesh(canonical, scale.asDiagonal(), Vec3::Zero()); }

Mesh PlacedShape::world() const { return transform_mesh(canonical, R * scale.asDiagonal(), t); }

double PlacedShape::size() const {
  if (canonical.V.rows() == 0) return 0;
  const Vec3 extent = (canonical.V.colwise().maxCoeff() - canonical.V.colwise().minCoeff()).transpose();
  return extent.cwiseProduct(scale.cwiseAbs()).maxCoeff();
}

SurfaceScores surface_scores(const Mesh& pred_world, const Mesh& gt_world, const std::vector<double>& thresholds,
                             int64_t samples, uint64_t seed) {
  // Independent sample streams for the two meshes.
  const Points pred_pts = sample_surface(pred_world, samples, splitmix64(seed ^ 0x70726564ULL));
  const Points gt_pts = sample_surface(gt_world, samples, splitmix64(seed ^ 0x67740000ULL));
  const std::vector<double> to_gt = SurfaceDistance(gt_world).distances(pred_pts);    // precision side
  const std::vector<double> to_pred = SurfaceDistance(pred_world).distances(gt_pts);  // recall side
  SurfaceScores s;
  for (double tau : thresholds) {
    FScore f;
    f.threshold = tau;
    f.precision = static_cast<double>(std::count_if(to_gt.begin(), to_gt.end(), [&](double d) { return d <= tau; })) /
                  static_cast<double>(to_gt.size());
    f.recall = static_cast<double>(std::count_if(to_pred.begin(), to_pred.end(), [&](double d) { return d <= tau; })) /
               static_cast<double>(to_pred.size());
    f.f = f.precision + f.recall > 0 ? 2 * f.precision * f.recall / (f.precision + f.recall) : 0.0;
    s.fscore.push_back(f);
  }
  double a = 0, b = 0;
  for (double d : to_gt) a += d;
  for (double d : to_pred) b += d;
  s.chamfer = 0.5 * (a / static_cast<double>(to_gt.size()) + b / static_cast<double>(to_pred.size()));
  return s;
}

ShapeMetrics shape_metrics(const PlacedShape& pred, const PlacedShape& gt, const ShapeMetricsConfig& config) {
  return shape_metrics(pred, gt, find_symmetry(gt.scaled(), config.symmetry), config);
}

ShapeMetrics shape_metrics(const PlacedShape& pred, const PlacedShape& gt, const Symmetry& gt_symmetry,
                           const ShapeMetricsConfig& config) {
  SIMU_CHECK(config.max_voxel > 0 && config.voxels_across > 0, "shape metrics: max_voxel {} and voxels_across {} must "
             "be positive", config.max_voxel, config.voxels_across);
  for (const PlacedShape* s : {&pred, &gt})
    SIMU_CHECK(s->scale.allFinite() && s->R.allFinite() && s->t.allFinite(), "shape metrics: the {} pose is not finite",
               s == &pred ? "predicted" : "ground-truth");
  const double gt_size = gt.size();
  SIMU_CHECK(gt_size > 0, "shape metrics: the ground-truth mesh has no extent");
  const Mesh pred_world = pred.world(), gt_world = gt.world();
  ShapeMetrics m;
  const SolidIou iou = solid_iou(pred_world, gt_world, std::min(config.max_voxel, gt_size / config.voxels_across),
                                 config.max_voxels);
  m.iou = iou.iou;
  m.iou_voxel = iou.h;
  const SurfaceScores s = surface_scores(pred_world, gt_world, config.fscore_thresholds, config.samples, config.seed);
  m.fscore = s.fscore;
  m.chamfer = s.chamfer;
  m.rot_err_deg = rotation_error_deg(pred.R, gt.R, gt_symmetry);
  m.trans_err = (pred.t - gt.t).norm();
  m.scale_err_pct = 100.0 * std::abs(pred.size() / gt_size - 1.0);
  m.symmetry = gt_symmetry.describe();
  return m;
}

}  // namespace simu::physics
