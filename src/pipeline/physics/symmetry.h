// A shape's rotational self-symmetries, found from its geometry, and the rotation error modulo them
// (the rotation error of shape_metrics.h).
//
// Why from the geometry: the objects come from the shape world's families and from any folder of
// meshes, so no family label can be trusted to say what the symmetry is. A rotation S about the
// surface centroid is a symmetry when the shape and its rotated copy are indistinguishable: their
// mean symmetric surface distance (Chamfer, point samples to the exact surface) is below
// `tolerance` times the shape's longest side. Candidates, each tested:
//   - discrete: the 24 proper rotations that map a frame's axes onto its signed axes (the cube's
//     rotation group: 180-degree flips of a box, 90-degree turns of a square prism, all of a cube),
//     for two frames: the mesh's own axes (a canonical mesh is AABB-aligned, as the world builds it)
//     and the principal axes of its surface's second moments (exact triangle integrals), the latter
//     only when some principal axis is over 10 degrees from every mesh axis;
//   - continuous: rotations about each of those six axes by 17, 53, 97 and 151 degrees, none a
//     multiple of 360 / n for a small n; an axis that passes all four is a continuous symmetry axis
//     (lathes, cylinders, cones; an n-gon prism only when it is round to within the tolerance).
// Any proper symmetry of a surface maps its second-moment ellipsoid to itself, so it permutes the
// principal axes; the second frame therefore finds the symmetries of shapes whose axes are not the
// mesh's. Near a symmetry S, rotations S R(e) for small e pass the tolerance too; a candidate within
// 10 degrees of an accepted rotation (or axis) is taken as that one, the mesh-axis candidates first:
// two distinct symmetries that close would compose to a symmetry of order > 36, which the continuous
// test classifies as round.
//
// Rotation error: with symmetry group G of the ground truth (in its scaled canonical frame, where the
// world pose R acts), err = min over S in G of angle(R_gt S, R_pred) (geodesic, degrees). With one
// continuous axis a the minimum over the rotations about a is the angle between R_gt S a and R_pred a
// (any rotation taking a to b turns by at least angle(a, b), and the one about a x b by exactly that);
// with two non-parallel continuous axes (a sphere) every rotation is a symmetry and the error is 0.
#pragma once

#include "pipeline/physics/scene.h"

#include <cstdint>
#include <string>
#include <vector>

namespace simu::physics {

struct SymmetryConfig {
  double tolerance = 0.01;   // relative to the longest side: mean symmetric surface distance below it = symmetric
  int64_t samples = 2000;    // surface points per test
  uint64_t seed = 0;         // of the surface samples
};

// The symmetries found.
struct Symmetry {
  Vec3 centre = Vec3::Zero();      // the surface centroid the rotations turn about
  std::vector<Mat3> rotations;     // discrete proper rotations (the identity first), no two alike
  std::vector<Vec3> axes;          // continuous symmetry axes (unit), no two parallel
  bool spherical() const { return axes.size() >= 2; }
  // "none", "discrete-<n>" (n rotations including the identity), "axial" (one continuous axis, plus
  // "+flip" when a 180-degree turn reverses it) or "spherical".
  std::string describe() const;
};

// The symmetries of a mesh in its own frame (for the rotation error: the ground truth's canonical mesh
// scaled by its metric scale, s .* c). Throws simu::Error when the mesh has no triangle of positive area.
Symmetry find_symmetry(const Mesh& shape, const SymmetryConfig& config = {});

// Geodesic angle of a rotation (degrees, in [0, 180]).
double rotation_angle_deg(const Mat3& R);
// min over the symmetries of the geodesic angle between R_gt S and R_pred (degrees), as above.
double rotation_error_deg(const Mat3& R_pred, const Mat3& R_gt, const Symmetry& gt_symmetry);

// Rotation of `angle` radians about the unit `axis`.
Mat3 axis_rotation(const Vec3& axis, double angle);

}  // namespace simu::physics
