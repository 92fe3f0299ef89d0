#include "pipeline/reconstruct/icp_refine.h"

#include "common/error.h"
#include "pipeline/reconstruct/nn.h"
#include "pipeline/reconstruct/zbuffer.h"

#include <fmt/format.h>

#include <Eigen/SVD>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>

namespace simu::reconstruct {

namespace {

constexpr double kPi = 3.14159265358979323846;

// Area-uniform samples of the mesh surface (fixed seed: the same mesh gives the same samples).
Points surface_samples(const Points& V, const Faces& F, int64_t n) {
  std::vector<double> cum(size_t(F.rows()));
  double total = 0;
  for (Eigen::Index f = 0; f < F.rows(); ++f) {
    const Vec3 a = V.row(F(f, 0)), b = V.row(F(f, 1)), c = V.row(F(f, 2));
    total += 0.5 * (b - a).cross(c - a).norm();
    cum[size_t(f)] = total;
  }
  if (!(total > 0)) return V;
  std::mt19937_64 rng(0x1c9u);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  Points S(n, 3);
  for (int64_t i = 0; i < n; ++i) {
    const double x = U(rng) * total;
    const size_t f = size_t(std::min<std::ptrdiff_t>(std::lower_bound(cum.begin(), cum.end(), x) - cum.begin(),
                                                     std::ptrdiff_t(cum.size()) - 1));
    const double r1 = std::sqrt(U(rng)), r2 = U(rng);
    const Vec3 a = V.row(F(Eigen::Index(f), 0)), b = V.row(F(Eigen::Index(f), 1)), c = V.row(F(Eigen::Index(f), 2));
    S.row(i) = ((1 - r1) * a + r1 * (1 - r2) * b + r1 * r2 * c).transpose();
  }
  return S;
}

// Trimmed ICP from (R, s, t): observed points Y to their nearest surface samples (tree over the shaped
// canonical samples); returns the trimmed mean residual at the end.
double trimmed_icp(const Points& Y, const NearestNeighbors& tree, Mat3& R, double& s, Vec3& t, double s0,
                   const Vec3& axis, const IcpConfig& cfg) {
  const Eigen::Index n = Y.rows();
  const Eigen::Index keep = std::max<Eigen::Index>(3, Eigen::Index(std::ceil(cfg.trim * double(n))));
  std::vector<double> d(static_cast<size_t>(n));
  std::vector<Eigen::Index> order(static_cast<size_t>(n));
  Points M(n, 3);  // matched canonical samples
  double residual = 0;
  for (int it = 0; it <= cfg.iterations; ++it) {
    // Correspondences at the current pose.
    const Mat3 Rt = R.transpose();
    for (Eigen::Index i = 0; i < n; ++i) {
      const Vec3 y = Y.row(i).transpose();
      const int64_t j = tree.nearest(Rt * (y - t) / s);
      M.row(i) = tree.points().row(j);
      d[size_t(i)] = (y - (s * (R * M.row(i).transpose()) + t)).norm();
      order[size_t(i)] = i;
    }
    std::nth_element(order.begin(), order.begin() + (keep - 1), order.end(),
                     [&](Eigen::Index a, Eigen::Index b) { return d[size_t(a)] < d[size_t(b)] || (d[size_t(a)] == d[size_t(b)] && a < b); });
    residual = 0;
    for (Eigen::Index k = 0; k < keep; ++k) residual += d[size_t(order[size_t(k)])];
    residual /= double(keep);
    if (it == cfg.iterations) break;
    // Closed-form fit on the kept pairs (Kabsch / Umeyama).
    Vec3 mx = Vec3::Zero(), my = Vec3::Zero();
    for (Eigen::Index k = 0; k < keep; ++k) {
      mx += M.row(order[size_t(k)]).transpose();
      my += Y.row(order[size_t(k)]).transpose();
    }
    mx /= double(keep);
    my /= double(keep);
    Mat3 S = Mat3::Zero();
    double var_x = 0;
    for (Eigen::Index k = 0; k < keep; ++k) {
      const Vec3 xc = M.row(order[size_t(k)]).transpose() - mx, yc = Y.row(order[size_t(k)]).transpose() - my;
      S += yc * xc.transpose();
      var_x += xc.squaredNorm();
    }
    if (cfg.yaw_only) {
      // The turn about the vertical axis a only (1 DoF): the pairs' placed offsets x = s R (m - mx) against
      // y - my; theta = atan2(sum a.(x cross y), sum x_perp . y_perp).
      const Mat3 A = R * S.transpose();  // sum (R xc) yc^T
      const Mat3 P = Mat3::Identity() - axis * axis.transpose();
      double sin_t = 0, cos_t = 0;
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) cos_t += P(i, j) * A(i, j);
      const Vec3 cross(A(1, 2) - A(2, 1), A(2, 0) - A(0, 2), A(0, 1) - A(1, 0));
      sin_t = axis.dot(cross);
      R = Eigen::AngleAxisd(std::atan2(sin_t, cos_t), axis).toRotationMatrix() * R;
      t = my - s * (R * mx);
      continue;
    }
    Eigen::JacobiSVD<Mat3> svd(S, Eigen::ComputeFullU | Eigen::ComputeFullV);
    Mat3 D = Mat3::Identity();
    if (svd.matrixU().determinant() * svd.matrixV().determinant() < 0) D(2, 2) = -1;
    const Mat3 Rn = svd.matrixU() * D * svd.matrixV().transpose();
    double sn = s;
    if (cfg.fit_scale && var_x > 0) {
      sn = (svd.singularValues().asDiagonal() * D).trace() / var_x;
      sn = std::clamp(sn, s0 * std::exp(-cfg.max_log_scale), s0 * std::exp(cfg.max_log_scale));
    }
    R = Rn;
    s = sn;
    t = my - s * (R * mx);
  }
  return residual;
}

// The canonical mesh with the prediction's shape (pose scale = s * shape).
Points shaped_mesh(const AlignInput& in) {
  Points V(in.canonical.rows(), 3);
  for (Eigen::Index i = 0; i < V.rows(); ++i) V.row(i) = in.canonical.row(i).cwiseProduct(in.shape.transpose());
  return V;
}

// The score's depth tolerance: depth_tol times the placed mesh's longest side, clamped (metres).
double score_tau(const Points& V, double s, const IcpConfig& cfg) {
  const double size = s * (V.colwise().maxCoeff() - V.colwise().minCoeff()).maxCoeff();
  return std::clamp(cfg.depth_tol * size, cfg.min_tol, cfg.max_tol);
}

double angle_deg(const Mat3& A, const Mat3& B) {
  const double c = std::clamp(((A.transpose() * B).trace() - 1) / 2, -1.0, 1.0);
  return std::acos(c) * 180 / kPi;
}

}  // namespace

double render_compare_score(const Points& shaped, const Faces& F, const Mat3& R, double s, const Vec3& t,
                            const AlignInput& in, double tau) {
  const std::vector<float> z = render_depth(transform(shaped, Similarity{s, R, t}), F, in.K);
  const int64_t mask_n = std::max<int64_t>(1, in.mask.count());
  double cost = 0;
  for (size_t i = 0; i < z.size(); ++i) {
    const bool drawn = std::isfinite(z[i]), inside = in.mask.data[i] != 0;
    if (!drawn && !inside) continue;
    const Vec3* o = in.depth && PointMap::valid(in.depth->p[i]) ? &in.depth->p[i] : nullptr;
    if (inside && !drawn) cost += 1;
    else if (inside && o) cost += std::min(std::abs(double(z[i]) - o->z()), tau) / tau;
    else if (!inside && o && o->z() > double(z[i]) + tau) cost += 1;
  }
  return cost / double(mask_n);
}

double pose_score(const AlignInput& in, const Mat3& R, double s, const Vec3& t, const IcpConfig& cfg) {
  SIMU_CHECK(in.K.valid(), "pose score {}: invalid intrinsics", in.id);
  SIMU_CHECK(in.mask.width == in.K.width && in.mask.height == in.K.height, "pose score {}: mask is {}x{}, the image {}x{}",
             in.id, in.mask.width, in.mask.height, in.K.width, in.K.height);
  if (in.canonical.rows() == 0 || in.faces.rows() == 0) return std::numeric_limits<double>::infinity();
  const Points V = shaped_mesh(in);
  return render_compare_score(V, in.faces, R, s, t, in, score_tau(V, s, cfg));
}

IcpResult refine_rotation_icp(const AlignInput& in, const Vec3& up_in, const IcpConfig& cfg) {
  IcpResult res;
  res.R = in.R_init;
  res.s = in.s_init;
  res.t = in.t_init;
  SIMU_CHECK(in.K.valid(), "icp {}: invalid intrinsics", in.id);
  SIMU_CHECK(in.mask.width == in.K.width && in.mask.height == in.K.height, "icp {}: mask is {}x{}, the image {}x{}",
             in.id, in.mask.width, in.mask.height, in.K.width, in.K.height);
  SIMU_CHECK(!in.depth || (in.depth->width == in.K.width && in.depth->height == in.K.height),
             "icp {}: point map is {}x{}, the image {}x{}", in.id, in.depth->width, in.depth->height, in.K.width, in.K.height);
  SIMU_CHECK(cfg.yaw_steps >= 1 && cfg.trim > 0 && cfg.trim <= 1, "icp {}: yaw_steps {} or trim {} out of range", in.id,
             cfg.yaw_steps, cfg.trim);
  if (in.canonical.rows() == 0 || in.faces.rows() == 0) {
    res.message = fmt::format("object {}: empty mesh", in.id);
    return res;
  }
  if (in.observed.rows() < cfg.min_points) {
    res.message = fmt::format("object {}: {} valid depth points under the mask, at least {} needed for ICP", in.id,
                              in.observed.rows(), cfg.min_points);
    return res;
  }
  // The shaped canonical mesh (pose scale = s * shape), its surface samples and their tree.
  const Points V = shaped_mesh(in);
  const NearestNeighbors tree(surface_samples(V, in.faces, cfg.surface_samples));
  const Points Y = subsample(in.observed, cfg.max_points);
  const double tau = score_tau(V, in.s_init, cfg);
  res.aligned_score = render_compare_score(V, in.faces, in.R_init, in.s_init, in.t_init, in, tau);
  // The vertical axis: the predicted canonical axis closest to up; the flip axis: the longer horizontal side.
  const Vec3 up = up_in.norm() > 0 ? up_in.normalized() : Vec3(0, -1, 0);
  int v = 0;
  for (int k = 1; k < 3; ++k)
    if (std::abs(in.R_init.col(k).dot(up)) > std::abs(in.R_init.col(v).dot(up))) v = k;
  const Vec3 axis = in.R_init.col(v) * (in.R_init.col(v).dot(up) < 0 ? -1.0 : 1.0);
  const int h1 = (v + 1) % 3, h2 = (v + 2) % 3;
  const Vec3 ext = V.colwise().maxCoeff() - V.colwise().minCoeff();
  const Vec3 flip_axis = in.R_init.col(ext[h1] >= ext[h2] ? h1 : h2);
  // Every hypothesis: turned about the object's centre, refined, scored.
  for (int flip = 0; flip <= (cfg.flips ? 1 : 0); ++flip)
    for (int k = 0; k < cfg.yaw_steps; ++k) {
      IcpHypothesis h;
      h.yaw_deg = 360.0 * k / cfg.yaw_steps;
      h.flipped = flip != 0;
      const Mat3 F = flip ? Mat3(Eigen::AngleAxisd(kPi, flip_axis)) : Mat3::Identity();
      h.R = Eigen::AngleAxisd(h.yaw_deg * kPi / 180, axis).toRotationMatrix() * F * in.R_init;
      h.s = in.s_init;
      h.t = in.t_init;
      const Mat3 R_start = h.R;
      h.residual = trimmed_icp(Y, tree, h.R, h.s, h.t, in.s_init, axis, cfg);
      h.score = render_compare_score(V, in.faces, h.R, h.s, h.t, in, tau);
      // ICP may correct the tilt a little; a hypothesis it tipped further than max_tilt_deg is dropped.
      const Vec3 v_start = R_start.col(v), v_end = h.R.col(v);
      h.tilt_deg = std::acos(std::clamp(v_start.dot(v_end), -1.0, 1.0)) * 180 / kPi;
      h.dropped = h.tilt_deg > cfg.max_tilt_deg;
      res.hypotheses.push_back(h);
    }
  for (size_t k = 0; k < res.hypotheses.size(); ++k)
    if (!res.hypotheses[k].dropped && (res.best < 0 || res.hypotheses[k].score < res.hypotheses[size_t(res.best)].score))
      res.best = int(k);
  if (res.best < 0) {
    res.message = fmt::format("object {}: icp kept the aligned pose (every hypothesis tipped by more than {} deg)",
                              in.id, cfg.max_tilt_deg);
    return res;
  }
  const IcpHypothesis& b = res.hypotheses[size_t(res.best)];
  if (!(b.score < res.aligned_score - cfg.min_gain && b.score < (1 - cfg.min_rel_gain) * res.aligned_score)) {
    res.message = fmt::format("object {}: icp kept the aligned pose (score {:.3f}, best hypothesis {:.3f} at yaw {:.0f})",
                              in.id, res.aligned_score, b.score, b.yaw_deg);
    return res;
  }
  res.changed = true;
  res.R = b.R;
  res.s = b.s;
  res.t = b.t;
  res.turn_deg = angle_deg(in.R_init, b.R);
  return res;
}

}  // namespace simu::reconstruct
