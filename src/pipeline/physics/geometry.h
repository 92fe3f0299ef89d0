// Gravity diagnostics and the gravity-axis stretch of the paper (Sec. 3.3 "Displacement-Based Shape
// Correction Criterion", Sec. 3.4 "Gravity-axis Stretch" / "Amodal Shape Resampling", and the
// supplementary "Gravity-axis Stretch Details").
//
// Notation (paper):  g = unit gravity direction; B_pre = OBB of the pre-simulation world mesh;
//   u = the OBB axis most aligned with g, oriented so that u.g >= 0 (it points "down");
//   l_pre = side length of B_pre along u;  d = dt_pen + dt_grv (penetration + gravity displacement);
//   rho = |g.d| / l_pre,  eta = g.d / l_pre;  rho >= threshold (0.15) -> resample, else stretch.
//   Stretch: a = R_pre^T u (canonical axis), lambda = 1 + eta,
//            v' = lambda (v.a) a + (I - a a^T) v             (canonical frame, about the origin)
//            M_str = M_bar / gamma, s_str = gamma s          (gamma = longest AABB side of M_bar)
//            t_str = t_pre + 0.5 eta l_pre u                 (the anti-gravity OBB face stays put)
//
// The scene stores a per-axis scale s (world x = R (s .* v) + t, see scene.h). For an isotropic s
// the functions below reproduce the paper's equations literally. For an anisotropic s the stretch is
// applied to the scaled canonical vertices (s .* v), which is the same world-space operation.
#pragma once

#include "common/config.h"
#include "pipeline/physics/scene.h"

#include <array>
#include <string>

namespace simu::physics {

// Row-major [n, 3] point set (same layout as Mesh::V).
using Points = Eigen::Matrix<double, -1, 3, Eigen::RowMajor>;

// An oriented bounding box. axes.col(k) is a unit axis (right-handed frame), extents(k) the FULL
// side length along it; the box is {center + axes * y : |y_k| <= extents_k / 2}.
struct Obb {
  Vec3 center = Vec3::Zero();
  Mat3 axes = Mat3::Identity();
  Vec3 extents = Vec3::Zero();

  double volume() const { return extents.prod(); }
  // The 8 corners; corner c has local sign (+/-) per axis from bits 0,1,2 of c (bit set = +).
  std::array<Vec3, 8> corners() const;
  // True when x lies inside the box grown by tol on every side.
  bool contains(const Vec3& x, double tol = 1e-9) const;
  // A closed triangle mesh of the box (8 vertices, 12 triangles, outward counter-clockwise).
  Mesh to_mesh() const;
};

// Whether the segment from a to b misses the axis-aligned box [lo, hi] (slab test; touching counts as a hit).
bool segment_misses_box(const Vec3& a, const Vec3& b, const Vec3& lo, const Vec3& hi);

// How compute_obb searches. Deterministic: a fixed list of candidate frames, each refined by
// minimum-area rectangles (rotating calipers) in the plane orthogonal to each of its axes; the
// smallest-volume box wins (ties keep the earlier candidate).
struct ObbOptions {
  bool use_pca = true;          // principal axes of the points
  bool use_world_axes = true;   // the world axes (after the hints and PCA)
  bool refine_calipers = true;  // min-area rectangle refinement around each candidate axis
  double tie_tolerance = 1e-9;  // relative volume difference treated as a tie
};

// OBB of a point set (world vertices). `hint` frames (e.g. R_pre, the identity, a gravity-aligned
// frame) are tried first in the given order, so a mesh's own canonical frame wins ties. Throws
// simu::Error on an empty or non-finite point set.
Obb compute_obb(const Points& points, const std::vector<Mat3>& hints = {}, const ObbOptions& options = {});

// Frame whose third axis is n and whose first axis is the edge direction of the minimum-area
// rectangle enclosing the points projected on the plane orthogonal to n (rotating calipers over the
// edges of their 2-D convex hull). Returns false for a degenerate projection (fewer than 3 hull points).
bool caliper_frame(const Points& P, const Vec3& n, Mat3* out);

// OBB of an object in the pre-simulation scene, eq. (obb_pre): OBB(R (s .* M) + t). The object's
// own rotation, the identity and a gravity-aligned frame are the hints (in this order).
Obb object_obb(const Mesh& canonical, const Vec3& scale, const Mat3& R, const Vec3& t, const Vec3& gravity);

// The OBB axis most aligned with the unit gravity direction.
struct GravityAxis {
  int index = 0;              // which column of Obb::axes
  Vec3 u = Vec3::UnitZ();     // that axis, oriented so that u.g >= 0 (points along gravity)
  double length = 0;          // l_pre: the OBB side length along u
  double alignment = 0;       // |u.g| (1 = exactly vertical)
};
GravityAxis gravity_axis(const Obb& obb, const Vec3& gravity);

// Which correction a free object gets.
enum class Branch { Stretch, Resample };
const char* to_string(Branch b);

// Decision parameters (the paper's defaults).
struct CorrectionConfig {
  double resample_threshold = 0.15;  // rho >= this -> resample
  double min_lambda = 0.05;          // smallest stretch factor accepted (eta <= -0.95 is clamped)
  double lowest_part_margin = 0.0;   // extra height of M''s lowest part, as a fraction of l_pre
  static CorrectionConfig from(simu::config::Reader& r);
};

// rho, eta and the branch for one object, eqs. (stretch_ratio), (stretch_displacement).
struct Diagnosis {
  Obb obb_pre;
  GravityAxis axis;
  double g_displacement = 0;  // g.(dt_pen + dt_grv), metres (positive = moved along gravity)
  double rho = 0;
  double eta = 0;
  Branch branch = Branch::Stretch;
};
// Throws simu::Error when l_pre is not positive or an input is not finite.
Diagnosis diagnose(const Obb& obb_pre, const Vec3& gravity, const Vec3& dt_pen, const Vec3& dt_grv,
                   const CorrectionConfig& config = {});

// The stretched object (M_str, s_str, t_str, R). When the stretch axis a is (to 1e-9) a canonical
// axis k, the stretch folds into the per-axis scale and the mesh is unchanged (mesh_changed false,
// canonical = the input); otherwise canonical holds the new AABB-centred, longest-side-1 vertices
// (faces unchanged) and scale is isotropic gamma (times the old isotropic scale). Both describe
// the same world geometry.
struct StretchResult {
  Points canonical;           // M_str vertices (faces are those of the input mesh)
  bool mesh_changed = false;
  Vec3 scale = Vec3::Ones();  // s_str
  Mat3 R = Mat3::Identity();  // dR_grv R_pre (unchanged by the stretch)
  Vec3 t = Vec3::Zero();      // t_str = t_pre + 0.5 eta l_pre u
  double lambda = 1;          // 1 + eta (clamped below at CorrectionConfig::min_lambda)
  double gamma = 1;           // longest AABB side of the stretched (scaled) canonical mesh
  Vec3 axis_canonical = Vec3::UnitZ();  // a = R_pre^T u
  // Movement of the anti-gravity OBB face along u (world, metres): 0 when the canonical origin is
  // the OBB centre along u, as the paper's translation update assumes.
  double top_face_shift = 0;
};
StretchResult gravity_axis_stretch(const Points& canonical, const Vec3& scale, const Mat3& R_pre, const Vec3& t_pre,
                                   const Mat3& R_after, const Diagnosis& d, const CorrectionConfig& config = {});

// B_str: B_pre stretched along u by eta * l_pre with its anti-gravity face fixed (the desired OBB of
// the resampling branch; its centre is the resampled object's translation t_re).
Obb stretched_obb(const Diagnosis& d, const CorrectionConfig& config = {});

// The "lowest part" of B_str used for the auxiliary crop mask M': the slab of B_str between its
// gravity-most face and the gravity-most face of B_pre (the extent the simulation says is missing
// below the reconstructed shape), grown upward by lowest_part_margin * l_pre. Empty (nullopt) when
// eta <= 0 and the margin is 0 (nothing is missing below the object).
std::optional<Obb> lowest_part(const Diagnosis& d, const CorrectionConfig& config = {});

}  // namespace simu::physics
