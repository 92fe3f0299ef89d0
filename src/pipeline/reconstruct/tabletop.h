// Tabletop-plane refinement for objects labelled table or desk (supplementary "Tabletop-Plane
// Refinement", Eqs. hard_snap and table_refine).
//
//   support plane (n^d, p^d)  pixels of the table's mask whose point-map normal faces up (within
//       up_angle_deg of u), then a height band: the highest height bin holding at least band_min_frac
//       of the fullest bin, +- band (clutter above, under-shelf surfaces below are cut), then RANSAC
//       (ransac_threshold) constrained to within max_tilt_deg of u;
//   mesh top (n^m, p^m)  the placed mesh's vertices within top_band (fraction of its height) of its top
//       along u: centroid p^m and least-squares normal n^m (signed along u);
//   hard_snap  T_snap(v) = R_snap v + (p^m - R_snap p^m) + delta, R_snap the smallest rotation taking
//       n^m onto n^d, delta = ((p^d - p^m) . n^d) n^d;
//   table_refine  from the snapped pose, yaw theta about n^d through the snapped top centre, in-plane
//       translation (t_x, t_y) and log-scale about the same centre, by Adam on
//       1/2 (d_{P^ -> P} + d_{P -> P^}) + lambda [(theta/theta_0)^2 + (t_x/t_0)^2 + (t_y/t_0)^2 + (log s/sigma_0)^2]
//       (P^ = the mesh's vertices visible at the snapped pose, P = the mask's depth points; d = mean
//       nearest distance), then the top re-snapped onto the plane;
//   sanity  rejected (the input pose kept, a reason given) on insufficient support (< min_support
//       points or < min_support_frac of the mask's valid points), a non-horizontal plane (angle to u
//       > max_tilt_deg) and floor degeneracy (the plane within floor_gap of the floor).
#pragma once

#include "pipeline/reconstruct/types.h"

#include <optional>
#include <string>

namespace simu::reconstruct {

struct TabletopConfig {
  double up_angle_deg = 30;       // upward-facing pixels
  double height_bin = 0.01;       // m
  double band = 0.03;             // m, +- around the support height
  double band_min_frac = 0.2;
  double ransac_threshold = 0.01; // m
  int ransac_iterations = 300;
  double max_tilt_deg = 10;
  int64_t min_support = 50;
  double min_support_frac = 0.05;
  double floor_gap = 0.05;        // m
  double top_band = 0.03;         // fraction of the mesh height
  // table_refine
  int iterations = 200;
  double lambda = 1e-3;
  double theta0_deg = 10, t0 = 0.05, sigma0 = 0.1;
  double lr_theta_deg = 0.5, lr_t = 0.005, lr_log_s = 0.005;
  double max_edge = 1.0 / 40;     // canonical densification (as the alignment's)
  double visibility_tol = 0.01;
  int64_t max_points = 3000;
};

struct TabletopInput {
  std::string id;
  Points canonical;
  Faces faces;
  Vec3 scale = Vec3::Ones();
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
  const PointMap* points = nullptr;  // the photo's point map (camera frame)
  Mask mask;                         // the table's visible mask
  Pinhole K;
  Vec3 up = -Vec3::UnitY();
  std::optional<PlaneFit> floor;     // for the degeneracy check
};

struct TabletopResult {
  bool ok = false;                   // refined (false: rejected, pose unchanged)
  std::string message;               // the rejection reason
  PlaneFit support;                  // (n^d, p^d)
  PlaneFit mesh_top;                 // (n^m, p^m) before the snap
  Similarity snap;                   // T_snap (s = 1)
  Similarity refine;                 // the 4-DoF refinement after the snap
  Similarity total;                  // refine o snap (world similarity applied to the placed mesh)
  double theta_deg = 0, tx = 0, ty = 0, log_s = 0;
  double chamfer_before = 0, chamfer_after = 0;  // symmetric chamfer at the snapped / refined pose
  // The new pose: world = R (scale .* c) + t.
  Vec3 scale = Vec3::Ones();
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
};

// Per-pixel unit normals of a point map (cross product of central differences; NaN where undefined),
// oriented towards the camera.
std::vector<Vec3> point_map_normals(const PointMap& map);

// The depth-supported top plane of a table mask (the first step above); nullopt with a reason.
std::optional<PlaneFit> table_support_plane(const TabletopInput& in, const TabletopConfig& cfg, std::string* why);

// The whole refinement.
TabletopResult refine_tabletop(const TabletopInput& in, const TabletopConfig& config = {});

// Whether a label names a table or desk (case-insensitive substring "table" or "desk").
bool is_table_label(const std::string& label);

}  // namespace simu::reconstruct
