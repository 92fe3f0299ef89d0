// OBB search, gravity diagnostics (rho, eta), the gravity-axis stretch and B_str / its lowest part.
#include "pipeline/physics/geometry.h"

#include "common/error.h"

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <cmath>

namespace simu::physics {

namespace {

using Vec2 = Eigen::Vector2d;

// Makes a frame right-handed by flipping its third axis when needed.
Mat3 right_handed(Mat3 F) {
  if (F.determinant() < 0) F.col(2) = -F.col(2);
  return F;
}

// The tightest box of the points with the given (orthonormal) axes.
Obb box_in_frame(const Points& P, const Mat3& F) {
  Eigen::Matrix<double, -1, 3> local = P * F;  // [n, 3] coordinates along the axes
  const Vec3 lo = local.colwise().minCoeff().transpose();
  const Vec3 hi = local.colwise().maxCoeff().transpose();
  Obb b;
  b.axes = F;
  b.extents = hi - lo;
  b.center = F * (0.5 * (lo + hi));
  return b;
}

// Cross product sign of (b - a) x (c - a).
double cross2(const Vec2& a, const Vec2& b, const Vec2& c) {
  return (b.x() - a.x()) * (c.y() - a.y()) - (b.y() - a.y()) * (c.x() - a.x());
}

// Convex hull of 2D points (Andrew's monotone chain), counter-clockwise, no repeated end point.
std::vector<Vec2> hull2d(std::vector<Vec2> p) {
  std::sort(p.begin(), p.end(), [](const Vec2& a, const Vec2& b) {
    return a.x() < b.x() || (a.x() == b.x() && a.y() < b.y());
  });
  p.erase(std::unique(p.begin(), p.end(), [](const Vec2& a, const Vec2& b) { return a == b; }), p.end());
  if (p.size() < 3) return p;
  std::vector<Vec2> h(2 * p.size());
  size_t k = 0;
  for (size_t i = 0; i < p.size(); ++i) {
    while (k >= 2 && cross2(h[k - 2], h[k - 1], p[i]) <= 0) --k;
    h[k++] = p[i];
  }
  for (size_t i = p.size() - 1, t = k + 1; i > 0; --i) {
    while (k >= t && cross2(h[k - 2], h[k - 1], p[i - 1]) <= 0) --k;
    h[k++] = p[i - 1];
  }
  h.resize(k - 1);
  return h;
}

}  // namespace

bool caliper_frame(const Points& P, const Vec3& n, Mat3* out) {
  Vec3 e1 = n.unitOrthogonal();
  Vec3 e2 = n.cross(e1);
  std::vector<Vec2> q(P.rows());
  for (Eigen::Index i = 0; i < P.rows(); ++i) {
    const Vec3 x = P.row(i).transpose();
    q[i] = Vec2(x.dot(e1), x.dot(e2));
  }
  const std::vector<Vec2> h = hull2d(std::move(q));
  if (h.size() < 3) return false;
  double best_area = std::numeric_limits<double>::infinity();
  Vec2 best_dir(1, 0);
  for (size_t i = 0; i < h.size(); ++i) {
    Vec2 d = h[(i + 1) % h.size()] - h[i];
    const double len = d.norm();
    if (len <= 0) continue;
    d /= len;
    const Vec2 o(-d.y(), d.x());
    double lo1 = 1e300, hi1 = -1e300, lo2 = 1e300, hi2 = -1e300;
    for (const Vec2& p : h) {
      const double a = p.dot(d), b = p.dot(o);
      lo1 = std::min(lo1, a), hi1 = std::max(hi1, a), lo2 = std::min(lo2, b), hi2 = std::max(hi2, b);
    }
    const double area = (hi1 - lo1) * (hi2 - lo2);
    if (area < best_area * (1 - 1e-12)) best_area = area, best_dir = d;
  }
  Mat3 F;
  F.col(0) = (best_dir.x() * e1 + best_dir.y() * e2).normalized();
  F.col(2) = n.normalized();
  F.col(1) = F.col(2).cross(F.col(0));
  *out = right_handed(F);
  return true;
}

namespace {

// Orthonormalises a hint frame (closest rotation via SVD); false when it is degenerate.
bool orthonormal(const Mat3& H, Mat3* out) {
  if (!H.allFinite()) return false;
  Eigen::JacobiSVD<Mat3> svd(H, Eigen::ComputeFullU | Eigen::ComputeFullV);
  if (svd.singularValues()(2) < 1e-9) return false;
  *out = right_handed(svd.matrixU() * svd.matrixV().transpose());
  return true;
}

// A frame whose third axis is g.
Mat3 gravity_frame(const Vec3& g) {
  Mat3 F;
  F.col(2) = g.normalized();
  F.col(0) = F.col(2).unitOrthogonal();
  F.col(1) = F.col(2).cross(F.col(0));
  return F;
}

}  // namespace

std::array<Vec3, 8> Obb::corners() const {
  std::array<Vec3, 8> c;
  for (int k = 0; k < 8; ++k) {
    Vec3 y;
    for (int a = 0; a < 3; ++a) y(a) = ((k >> a) & 1 ? 0.5 : -0.5) * extents(a);
    c[k] = center + axes * y;
  }
  return c;
}

bool Obb::contains(const Vec3& x, double tol) const {
  const Vec3 y = axes.transpose() * (x - center);
  for (int a = 0; a < 3; ++a)
    if (std::abs(y(a)) > 0.5 * extents(a) + tol) return false;
  return true;
}

Mesh Obb::to_mesh() const {
  Mesh m;
  m.V.resize(8, 3);
  const auto c = corners();
  for (int k = 0; k < 8; ++k) m.V.row(k) = c[k].transpose();
  // Faces of the unit cube in corner-bit order, outward counter-clockwise for a right-handed frame.
  static const int F[12][3] = {{0, 2, 3}, {0, 3, 1}, {4, 5, 7}, {4, 7, 6},   // -z, +z
                               {0, 1, 5}, {0, 5, 4}, {2, 6, 7}, {2, 7, 3},   // -y, +y
                               {0, 4, 6}, {0, 6, 2}, {1, 3, 7}, {1, 7, 5}};  // -x, +x
  m.F.resize(12, 3);
  for (int f = 0; f < 12; ++f) m.F.row(f) << F[f][0], F[f][1], F[f][2];
  return m;
}

Obb compute_obb(const Points& points, const std::vector<Mat3>& hints, const ObbOptions& options) {
  SIMU_CHECK(points.rows() > 0, "compute_obb: empty point set");
  SIMU_CHECK(points.allFinite(), "compute_obb: non-finite point coordinates ({} points)", points.rows());
  // Candidate frames: the hints in order, then the principal axes.
  std::vector<Mat3> frames;
  for (const Mat3& h : hints) {
    Mat3 F;
    if (orthonormal(h, &F)) frames.push_back(F);
  }
  if (options.use_pca && points.rows() >= 2) {
    const Eigen::RowVector3d mean = points.colwise().mean();
    const Eigen::Matrix<double, -1, 3> X = points.rowwise() - mean;
    const Mat3 C = X.transpose() * X / double(points.rows());
    Eigen::SelfAdjointEigenSolver<Mat3> es(C);
    Mat3 F = es.eigenvectors().rowwise().reverse();  // largest variance first
    frames.push_back(right_handed(F));
  }
  if (options.use_world_axes || frames.empty()) frames.push_back(Mat3::Identity());

  // Smallest volume over the candidates and their caliper refinements; ties keep the earlier one.
  Obb best = box_in_frame(points, frames[0]);
  auto consider = [&](const Mat3& F) {
    const Obb b = box_in_frame(points, F);
    if (b.volume() < best.volume() * (1 - options.tie_tolerance)) best = b;
  };
  for (const Mat3& F : frames) consider(F);
  if (options.refine_calipers) {
    for (const Mat3& F : frames)
      for (int k = 0; k < 3; ++k) {
        Mat3 G;
        if (caliper_frame(points, F.col(k), &G)) consider(G);
      }
  }
  return best;
}

Obb object_obb(const Mesh& canonical, const Vec3& scale, const Mat3& R, const Vec3& t, const Vec3& gravity) {
  SIMU_CHECK(canonical.V.rows() > 0, "object_obb: empty mesh");
  const Mat3 L = R * scale.asDiagonal();
  Points P = (canonical.V * L.transpose()).rowwise() + t.transpose();
  std::vector<Mat3> hints{R, Mat3::Identity()};
  if (gravity.norm() > 0) hints.push_back(gravity_frame(gravity));
  return compute_obb(P, hints);
}

GravityAxis gravity_axis(const Obb& obb, const Vec3& gravity) {
  SIMU_CHECK(gravity.allFinite() && gravity.norm() > 0, "gravity_axis: gravity must be a non-zero finite vector");
  const Vec3 g = gravity.normalized();
  GravityAxis ga;
  double best = -1;
  for (int k = 0; k < 3; ++k) {
    const double a = std::abs(obb.axes.col(k).dot(g));
    if (a > best + 1e-12) best = a, ga.index = k;
  }
  const Vec3 col = obb.axes.col(ga.index);
  ga.u = col.dot(g) >= 0 ? col : Vec3(-col);
  ga.length = obb.extents(ga.index);
  ga.alignment = best;
  return ga;
}

const char* to_string(Branch b) { return b == Branch::Resample ? "resample" : "stretch"; }

CorrectionConfig CorrectionConfig::from(simu::config::Reader& r) {
  CorrectionConfig c;
  r.field("resample_threshold", c.resample_threshold);
  r.field("min_lambda", c.min_lambda);
  r.field("lowest_part_margin", c.lowest_part_margin);
  r.finish();
  return c;
}

Diagnosis diagnose(const Obb& obb_pre, const Vec3& gravity, const Vec3& dt_pen, const Vec3& dt_grv,
                   const CorrectionConfig& config) {
  SIMU_CHECK(dt_pen.allFinite() && dt_grv.allFinite(), "diagnose: non-finite displacement (pen {} {} {}, grv {} {} {})",
             dt_pen.x(), dt_pen.y(), dt_pen.z(), dt_grv.x(), dt_grv.y(), dt_grv.z());
  Diagnosis d;
  d.obb_pre = obb_pre;
  d.axis = gravity_axis(obb_pre, gravity);
  SIMU_CHECK(d.axis.length > 0 && std::isfinite(d.axis.length),
             "diagnose: OBB side along gravity is {} (expected > 0; flat or degenerate object)", d.axis.length);
  const Vec3 g = gravity.normalized();
  d.g_displacement = g.dot(dt_pen + dt_grv);
  d.eta = d.g_displacement / d.axis.length;
  d.rho = std::abs(d.eta);
  d.branch = d.rho >= config.resample_threshold ? Branch::Resample : Branch::Stretch;
  return d;
}

StretchResult gravity_axis_stretch(const Points& canonical, const Vec3& scale, const Mat3& R_pre, const Vec3& t_pre,
                                   const Mat3& R_after, const Diagnosis& d, const CorrectionConfig& config) {
  SIMU_CHECK(canonical.rows() > 0, "gravity_axis_stretch: empty mesh");
  SIMU_CHECK(scale.allFinite() && scale.minCoeff() > 0, "gravity_axis_stretch: scale must be positive");
  StretchResult r;
  r.R = R_after;
  r.lambda = std::max(1.0 + d.eta, config.min_lambda);
  const Vec3 u = d.axis.u;
  const Vec3 a = (R_pre.transpose() * u).normalized();
  r.axis_canonical = a;
  const double l_pre = d.axis.length;
  // Paper: t_str = t_pre + 0.5 eta l_pre u (uses the clamped lambda - 1 so the face stays fixed).
  const Vec3 t_paper = t_pre + 0.5 * (r.lambda - 1.0) * l_pre * u;

  // Scaled canonical vertices W = s .* v and their stretch W' = lambda (W.a) a + (I - a a^T) W.
  const Points W = canonical * scale.asDiagonal();
  const Mat3 S = Mat3::Identity() + (r.lambda - 1.0) * a * a.transpose();
  const Points Ws = W * S.transpose();
  const Vec3 lo = Ws.colwise().minCoeff().transpose(), hi = Ws.colwise().maxCoeff().transpose();
  const double longest_w = (hi - lo).maxCoeff();
  SIMU_CHECK(longest_w > 0, "gravity_axis_stretch: degenerate stretched mesh");
  r.gamma = longest_w / scale.maxCoeff();

  // Is a a canonical axis? Then fold lambda into that axis' scale and keep the mesh.
  Eigen::Index k = 0;
  const double amax = a.cwiseAbs().maxCoeff(&k);
  if (amax > 1 - 1e-9) {
    r.canonical = canonical;
    r.mesh_changed = false;
    r.scale = scale;
    r.scale(k) *= r.lambda;
    r.t = t_paper;
  } else {
    // Renormalise: AABB-centred, longest side 1; gamma (with the old scale) becomes the scale and
    // the re-centring offset moves into t so the world geometry is unchanged.
    const Vec3 c = 0.5 * (lo + hi);
    r.canonical = (Ws.rowwise() - c.transpose()) / longest_w;
    r.mesh_changed = true;
    r.scale = Vec3::Constant(longest_w);
    r.t = t_paper + R_after * c;
  }

  // Diagnostic: movement of the anti-gravity face (minimum of u.x over the vertices) with R_pre.
  const Eigen::VectorXd before = (W * (R_pre.transpose() * u)).array() + u.dot(t_pre);
  const Points W_after = r.canonical * r.scale.asDiagonal();
  const Vec3 t_after = r.mesh_changed ? Vec3(t_paper + R_pre * (0.5 * (lo + hi))) : t_paper;
  const Eigen::VectorXd after = (W_after * (R_pre.transpose() * u)).array() + u.dot(t_after);
  r.top_face_shift = after.minCoeff() - before.minCoeff();
  return r;
}

Obb stretched_obb(const Diagnosis& d, const CorrectionConfig& config) {
  Obb b = d.obb_pre;
  const double l = d.axis.length;
  const double l_new = std::max(1.0 + d.eta, config.min_lambda) * l;
  // Top (anti-gravity) face fixed at center - l/2 u; the bottom moves to top + l_new u.
  b.center = d.obb_pre.center + 0.5 * (l_new - l) * d.axis.u;
  b.extents(d.axis.index) = l_new;
  return b;
}

std::optional<Obb> lowest_part(const Diagnosis& d, const CorrectionConfig& config) {
  const Obb s = stretched_obb(d, config);
  const double l = d.axis.length;
  const double l_new = s.extents(d.axis.index);
  const double h = std::min(std::max(l_new - l, 0.0) + config.lowest_part_margin * l, l_new);
  if (h <= 0) return std::nullopt;
  // Slab [bottom - h, bottom] along u, where bottom = centre + l_new/2 u is B_str's gravity-most face.
  Obb slab = s;
  slab.center = s.center + 0.5 * (l_new - h) * d.axis.u;
  slab.extents(d.axis.index) = h;
  return slab;
}

bool segment_misses_box(const Vec3& a, const Vec3& b, const Vec3& lo, const Vec3& hi) {
  double t0 = 0, t1 = 1;
  for (int k = 0; k < 3; ++k) {
    const double d = b[k] - a[k];
    if (std::abs(d) < 1e-12) {
      if (a[k] < lo[k] || a[k] > hi[k]) return true;
      continue;
    }
    double s0 = (lo[k] - a[k]) / d, s1 = (hi[k] - a[k]) / d;
    if (s0 > s1) std::swap(s0, s1);
    t0 = std::max(t0, s0), t1 = std::min(t1, s1);
    if (t0 > t1) return true;
  }
  return false;
}

}  // namespace simu::physics
