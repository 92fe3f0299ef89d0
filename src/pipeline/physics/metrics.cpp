// Aggregation of the paper's physics and overlap metrics.
#include "pipeline/physics/metrics.h"

#include "common/error.h"

#include <algorithm>
#include <cmath>

namespace simu::physics {

MetricCategory metric_category(PoseDof dof) {
  return dof == PoseDof::Free ? MetricCategory::Free : MetricCategory::Hanging;
}

bool is_valid(const SettleRecord& r, const MetricsConfig& c) {
  if (r.physics_disabled) return false;
  if (!(r.max_penetration <= c.penetration_depth)) return false;
  if (c.unstable_is_invalid && r.category == MetricCategory::Free && !(r.displacement < c.stable_displacement))
    return false;
  return true;
}

PhysicsMetrics physics_metrics(const std::vector<SettleRecord>& objects, const MetricsConfig& c,
                               double scene_peak_energy) {
  PhysicsMetrics m;
  int stable = 0, penetrating = 0, initially = 0;
  double disp = 0, peak = 0;
  for (const SettleRecord& r : objects) {
    if (r.category == MetricCategory::Fixed) continue;
    if (r.physics_disabled) {
      ++m.disabled_count;
      continue;
    }
    // Penetration ratio, mean displacement and peak energy over every evaluated object.
    ++m.evaluated_count;
    penetrating += r.max_penetration > c.penetration_depth;
    initially += r.initially_penetrating;
    disp += r.displacement;
    peak = std::max(peak, r.peak_kinetic_energy);
    // Stability over free objects that did not start out penetrating.
    if (r.category == MetricCategory::Free && !r.initially_penetrating) {
      ++m.stability_count;
      stable += r.displacement < c.stable_displacement;
    }
  }
  m.stability = m.stability_count ? 100.0 * stable / m.stability_count : 0.0;
  m.penetration_ratio = m.evaluated_count ? 100.0 * penetrating / m.evaluated_count : 0.0;
  m.initial_penetration_ratio = m.evaluated_count ? 100.0 * initially / m.evaluated_count : 0.0;
  m.mean_displacement = m.evaluated_count ? disp / m.evaluated_count : 0.0;
  m.peak_energy = scene_peak_energy >= 0 ? scene_peak_energy : peak;
  return m;
}

double mask_iou(const BinaryMask& a, const BinaryMask& b) {
  SIMU_CHECK(a.width == b.width && a.height == b.height, "mask_iou: size {}x{} vs {}x{}", a.width, a.height, b.width,
             b.height);
  int64_t inter = 0, uni = 0;
  for (size_t i = 0; i < a.data.size(); ++i) {
    const bool x = a.data[i] != 0, y = b.data[i] != 0;
    inter += x && y;
    uni += x || y;
  }
  return uni ? double(inter) / double(uni) : 0.0;
}

double box_iou(const Box3& a, const Box3& b) {
  auto vol = [](const Vec3& lo, const Vec3& hi) { return (hi - lo).cwiseMax(0.0).prod(); };
  const double inter = vol(a.min.cwiseMax(b.min), a.max.cwiseMin(b.max));
  const double uni = vol(a.min, a.max) + vol(b.min, b.max) - inter;
  return uni > 0 ? inter / uni : 0.0;
}

Box3 world_aabb(const Mesh& m) {
  SIMU_CHECK(m.V.rows() > 0, "mesh_aabb: empty mesh");
  Box3 b;
  b.min = m.V.colwise().minCoeff().transpose();
  b.max = m.V.colwise().maxCoeff().transpose();
  return b;
}

OverlapMetrics overlap_metrics(const std::vector<std::vector<double>>& iou, const std::vector<bool>& valid,
                               const std::vector<MetricCategory>& category) {
  OverlapMetrics m;
  const size_t n = iou.size();
  SIMU_CHECK(valid.size() >= n && category.size() >= n, "overlap_metrics: {} ground-truth rows but {} valid flags and {} categories",
             n, valid.size(), category.size());
  const size_t n_pred = category.size();
  m.n_gt = int(n);
  auto in_fh = [&](size_t j) { return category[j] != MetricCategory::Fixed; };
  auto in_fo = [&](size_t j) { return category[j] == MetricCategory::Free; };
  double s_iou = 0, s_abo = 0, s_iou_fh = 0, s_iou_fo = 0, s_abo_fh = 0, s_abo_fo = 0;
  for (size_t i = 0; i < n; ++i) {
    const std::vector<double>& row = iou[i];
    const double ident = i < row.size() ? row[i] : 0.0;
    // Best overlap over all predictions / over the valid ones of each strict set.
    double best = 0, best_fh = 0, best_fo = 0;
    for (size_t j = 0; j < row.size() && j < n_pred; ++j) {
      best = std::max(best, row[j]);
      if (valid[j] && in_fh(j)) best_fh = std::max(best_fh, row[j]);
      if (valid[j] && in_fo(j)) best_fo = std::max(best_fo, row[j]);
    }
    s_iou += ident;
    s_abo += best;
    if (in_fh(i)) {
      ++m.n_fh;
      s_iou_fh += valid[i] ? ident : 0.0;
      s_abo_fh += best_fh;
    }
    if (in_fo(i)) {
      ++m.n_fo;
      s_iou_fo += valid[i] ? ident : 0.0;
      s_abo_fo += best_fo;
    }
  }
  if (m.n_gt) m.iou = s_iou / m.n_gt, m.abo = s_abo / m.n_gt;
  if (m.n_fh) m.iou_fh = s_iou_fh / m.n_fh, m.abo_fh = s_abo_fh / m.n_fh;
  if (m.n_fo) m.iou_fo = s_iou_fo / m.n_fo, m.abo_fo = s_abo_fo / m.n_fo;
  return m;
}

OverlapMetrics mask_metrics(const Camera& cam, const std::vector<const Mesh*>& world_meshes,
                            const std::vector<BinaryMask>& gt_masks, const std::vector<bool>& valid,
                            const std::vector<MetricCategory>& category) {
  const LabelImage img = render_labels(cam, world_meshes);
  std::vector<BinaryMask> pred;
  for (size_t j = 0; j < world_meshes.size(); ++j) pred.push_back(img.mask_of(int(j)));
  std::vector<std::vector<double>> iou(gt_masks.size(), std::vector<double>(pred.size(), 0.0));
  for (size_t i = 0; i < gt_masks.size(); ++i)
    for (size_t j = 0; j < pred.size(); ++j) iou[i][j] = mask_iou(gt_masks[i], pred[j]);
  return overlap_metrics(iou, valid, category);
}

OverlapMetrics box_metrics(const std::vector<const Mesh*>& world_meshes, const std::vector<Box3>& gt_boxes,
                           const std::vector<bool>& valid, const std::vector<MetricCategory>& category) {
  std::vector<std::vector<double>> iou(gt_boxes.size(), std::vector<double>(world_meshes.size(), 0.0));
  for (size_t j = 0; j < world_meshes.size(); ++j) {
    if (!world_meshes[j] || world_meshes[j]->V.rows() == 0) continue;
    const Box3 p = world_aabb(*world_meshes[j]);
    for (size_t i = 0; i < gt_boxes.size(); ++i) iou[i][j] = box_iou(gt_boxes[i], p);
  }
  return overlap_metrics(iou, valid, category);
}

}  // namespace simu::physics
