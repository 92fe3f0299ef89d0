// A table or desk fitted as a box from its mask and the point map, instead of lifted (sidecar
// "fit": "box"). The miniature never saw a scene table: its lifted tables are often a fraction of the
// real top or miss the floor, and what stood on them falls (docs/results.md, the ablation). A fixed base
// needs only its support surface and its footprint, which the depth measures directly:
//
//   top plane   table_support_plane (tabletop.h): the upward-facing pixels of the mask, the highest
//               well-populated height band, RANSAC within max_tilt_deg of up; its normal n is the box's up;
//   footprint   the mask's valid points at or below the top (+ band) projected onto the plane: the
//               minimum-area rectangle of their convex hull gives the yaw, the [q, 1 - q] quantiles of
//               the points along its two sides the extents (q = footprint_trim: flying pixels);
//   height      from the top down to the floor plane when one is fitted, else to the mask's lowest point
//               (legs, apron), at least min_height.
//
// The box is what the shape world's own physics uses for its table (world/settle.cpp: the table as its
// bounding box; nothing stands under it). Only the visible part of the top is measured: a top cut by
// the image border ends at the border.
#pragma once

#include "pipeline/reconstruct/tabletop.h"

namespace simu::reconstruct {

struct SupportBoxConfig {
  double footprint_trim = 0.005;  // quantile cut at each end of each side (flying pixels)
  double min_height = 0.02;       // m
};

struct SupportBoxResult {
  bool ok = false;
  std::string message;            // the rejection reason (ok = false)
  PlaneFit top;                   // the support plane (normal = the box's up)
  Vec3 extents = Vec3::Zero();    // side a, side b (in the plane), height (along the normal), metres
  double yaw_deg = 0;             // side a's angle in the plane (from the plane basis' first axis)
  int64_t points = 0;             // mask points in the footprint
  // The placed box: world = R (scale .* c) + t with the canonical unit cube c in [-0.5, 0.5]^3.
  Points canonical = Points(0, 3);
  Faces faces = Faces(0, 3);
  Vec3 scale = Vec3::Ones();
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
};

// The minimum-area enclosing rectangle of 2-D points: the angle (radians) of one side; the other is
// perpendicular (physics::caliper_frame, the OBB's rotating calipers).
double min_area_rectangle_angle(const std::vector<Eigen::Vector2d>& pts);

// The fit above. in.canonical / faces / pose are not used (the box replaces the lift); in.up, mask,
// points and floor are.
SupportBoxResult fit_support_box(const TabletopInput& in, const TabletopConfig& tabletop = {},
                                 const SupportBoxConfig& config = {});

}  // namespace simu::reconstruct
