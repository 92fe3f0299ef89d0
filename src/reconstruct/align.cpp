#include "reconstruct/align.h"

#include "common/error.h"
#include "reconstruct/nn.h"
#include "reconstruct/zbuffer.h"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

namespace simu::reconstruct {

namespace {

// Adam on a small parameter vector with per-parameter step sizes.
struct Adam {
  Eigen::VectorXd m, v;
  int step = 0;
  explicit Adam(int n) : m(Eigen::VectorXd::Zero(n)), v(Eigen::VectorXd::Zero(n)) {}
  void update(Eigen::VectorXd& x, const Eigen::VectorXd& g, const Eigen::VectorXd& lr, double b1, double b2,
              double eps) {
    ++step;
    m = b1 * m + (1 - b1) * g;
    v = b2 * v + (1 - b2) * g.cwiseProduct(g);
    const double c1 = 1 - std::pow(b1, step), c2 = 1 - std::pow(b2, step);
    for (int i = 0; i < x.size(); ++i) x[i] -= lr[i] * (m[i] / c1) / (std::sqrt(v[i] / c2) + eps);
  }
};

// L_align and its gradient in (log s, t) for the pose (R, s, t); the tree holds V_vis (canonical).
double align_loss(const Points& Y, const NearestNeighbors& tree, const Mat3& R, double s, const Vec3& t,
                  double* g_logs, Vec3* g_t) {
  double loss = 0, gl = 0;
  Vec3 gt = Vec3::Zero();
  const Mat3 Rt = R.transpose();
  for (Eigen::Index i = 0; i < Y.rows(); ++i) {
    const Vec3 y = Y.row(i).transpose();
    const int64_t j = tree.nearest(Rt * (y - t) / s);
    const Vec3 p = s * (R * tree.points().row(j).transpose());
    const Vec3 r = y - p - t;
    const double d = r.norm();
    loss += d;
    if (d > 1e-12) {
      gt -= r / d;
      gl -= r.dot(p) / d;
    }
  }
  const double n = double(std::max<Eigen::Index>(1, Y.rows()));
  if (g_logs) *g_logs = gl / n;
  if (g_t) *g_t = gt / n;
  return loss / n;
}

}  // namespace

AlignResult align_translation_scale(const AlignInput& in, const AlignConfig& cfg) {
  AlignResult res;
  res.s = in.s_init;
  res.t = in.t_init;
  SIMU_CHECK(in.K.valid(), "align {}: invalid intrinsics", in.id);
  SIMU_CHECK(in.s_init > 0 && std::isfinite(in.s_init), "align {}: initial scale {} is not positive", in.id, in.s_init);
  SIMU_CHECK(!cfg.rho.empty(), "align {}: no multi-start factor (rho) given", in.id);
  if (in.canonical.rows() == 0 || in.faces.rows() == 0) {
    res.message = fmt::format("object {}: empty mesh", in.id);
    return res;
  }
  if (in.observed.rows() < cfg.min_points) {
    res.message = fmt::format("object {}: {} valid depth points under the mask, at least {} needed", in.id,
                              in.observed.rows(), cfg.min_points);
    return res;
  }
  // The shaped canonical mesh, densified, placed at the initial pose (camera frame).
  Points V(in.canonical.rows(), 3);
  for (Eigen::Index i = 0; i < V.rows(); ++i) V.row(i) = in.canonical.row(i).cwiseProduct(in.shape.transpose());
  Faces F = in.faces;
  densify(V, F, cfg.max_edge * std::max(1e-9, in.shape.maxCoeff()));
  const Similarity T0{in.s_init, in.R_init, in.t_init};
  const Points V0 = transform(V, T0);
  const double diag = (V0.colwise().maxCoeff() - V0.colwise().minCoeff()).norm();
  // Visibility once, at the initial pose.
  const std::vector<int64_t> vis = visible_vertices(V0, F, in.K, cfg.visibility_tol * diag);
  res.visible_vertices = int64_t(vis.size());
  if (vis.size() < 3) {
    res.message = fmt::format("object {}: {} vertices visible at the initial pose (behind the camera or off the image?)",
                              in.id, vis.size());
    return res;
  }
  Points Vvis(Eigen::Index(vis.size()), 3);
  for (size_t i = 0; i < vis.size(); ++i) Vvis.row(Eigen::Index(i)) = V.row(vis[i]);
  const NearestNeighbors tree(Vvis);
  const Points Y = subsample(in.observed, cfg.max_points);
  res.points_used = Y.rows();
  const NearestNeighbors obs_tree(Y);
  const double obs_diag = (Y.colwise().maxCoeff() - Y.colwise().minCoeff()).norm();
  const double obs_mean_z = Y.col(2).mean();
  const int64_t mask_n = in.mask.count();
  SIMU_CHECK(in.mask.width == in.K.width && in.mask.height == in.K.height,
             "align {}: mask is {}x{}, the image {}x{}", in.id, in.mask.width, in.mask.height, in.K.width, in.K.height);

  Eigen::VectorXd lr(4);
  lr << cfg.lr_log_scale, cfg.lr_translation * obs_diag, cfg.lr_translation * obs_diag, cfg.lr_translation * obs_diag;
  const double log_s_init = std::log(in.s_init);
  for (double rho : cfg.rho) {
    AlignCandidate c;
    c.rho = rho;
    // x = (log s, t).
    // t_0: t_init moved along its viewing ray so that the visible vertices' mean depth at s_0 equals the
    // observed points' mean depth (ours; the paper does not say how t starts).
    Vec3 t0 = in.t_init;
    if (cfg.depth_init && in.t_init.z() > 0) {
      const Mat3 A = rho * in.s_init * in.R_init;
      double zv = 0;
      for (Eigen::Index i = 0; i < Vvis.rows(); ++i) zv += (A * Vvis.row(i).transpose()).z();
      zv /= double(Vvis.rows());
      const Vec3 dir = in.t_init.normalized();
      t0 = in.t_init + ((obs_mean_z - zv - in.t_init.z()) / dir.z()) * dir;
    }
    Eigen::VectorXd x(4);
    x << std::log(rho * in.s_init), t0.x(), t0.y(), t0.z();
    Adam adam(4);
    for (int it = 0; it < cfg.iterations; ++it) {
      double gl = 0;
      Vec3 gt;
      const double s = std::exp(x[0]);
      align_loss(Y, tree, in.R_init, s, x.tail<3>(), &gl, &gt);
      Eigen::VectorXd g(4);
      g << gl + 2 * cfg.lambda * (x[0] - log_s_init), gt.x(), gt.y(), gt.z();
      const double decay = 1.0 - 0.9 * double(it) / double(std::max(1, cfg.iterations - 1));
      adam.update(x, g, lr * decay, cfg.beta1, cfg.beta2, cfg.eps);
    }
    c.s = std::exp(x[0]);
    c.t = x.tail<3>();
    c.chamfer = align_loss(Y, tree, in.R_init, c.s, c.t, nullptr, nullptr);
    c.loss = c.chamfer + cfg.lambda * std::pow(x[0] - log_s_init, 2);
    // Selection terms: silhouette recall of the mask, bidirectional chamfer on unoccluded visible vertices.
    const Similarity Tc{c.s, in.R_init, c.t};
    const Points Vc = transform(V, Tc);
    const Mask sil = silhouette(render_depth(Vc, F, in.K), in.K);
    int64_t hit = 0;
    for (size_t i = 0; i < sil.data.size(); ++i) hit += sil.data[i] && in.mask.data[i];
    c.recall = mask_n > 0 ? double(hit) / double(mask_n) : 0.0;
    double mesh_side = 0;
    int64_t mesh_n = 0;
    for (int64_t j : vis) {
      const Vec3 p = Vc.row(j).transpose();
      if (in.depth && p.z() > 0) {
        const int col = int(std::lround(in.K.fx * p.x() / p.z() + in.K.cx));
        const int row = int(std::lround(in.K.fy * p.y() / p.z() + in.K.cy));
        if (col >= 0 && row >= 0 && col < in.K.width && row < in.K.height && !in.mask.at(row, col)) {
          const Vec3& o = in.depth->at(row, col);
          if (PointMap::valid(o) && o.z() < p.z() - cfg.occlusion_margin) continue;  // hidden by something in front
        }
      }
      double d2 = 0;
      obs_tree.nearest(p, &d2);
      mesh_side += std::sqrt(d2);
      ++mesh_n;
    }
    c.bichamfer = 0.5 * (c.chamfer + (mesh_n ? mesh_side / double(mesh_n) : 0.0));
    res.candidates.push_back(c);
  }
  // align_select with the tildes as division by the largest value over the candidates.
  double max_recall = 0, max_bi = 0;
  for (auto& c : res.candidates) {
    max_recall = std::max(max_recall, c.recall);
    max_bi = std::max(max_bi, c.bichamfer);
  }
  double best = -1e300;
  for (size_t k = 0; k < res.candidates.size(); ++k) {
    auto& c = res.candidates[k];
    const double rn = max_recall > 0 ? c.recall / max_recall : 0.0;
    const double bn = max_bi > 0 ? c.bichamfer / max_bi : 0.0;
    c.score = 0.5 * rn + 0.5 * (1 - bn);
    if (c.score > best) {
      best = c.score;
      res.best = int(k);
    }
  }
  res.s = res.s_selected = res.candidates[size_t(res.best)].s;
  res.t = res.t_selected = res.candidates[size_t(res.best)].t;
  if (cfg.polish_iterations > 0) {
    // The mesh side's vertices: visible at the initial pose, not hidden behind the observed depth at the
    // selected pose (fixed during the polish).
    const Points Vs = transform(V, Similarity{res.s, in.R_init, res.t});
    std::vector<int64_t> keep;
    for (int64_t j : vis) {
      const Vec3 p = Vs.row(j).transpose();
      bool hidden = false;
      if (in.depth && p.z() > 0) {
        const int col = int(std::lround(in.K.fx * p.x() / p.z() + in.K.cx));
        const int row = int(std::lround(in.K.fy * p.y() / p.z() + in.K.cy));
        if (col >= 0 && row >= 0 && col < in.K.width && row < in.K.height && !in.mask.at(row, col)) {
          const Vec3& o = in.depth->at(row, col);
          hidden = PointMap::valid(o) && o.z() < p.z() - cfg.occlusion_margin;
        }
      }
      if (!hidden) keep.push_back(j);
    }
    Points Vm(Eigen::Index(keep.size()), 3);
    for (size_t i = 0; i < keep.size(); ++i) Vm.row(Eigen::Index(i)) = V.row(keep[i]);
    Vm = subsample(Vm, cfg.max_points);
    if (Vm.rows() >= 3) {
      Eigen::VectorXd x(4);
      x << std::log(res.s), res.t.x(), res.t.y(), res.t.z();
      Adam adam(4);
      for (int it = 0; it < cfg.polish_iterations; ++it) {
        const double s = std::exp(x[0]);
        const Vec3 t = x.tail<3>();
        double gl = 0;
        Vec3 gt;
        align_loss(Y, tree, in.R_init, s, t, &gl, &gt);
        double gl2 = 0;
        Vec3 gt2 = Vec3::Zero();
        for (Eigen::Index i = 0; i < Vm.rows(); ++i) {
          const Vec3 p = s * (in.R_init * Vm.row(i).transpose());
          const Vec3 r = p + t - obs_tree.points().row(obs_tree.nearest(p + t)).transpose();
          const double d = r.norm();
          if (d > 1e-12) {
            gt2 += r / d;
            gl2 += r.dot(p) / d;
          }
        }
        gl2 /= double(Vm.rows());
        gt2 /= double(Vm.rows());
        Eigen::VectorXd g(4);
        g << 0.5 * (gl + gl2) + 2 * cfg.lambda * (x[0] - log_s_init), 0.5 * (gt + gt2).x(), 0.5 * (gt + gt2).y(),
            0.5 * (gt + gt2).z();
        const double decay = 1.0 - 0.9 * double(it) / double(std::max(1, cfg.polish_iterations - 1));
        adam.update(x, g, 0.25 * lr * decay, cfg.beta1, cfg.beta2, cfg.eps);
      }
      res.s = std::exp(x[0]);
      res.t = x.tail<3>();
    }
  }
  res.ok = true;
  return res;
}

}  // namespace simu::reconstruct
