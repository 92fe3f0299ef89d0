// Self-symmetries from candidate rotations tested by surface distance; rotation error modulo them.
#include "pipeline/physics/symmetry.h"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>

#include <algorithm>
#include <array>
#include <cmath>

#include <fmt/format.h>

#include "common/error.h"
#include "pipeline/physics/surface_distance.h"

namespace simu::physics {

namespace {

constexpr double kPi = 3.14159265358979323846;

// The 24 proper rotations with one +-1 per row and column (signed permutation matrices, det +1).
std::vector<Mat3> signed_permutations() {
  std::vector<Mat3> out;
  std::array<int, 3> perm{0, 1, 2};
  do {
    for (int signs = 0; signs < 8; ++signs) {
      Mat3 P = Mat3::Zero();
      for (int r = 0; r < 3; ++r) P(r, perm[r]) = (signs >> r & 1) ? -1.0 : 1.0;
      if (P.determinant() > 0) out.push_back(P);
    }
  } while (std::next_permutation(perm.begin(), perm.end()));
  return out;
}

// True when the mean symmetric surface distance between the shape and its copy turned by S about
// centre is below tol: samples p of the shape, the mean over both of d(centre + S (p - centre)) and
// d(centre + S^T (p - centre)). The sum only grows, so it stops once it passes the bound.
bool turned_within(const SurfaceDistance& surface, const Points& samples, const Vec3& centre, const Mat3& S,
                   double tol) {
  const double bound = tol * 2.0 * static_cast<double>(samples.rows());
  double sum = 0;
  for (Eigen::Index i = 0; i < samples.rows() && sum < bound; ++i) {
    const Vec3 p = samples.row(i).transpose() - centre;
    sum += surface.distance(centre + S * p) + surface.distance(centre + S.transpose() * p);
  }
  return sum < bound;
}

// Exact second moment of the surface about c: sum over triangles of the integral of (x - c)(x - c)^T dA,
// (A / 12) (sum_k v_k v_k^T + s s^T) with v_k the corners relative to c and s their sum.
Mat3 surface_second_moment(const Mesh& m, const Vec3& c) {
  Mat3 M = Mat3::Zero();
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    const Vec3 a = m.V.row(m.F(f, 0)).transpose() - c, b = m.V.row(m.F(f, 1)).transpose() - c,
               d = m.V.row(m.F(f, 2)).transpose() - c;
    const double area = 0.5 * (b - a).cross(d - a).norm();
    const Vec3 s = a + b + d;
    M += area / 12.0 * (a * a.transpose() + b * b.transpose() + d * d.transpose() + s * s.transpose());
  }
  return M;
}

// Candidates closer than this (degrees) to an accepted symmetry are the same one.
constexpr double kMergeDeg = 10.0;

// The angles (degrees) a continuous symmetry axis must pass.
constexpr std::array<double, 4> kContinuousTestDeg{17.0, 53.0, 97.0, 151.0};

}  // namespace

Mat3 axis_rotation(const Vec3& axis, double angle) { return Eigen::AngleAxisd(angle, axis.normalized()).toRotationMatrix(); }

double rotation_angle_deg(const Mat3& R) {
  const double c = std::clamp((R.trace() - 1.0) / 2.0, -1.0, 1.0);
  return std::acos(c) * 180.0 / kPi;
}

std::string Symmetry::describe() const {
  if (spherical()) return "spherical";
  if (axes.size() == 1) {
    // A flip: a discrete rotation that reverses the axis.
    for (const Mat3& S : rotations)
      if ((S * axes[0]).dot(axes[0]) < 0) return "axial+flip";
    return "axial";
  }
  if (rotations.size() <= 1) return "none";
  return fmt::format("discrete-{}", rotations.size());
}

Symmetry find_symmetry(const Mesh& shape, const SymmetryConfig& config) {
  SIMU_CHECK(config.tolerance > 0, "symmetry: tolerance {} must be positive", config.tolerance);
  Symmetry sym;
  sym.centre = surface_centroid(shape);
  const Points samples = sample_surface(shape, config.samples, config.seed);
  const SurfaceDistance surface(shape);
  const double longest = (shape.V.colwise().maxCoeff() - shape.V.colwise().minCoeff()).maxCoeff();
  const double tol = config.tolerance * longest;
  auto symmetric = [&](const Mat3& S) { return turned_within(surface, samples, sym.centre, S, tol); };

  // Candidate frames: the mesh's axes, then the principal axes of the surface's second moments, unless
  // each of those lies within kMergeDeg of a mesh axis (then it adds nothing but near-copies).
  std::vector<Mat3> frames{Mat3::Identity()};
  Mat3 principal = Eigen::SelfAdjointEigenSolver<Mat3>(surface_second_moment(shape, sym.centre)).eigenvectors();
  if (principal.determinant() < 0) principal.col(2) *= -1;
  const double merge_cos = std::cos(kMergeDeg * kPi / 180.0);
  if ((principal.cwiseAbs().colwise().maxCoeff().array() < merge_cos).any()) frames.push_back(principal);

  // Discrete: the signed permutations of each frame, F P F^T, the identity first. A candidate within
  // kMergeDeg of one already accepted is the same symmetry (two distinct symmetries that close would make
  // a symmetry of order > 36, which the continuous test classifies).
  sym.rotations.push_back(Mat3::Identity());
  const std::vector<Mat3> perms = signed_permutations();
  for (const Mat3& F : frames)
    for (const Mat3& P : perms) {
      const Mat3 S = F * P * F.transpose();
      const bool seen = std::any_of(sym.rotations.begin(), sym.rotations.end(),
                                    [&](const Mat3& T) { return rotation_angle_deg(T.transpose() * S) < kMergeDeg; });
      if (!seen && symmetric(S)) sym.rotations.push_back(S);
    }
  // Continuous: every test angle about the axis passes; axes within kMergeDeg counted once.
  for (const Mat3& F : frames)
    for (int k = 0; k < 3; ++k) {
      const Vec3 a = F.col(k);
      const bool seen = std::any_of(sym.axes.begin(), sym.axes.end(),
                                    [&](const Vec3& b) { return std::abs(a.dot(b)) > merge_cos; });
      if (seen) continue;
      const bool all = std::all_of(kContinuousTestDeg.begin(), kContinuousTestDeg.end(),
                                   [&](double deg) { return symmetric(axis_rotation(a, deg * kPi / 180.0)); });
      if (all) sym.axes.push_back(a);
    }
  return sym;
}

double rotation_error_deg(const Mat3& R_pred, const Mat3& R_gt, const Symmetry& gt_symmetry) {
  if (gt_symmetry.spherical()) return 0.0;
  const std::vector<Mat3> identity{Mat3::Identity()};
  const std::vector<Mat3>& group = gt_symmetry.rotations.empty() ? identity : gt_symmetry.rotations;
  double best = 180.0;
  for (const Mat3& S : group) {
    const Mat3 Rg = R_gt * S;
    double err;
    if (gt_symmetry.axes.size() == 1) {
      const Vec3& a = gt_symmetry.axes[0];
      err = std::acos(std::clamp((Rg * a).normalized().dot((R_pred * a).normalized()), -1.0, 1.0)) * 180.0 / kPi;
    } else {
      err = rotation_angle_deg(Rg.transpose() * R_pred);
    }
    best = std::min(best, err);
  }
  return best;
}

}  // namespace simu::physics
