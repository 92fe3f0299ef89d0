// 3D metrics of one predicted object against its ground truth, both in the world frame (eval_lift):
// each is a canonical mesh placed by a pose in the scene convention, world = R (s .* c) + t
// (docs/scene_format.md; c AABB-centred, longest side 1).
//
//   iou            voxel IoU of the filled occupancies (solid_voxels.h) on the world lattice: shape and
//                  pose together. Spacing h = min(max_voxel (1 cm), longest GT side / voxels_across), so
//                  a 2 cm object is still resolved; grows only when a grid would exceed max_voxels
//                  (a prediction metres wide), and iou_voxel records the h used.
//   fscore         at each threshold tau (1 cm, 2 cm): precision = share of the prediction's surface
//                  samples within tau of the GT surface, recall = share of the GT's samples within tau of
//                  the predicted surface, F = 2 P R / (P + R) (Tatarchenko et al. 2019), distances to the
//                  exact surface (surface_distance.h), so identical surfaces score exactly 1.
//   chamfer        symmetric L1 Chamfer distance in metres: the mean of the two directions' mean
//                  point-to-surface distances, (mean_p d(p, GT) + mean_q d(q, pred)) / 2.
//   rot_err_deg    rotation error modulo the GT's own symmetry, found from its geometry (symmetry.h).
//   trans_err      |t_pred - t_gt| in metres (the canonical origin is the AABB centre of each mesh).
//   scale_err_pct  100 |L_pred / L_gt - 1|, L = the longest side of s .* c (the object's metric size as
//                  the shape world states it: the longest AABB side in its own frame).
#pragma once

#include "pipeline/physics/scene.h"
#include "pipeline/physics/symmetry.h"

#include <cstdint>
#include <string>
#include <vector>

namespace simu::physics {

// A canonical mesh and its pose in the scene convention.
struct PlacedShape {
  Mesh canonical;
  Vec3 scale = Vec3::Ones();
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
  // The mesh in the object's metric frame, s .* c (where R acts).
  Mesh scaled() const;
  // The mesh in the world, R (s .* c) + t.
  Mesh world() const;
  // The longest side of s .* c (metres).
  double size() const;
};

struct ShapeMetricsConfig {
  double max_voxel = 0.01;                         // m: the IoU lattice's largest spacing
  int voxels_across = 50;                          // the GT's longest side spans at least this many voxels
  int64_t max_voxels = int64_t{1} << 24;           // per grid (16.8 M; above it the spacing grows)
  std::vector<double> fscore_thresholds{0.01, 0.02};  // m
  int64_t samples = 10000;                         // surface samples per mesh (F-score, Chamfer)
  uint64_t seed = 0;                               // of the surface samples
  SymmetryConfig symmetry;
};

struct FScore {
  double threshold = 0;  // m
  double precision = 0, recall = 0, f = 0;
};

struct ShapeMetrics {
  double iou = 0;
  double iou_voxel = 0;        // lattice spacing used (m)
  std::vector<FScore> fscore;  // one per ShapeMetricsConfig::fscore_thresholds
  double chamfer = 0;          // m
  double rot_err_deg = 0;
  double trans_err = 0;        // m
  double scale_err_pct = 0;
  std::string symmetry;        // Symmetry::describe() of the GT
};

// Surface scores of two world meshes: F-scores at the thresholds and the Chamfer distance.
struct SurfaceScores {
  std::vector<FScore> fscore;
  double chamfer = 0;
};
SurfaceScores surface_scores(const Mesh& pred_world, const Mesh& gt_world, const std::vector<double>& thresholds,
                             int64_t samples, uint64_t seed);

// All metrics; the GT's symmetry is found here.
ShapeMetrics shape_metrics(const PlacedShape& pred, const PlacedShape& gt, const ShapeMetricsConfig& config = {});
// The same with the GT's symmetry given (find_symmetry(gt.scaled(), config.symmetry)), for scoring
// several predictions of one object.
ShapeMetrics shape_metrics(const PlacedShape& pred, const PlacedShape& gt, const Symmetry& gt_symmetry,
                           const ShapeMetricsConfig& config = {});

}  // namespace simu::physics
