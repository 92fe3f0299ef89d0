// The paper's evaluation metrics (supplementary "Metrics"): stability, penetration ratio, mean
// displacement, peak kinetic energy, 2D IoU / ABO from rendered visible masks, 3D AABB IoU / ABO,
// and the strict fh / fo variants that zero invalid instances.
//
// The physics numbers come from the probe's evaluation settle (5 s under gravity) as one plain
// record per object (SettleRecord); this file only aggregates them.
#pragma once

#include "pipeline/physics/raster.h"
#include "pipeline/physics/scene.h"

#include <string>
#include <vector>

namespace simu::physics {

// What an object is for the metrics: free (6-DoF), hanging (point/line anchored), or fixed (a base;
// never counted by fh/fo).
enum class MetricCategory { Free, Hanging, Fixed };
MetricCategory metric_category(PoseDof dof);

// Per-object outcome of a settle (the probe's final joint settle or the 5 s evaluation settle).
struct SettleRecord {
  MetricCategory category = MetricCategory::Free;
  bool physics_disabled = false;       // flagged by penetration resolution / bad input: invalid
  bool initially_penetrating = false;  // penetrating (> eps) at the start of the settle
  double displacement = 0;             // |final - initial| position of the object (metres)
  double initial_penetration = 0;      // deepest contact depth of the object before the settle (metres)
  double max_penetration = 0;          // deepest contact depth of the object after the settle (metres)
  double peak_kinetic_energy = 0;      // max over time of this object's kinetic energy (J)
};

// Thresholds (paper defaults).
struct MetricsConfig {
  double stable_displacement = 0.05;  // metres: stable when displacement < this
  double penetration_depth = 0.002;   // metres: penetrating when a contact is deeper than this
  // Invalid instances for fh / fo: penetrating or physics-disabled; and, when set, unstable free ones.
  bool unstable_is_invalid = true;
};

// Physics metrics of one scene.
struct PhysicsMetrics {
  double stability = 0;          // percent of free, not initially penetrating objects with displacement < 5 cm
  int stability_count = 0;       // its denominator
  double penetration_ratio = 0;  // percent of evaluated (not disabled, not fixed) objects with a contact > 2 mm
  int evaluated_count = 0;       // its denominator
  double mean_displacement = 0;  // metres, mean over evaluated objects
  double peak_energy = 0;        // J: scene_peak_energy when given (>= 0), else max of the per-object peaks
  double initial_penetration_ratio = 0;  // percent of evaluated objects penetrating (> 2 mm) at the start
  int disabled_count = 0;        // objects left out as physics-disabled
};
// scene_peak_energy: max over time of the total kinetic energy, if the probe measured it (< 0: not given).
PhysicsMetrics physics_metrics(const std::vector<SettleRecord>& objects, const MetricsConfig& config = {},
                               double scene_peak_energy = -1);

// True when the object counts as valid for the fh / fo variants.
bool is_valid(const SettleRecord& r, const MetricsConfig& config = {});

// Intersection over union of two masks of the same size (0 when both are empty).
double mask_iou(const BinaryMask& a, const BinaryMask& b);
// IoU of two world AABBs (0 when both are empty).
double box_iou(const Box3& a, const Box3& b);
// World AABB of a mesh's vertices.
Box3 world_aabb(const Mesh& world_mesh);

// Scores of one metric family (2D masks or 3D boxes).
struct OverlapMetrics {
  double iou = 0;     // mean identity-paired IoU over the ground-truth objects
  double abo = 0;     // (1 / N_gt) sum_i max_j IoU(g_i, p_j)
  double iou_fh = 0, iou_fo = 0, abo_fh = 0, abo_fo = 0;  // strict variants
  double iou_fhfo() const { return 0.5 * (iou_fh + iou_fo); }
  double abo_fhfo() const { return 0.5 * (abo_fh + abo_fo); }
  int n_gt = 0, n_fh = 0, n_fo = 0;
};

// Overlap metrics from a matrix iou(i, j) of ground truth i vs prediction j (prediction i is the
// identity pair of ground truth i; missing predictions score 0). valid[i] / category[i] describe
// prediction i (fh: free + hanging, fo: free; invalid ones score 0, fixed ones are left out).
OverlapMetrics overlap_metrics(const std::vector<std::vector<double>>& iou, const std::vector<bool>& valid,
                               const std::vector<MetricCategory>& category);

// 2D: renders the predicted world meshes jointly from the camera (visible surfaces), then compares
// each visible mask with the ground-truth masks. gt_masks[i] pairs with world_meshes[i].
OverlapMetrics mask_metrics(const Camera& cam, const std::vector<const Mesh*>& world_meshes,
                            const std::vector<BinaryMask>& gt_masks, const std::vector<bool>& valid,
                            const std::vector<MetricCategory>& category);
// 3D: AABB IoU of each predicted world mesh against the ground-truth boxes.
OverlapMetrics box_metrics(const std::vector<const Mesh*>& world_meshes, const std::vector<Box3>& gt_boxes,
                           const std::vector<bool>& valid, const std::vector<MetricCategory>& category);

}  // namespace simu::physics
