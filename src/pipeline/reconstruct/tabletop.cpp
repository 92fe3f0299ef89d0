#include "pipeline/reconstruct/tabletop.h"

#include "common/error.h"
#include "pipeline/reconstruct/nn.h"
#include "pipeline/reconstruct/planes.h"
#include "pipeline/reconstruct/zbuffer.h"

#include <fmt/format.h>

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <map>

namespace simu::reconstruct {

namespace {
constexpr double kPi = 3.14159265358979323846;

// The smallest rotation taking unit a onto unit b.
Mat3 rotation_between(const Vec3& a, const Vec3& b) {
  return Eigen::Quaterniond::FromTwoVectors(a, b).toRotationMatrix();
}

// Adam over a 4-vector with per-parameter step sizes.
struct Adam4 {
  Eigen::Vector4d m = Eigen::Vector4d::Zero(), v = Eigen::Vector4d::Zero();
  int k = 0;
  void step(Eigen::Vector4d& x, const Eigen::Vector4d& g, const Eigen::Vector4d& lr) {
    ++k;
    m = 0.9 * m + 0.1 * g;
    v = 0.999 * v + 0.001 * g.cwiseProduct(g);
    const double c1 = 1 - std::pow(0.9, k), c2 = 1 - std::pow(0.999, k);
    for (int i = 0; i < 4; ++i) x[i] -= lr[i] * (m[i] / c1) / (std::sqrt(v[i] / c2) + 1e-8);
  }
};
}  // namespace

bool is_table_label(const std::string& label) {
  std::string l = label;
  for (auto& ch : l) ch = char(std::tolower(static_cast<unsigned char>(ch)));
  return l.find("table") != std::string::npos || l.find("desk") != std::string::npos;
}

std::vector<Vec3> point_map_normals(const PointMap& map) {
  const Vec3 nan = Vec3::Constant(std::numeric_limits<double>::quiet_NaN());
  std::vector<Vec3> out(map.p.size(), nan);
  for (int r = 1; r + 1 < map.height; ++r)
    for (int c = 1; c + 1 < map.width; ++c) {
      const Vec3 &l = map.at(r, c - 1), &rt = map.at(r, c + 1), &u = map.at(r - 1, c), &d = map.at(r + 1, c);
      if (!PointMap::valid(l) || !PointMap::valid(rt) || !PointMap::valid(u) || !PointMap::valid(d)) continue;
      Vec3 n = (rt - l).cross(d - u);
      if (n.norm() < 1e-12) continue;
      n.normalize();
      if (n.dot(-map.at(r, c)) < 0) n = -n;
      out[size_t(r) * map.width + c] = n;
    }
  return out;
}

std::optional<PlaneFit> table_support_plane(const TabletopInput& in, const TabletopConfig& cfg, std::string* why) {
  SIMU_CHECK(in.points, "tabletop {}: no point map", in.id);
  const PointMap& map = *in.points;
  SIMU_CHECK(in.mask.width == map.width && in.mask.height == map.height, "tabletop {}: mask is {}x{}, the point map {}x{}",
             in.id, in.mask.width, in.mask.height, map.width, map.height);
  const std::vector<Vec3> normals = point_map_normals(map);
  const double cos_up = std::cos(cfg.up_angle_deg * kPi / 180);
  std::vector<Vec3> up_pts;
  int64_t valid = 0;
  for (int r = 0; r < map.height; ++r)
    for (int c = 0; c < map.width; ++c) {
      if (!in.mask.at(r, c) || !PointMap::valid(map.at(r, c))) continue;
      ++valid;
      const Vec3& n = normals[size_t(r) * map.width + c];
      if (n.allFinite() && n.dot(in.up) >= cos_up) up_pts.push_back(map.at(r, c));
    }
  const int64_t need = std::max<int64_t>(cfg.min_support, int64_t(std::ceil(cfg.min_support_frac * double(valid))));
  if (int64_t(up_pts.size()) < need) {
    *why = fmt::format("insufficient plane support: {} upward-facing points of {} valid in the mask, {} needed",
                       up_pts.size(), valid, need);
    return std::nullopt;
  }
  // Height band: the highest well-populated height bin, +- band.
  std::map<int64_t, int64_t> hist;
  for (auto& p : up_pts) ++hist[int64_t(std::floor(in.up.dot(p) / cfg.height_bin))];
  int64_t maxc = 0;
  for (auto& [b, n] : hist) maxc = std::max(maxc, n);
  int64_t top_bin = hist.begin()->first;
  for (auto& [b, n] : hist)
    if (double(n) >= cfg.band_min_frac * double(maxc)) top_bin = std::max(top_bin, b);
  const double h0 = (double(top_bin) + 0.5) * cfg.height_bin;
  std::vector<Vec3> band;
  for (auto& p : up_pts)
    if (std::abs(in.up.dot(p) - h0) <= cfg.band) band.push_back(p);
  Points B(Eigen::Index(band.size()), 3);
  for (size_t i = 0; i < band.size(); ++i) B.row(Eigen::Index(i)) = band[i].transpose();
  RansacConfig rc;
  rc.threshold = cfg.ransac_threshold;
  rc.iterations = cfg.ransac_iterations;
  rc.min_inliers = need;
  rc.axis = in.up;
  rc.max_angle_deg = 45;  // the tilt check below decides; this only guides the sampling
  auto f = ransac_plane(B, rc);
  if (!f) {
    *why = fmt::format("insufficient plane support: no plane with >= {} inliers in the height band ({} points)", need,
                       band.size());
    return std::nullopt;
  }
  if (f->normal.dot(in.up) < 0) f->normal = -f->normal;
  const double tilt = angle_deg(f->normal, in.up);
  if (tilt > cfg.max_tilt_deg) {
    *why = fmt::format("non-horizontal plane: the top plane is {:.1f} deg from up (> {})", tilt, cfg.max_tilt_deg);
    return std::nullopt;
  }
  if (in.floor && std::abs(in.floor->distance(f->point)) < cfg.floor_gap) {
    *why = fmt::format("floor degeneracy: the top plane is {:.3f} m from the floor (< {})",
                       std::abs(in.floor->distance(f->point)), cfg.floor_gap);
    return std::nullopt;
  }
  return f;
}

namespace {

// The mesh's top plane: centroid of the vertices within the top band along up, normal from their
// covariance (the up direction when they do not span a plane).
PlaneFit mesh_top_plane(const Points& W, const Vec3& up, double top_band) {
  Eigen::VectorXd h(W.rows());
  for (Eigen::Index i = 0; i < W.rows(); ++i) h[i] = up.dot(W.row(i).transpose());
  const double hmax = h.maxCoeff(), hmin = h.minCoeff();
  std::vector<int64_t> top;
  for (Eigen::Index i = 0; i < W.rows(); ++i)
    if (h[i] >= hmax - top_band * (hmax - hmin)) top.push_back(i);
  Vec3 pm = Vec3::Zero();
  for (int64_t i : top) pm += W.row(i).transpose();
  pm /= double(top.size());
  Vec3 nm = up;
  if (top.size() >= 3) {
    Mat3 Cv = Mat3::Zero();
    for (int64_t i : top) {
      const Vec3 d = W.row(i).transpose() - pm;
      Cv += d * d.transpose();
    }
    Eigen::SelfAdjointEigenSolver<Mat3> es(Cv);
    if (es.eigenvalues()[1] > 1e-12) nm = es.eigenvectors().col(0).normalized();  // a planar top, not a line
    if (nm.dot(up) < 0) nm = -nm;
  }
  PlaneFit top_plane;
  top_plane.point = pm;
  top_plane.normal = nm;
  return top_plane;
}

// Eq. table_refine: symmetric chamfer between the visible snapped vertices Vh and the observation, plus
// the yaw / translation / log-scale regularisers. x = (theta, tx, ty, log s);
// T(x)(v) = c + s Rz(theta) (v - c) + tx e1 + ty e2 with Rz about the support normal nd.
struct TableRefineLoss {
  const Points& Vh;      // [n, 3] visible snapped mesh vertices
  const Points& Pobs;    // [k, 3] observed table points
  const NearestNeighbors& obs;
  const NearestNeighbors& mesh;
  Vec3 nd, c, e1, e2;
  const TabletopConfig& cfg;

  // Returns (chamfer, regulariser); fills the gradient of chamfer + lambda * regulariser when g is given.
  std::pair<double, double> operator()(const Eigen::Vector4d& x, Eigen::Vector4d* g) const {
    const Mat3 Rz = Eigen::AngleAxisd(x[0], nd).toRotationMatrix();
    const double s = std::exp(x[3]);
    const Vec3 off = x[1] * e1 + x[2] * e2;
    Eigen::Vector4d ga = Eigen::Vector4d::Zero(), gb = Eigen::Vector4d::Zero();
    double la = 0, lb = 0;
    auto jac = [&](const Vec3& v) {  // d x'/d (theta, tx, ty, log s) at canonical-snapped v
      Eigen::Matrix<double, 3, 4> J;
      const Vec3 a = s * (Rz * (v - c));
      J.col(0) = nd.cross(a);
      J.col(1) = e1;
      J.col(2) = e2;
      J.col(3) = a;
      return J;
    };
    // Mesh -> observation.
    for (Eigen::Index i = 0; i < Vh.rows(); ++i) {
      const Vec3 v = Vh.row(i).transpose();
      const Vec3 xp = c + s * (Rz * (v - c)) + off;
      const Vec3 r = xp - obs.points().row(obs.nearest(xp)).transpose();
      const double d = r.norm();
      la += d;
      if (g && d > 1e-12) ga += jac(v).transpose() * (r / d);
    }
    // Observation -> mesh (nearest through the inverse similarity).
    for (Eigen::Index i = 0; i < Pobs.rows(); ++i) {
      const Vec3 y = Pobs.row(i).transpose();
      const Vec3 q = c + Rz.transpose() * (y - c - off) / s;
      const Vec3 v = mesh.points().row(mesh.nearest(q)).transpose();
      const Vec3 r = y - (c + s * (Rz * (v - c)) + off);
      const double d = r.norm();
      lb += d;
      if (g && d > 1e-12) gb -= jac(v).transpose() * (r / d);
    }
    const double na = double(Vh.rows()), nb = double(Pobs.rows());
    const double th0 = cfg.theta0_deg * kPi / 180;
    const double reg = std::pow(x[0] / th0, 2) + std::pow(x[1] / cfg.t0, 2) + std::pow(x[2] / cfg.t0, 2) +
                       std::pow(x[3] / cfg.sigma0, 2);
    if (g) {
      *g = 0.5 * (ga / na + gb / nb);
      (*g)[0] += cfg.lambda * 2 * x[0] / (th0 * th0);
      (*g)[1] += cfg.lambda * 2 * x[1] / (cfg.t0 * cfg.t0);
      (*g)[2] += cfg.lambda * 2 * x[2] / (cfg.t0 * cfg.t0);
      (*g)[3] += cfg.lambda * 2 * x[3] / (cfg.sigma0 * cfg.sigma0);
    }
    return std::make_pair(0.5 * (la / na + lb / nb), reg);
  }
};

// The refinement's similarity composed after the snap, the top re-snapped onto the plane, and the object's
// final pose written into res.
void compose_refined_pose(const Eigen::Vector4d& x, const Points& W, const TableRefineLoss& L, const Vec3& pd,
                          const TabletopInput& in, TabletopResult& res) {
  const Vec3& nd = L.nd;
  res.theta_deg = x[0] * 180 / kPi;
  res.tx = x[1];
  res.ty = x[2];
  res.log_s = x[3];
  const Mat3 Rz = Eigen::AngleAxisd(x[0], nd).toRotationMatrix();
  const double s = std::exp(x[3]);
  res.refine = Similarity{s, Rz, L.c - s * (Rz * L.c) + x[1] * L.e1 + x[2] * L.e2};
  res.total = Similarity{s, Rz * res.snap.R, s * (Rz * res.snap.t) + res.refine.t};
  // Re-snap the refined top onto the plane (the refinement keeps it there up to rounding).
  const Points Wf = transform(W, res.total);
  double top_h = -1e300;
  for (Eigen::Index i = 0; i < Wf.rows(); ++i) top_h = std::max(top_h, nd.dot(Wf.row(i).transpose()));
  const double gap = nd.dot(pd) - top_h;
  res.total.t += gap * nd;
  res.R = res.total.R * in.R;
  res.scale = res.total.s * in.scale;
  res.t = res.total.s * (res.total.R * in.t) + res.total.t;
}

}  // namespace

TabletopResult refine_tabletop(const TabletopInput& in, const TabletopConfig& cfg) {
  TabletopResult res;
  res.scale = in.scale;
  res.R = in.R;
  res.t = in.t;
  std::string why;
  auto support = table_support_plane(in, cfg, &why);
  if (!support) {
    res.message = fmt::format("table {}: {}", in.id, why);
    return res;
  }
  res.support = *support;
  const Vec3 nd = support->normal, pd = support->point;
  // Placed, densified mesh and its top plane.
  Points C = in.canonical;
  Faces F = in.faces;
  densify(C, F, cfg.max_edge);
  const Points W = place(C, in.scale, in.R, in.t);
  res.mesh_top = mesh_top_plane(W, in.up, cfg.top_band);
  const Vec3 pm = res.mesh_top.point, nm = res.mesh_top.normal;
  // Eq. hard_snap.
  const Mat3 Rs = rotation_between(nm, nd);
  const Vec3 delta = ((pd - pm).dot(nd)) * nd;
  res.snap = Similarity{1.0, Rs, pm - Rs * pm + delta};
  const Points Ws = transform(W, res.snap);
  const Vec3 c = res.snap.apply(pm);  // snapped top centre, on the plane
  // Visible vertices at the snapped pose (once) and the observation.
  const double diag = (Ws.colwise().maxCoeff() - Ws.colwise().minCoeff()).norm();
  const std::vector<int64_t> vis = visible_vertices(Ws, F, in.K, cfg.visibility_tol * diag);
  const Points Pobs = subsample(masked_points(*in.points, in.mask, "tabletop " + in.id), cfg.max_points);
  if (vis.size() < 3 || Pobs.rows() < 3) {
    res.message = fmt::format("table {}: insufficient plane support ({} visible vertices, {} depth points)", in.id,
                              vis.size(), Pobs.rows());
    return res;
  }
  Points Vh(Eigen::Index(vis.size()), 3);
  for (size_t i = 0; i < vis.size(); ++i) Vh.row(Eigen::Index(i)) = Ws.row(vis[i]);
  Vh = subsample(Vh, cfg.max_points);
  const NearestNeighbors obs(Pobs), mesh(Vh);
  const Vec3 e1 = nd.unitOrthogonal(), e2 = nd.cross(e1);
  const TableRefineLoss loss{Vh, Pobs, obs, mesh, nd, c, e1, e2, cfg};
  // Eq. table_refine by Adam from the snap (x = 0).
  Eigen::Vector4d x = Eigen::Vector4d::Zero();
  res.chamfer_before = loss(x, nullptr).first;
  Adam4 adam;
  const Eigen::Vector4d lr(cfg.lr_theta_deg * kPi / 180, cfg.lr_t, cfg.lr_t, cfg.lr_log_s);
  for (int it = 0; it < cfg.iterations; ++it) {
    Eigen::Vector4d g;
    loss(x, &g);
    const double decay = 1.0 - 0.9 * double(it) / double(std::max(1, cfg.iterations - 1));
    adam.step(x, g, lr * decay);
  }
  res.chamfer_after = loss(x, nullptr).first;
  if (!(res.chamfer_after <= res.chamfer_before)) x.setZero();  // never worse than the snap alone
  compose_refined_pose(x, W, loss, pd, in, res);
  res.ok = true;
  return res;
}

}  // namespace simu::reconstruct
