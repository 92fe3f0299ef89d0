#include "pipeline/reconstruct/align.h"

#include "common/error.h"
#include "pipeline/reconstruct/nn.h"
#include "pipeline/reconstruct/zbuffer.h"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <memory>

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

namespace {

// True when camera-frame point p projects outside the object's mask onto an observed depth point that lies
// more than the occlusion margin in front of it (p is hidden by something else).
bool hidden_behind_depth(const Vec3& p, const AlignInput& in, const AlignConfig& cfg) {
  if (!in.depth || p.z() <= 0) return false;
  const int col = int(std::lround(in.K.fx * p.x() / p.z() + in.K.cx));
  const int row = int(std::lround(in.K.fy * p.y() / p.z() + in.K.cy));
  if (col < 0 || row < 0 || col >= in.K.width || row >= in.K.height || in.mask.at(row, col)) return false;
  const Vec3& o = in.depth->at(row, col);
  return PointMap::valid(o) && o.z() < p.z() - cfg.occlusion_margin;
}

// What every start shares: the densified shaped mesh, its visible vertices at the initial pose (z-buffer
// once), nearest-neighbour trees of the visible vertices and of the observed points, Adam's step sizes.
struct AlignSetup {
  Points V;                  // [n, 3] densified canonical mesh times the shape
  Faces F;                   // [m, 3]
  std::vector<int64_t> vis;  // rows of V visible at the initial pose
  Points Vvis;               // [vis, 3]
  Points Y;                  // [k, 3] observed points used (subsampled)
  std::unique_ptr<NearestNeighbors> tree, obs_tree;
  double obs_mean_z = 0;
  int64_t mask_n = 0;
  Eigen::VectorXd lr;  // [4] (log s, t)
  double log_s_init = 0;
};

// One start of the multi-start Adam (align_loss + align_reg), then its selection terms (silhouette
// recall of the mask, bidirectional chamfer on unoccluded visible vertices).
AlignCandidate run_start(double rho, const AlignInput& in, const AlignConfig& cfg, const AlignSetup& su) {
  AlignCandidate c;
  c.rho = rho;
  // x = (log s, t).
  // t_0: t_init moved along its viewing ray so that the visible vertices' mean depth at s_0 equals the
  // observed points' mean depth (ours; the paper does not say how t starts).
  Vec3 t0 = in.t_init;
  if (cfg.depth_init && in.t_init.z() > 0) {
    const Mat3 A = rho * in.s_init * in.R_init;
    double zv = 0;
    for (Eigen::Index i = 0; i < su.Vvis.rows(); ++i) zv += (A * su.Vvis.row(i).transpose()).z();
    zv /= double(su.Vvis.rows());
    const Vec3 dir = in.t_init.normalized();
    t0 = in.t_init + ((su.obs_mean_z - zv - in.t_init.z()) / dir.z()) * dir;
  }
  Eigen::VectorXd x(4);
  x << std::log(rho * in.s_init), t0.x(), t0.y(), t0.z();
  Adam adam(4);
  for (int it = 0; it < cfg.iterations; ++it) {
    double gl = 0;
    Vec3 gt;
    const double s = std::exp(x[0]);
    align_loss(su.Y, *su.tree, in.R_init, s, x.tail<3>(), &gl, &gt);
    Eigen::VectorXd g(4);
    g << gl + 2 * cfg.lambda * (x[0] - su.log_s_init), gt.x(), gt.y(), gt.z();
    const double decay = 1.0 - 0.9 * double(it) / double(std::max(1, cfg.iterations - 1));
    adam.update(x, g, su.lr * decay, cfg.beta1, cfg.beta2, cfg.eps);
  }
  c.s = std::exp(x[0]);
  c.t = x.tail<3>();
  c.chamfer = align_loss(su.Y, *su.tree, in.R_init, c.s, c.t, nullptr, nullptr);
  c.loss = c.chamfer + cfg.lambda * std::pow(x[0] - su.log_s_init, 2);
  // Selection terms.
  const Points Vc = transform(su.V, Similarity{c.s, in.R_init, c.t});
  const Mask sil = silhouette(render_depth(Vc, su.F, in.K), in.K);
  int64_t hit = 0;
  for (size_t i = 0; i < sil.data.size(); ++i) hit += sil.data[i] && in.mask.data[i];
  c.recall = su.mask_n > 0 ? double(hit) / double(su.mask_n) : 0.0;
  double mesh_side = 0;
  int64_t mesh_n = 0;
  for (int64_t j : su.vis) {
    const Vec3 p = Vc.row(j).transpose();
    if (hidden_behind_depth(p, in, cfg)) continue;
    double d2 = 0;
    su.obs_tree->nearest(p, &d2);
    mesh_side += std::sqrt(d2);
    ++mesh_n;
  }
  c.bichamfer = 0.5 * (c.chamfer + (mesh_n ? mesh_side / double(mesh_n) : 0.0));
  return c;
}

// align_select with the tildes as division by the largest value over the candidates; sets scores and best.
void select_candidate(AlignResult& res) {
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
}

// The experimental L_bi polish (off by default): Adam on the symmetric chamfer from the selected pose.
void polish(AlignResult& res, const AlignInput& in, const AlignConfig& cfg, const AlignSetup& su) {
  // The mesh side's vertices: visible at the initial pose, not hidden behind the observed depth at the
  // selected pose (fixed during the polish).
  const Points Vs = transform(su.V, Similarity{res.s, in.R_init, res.t});
  std::vector<int64_t> keep;
  for (int64_t j : su.vis)
    if (!hidden_behind_depth(Vs.row(j).transpose(), in, cfg)) keep.push_back(j);
  Points Vm(Eigen::Index(keep.size()), 3);
  for (size_t i = 0; i < keep.size(); ++i) Vm.row(Eigen::Index(i)) = su.V.row(keep[i]);
  Vm = subsample(Vm, cfg.max_points);
  if (Vm.rows() < 3) return;
  Eigen::VectorXd x(4);
  x << std::log(res.s), res.t.x(), res.t.y(), res.t.z();
  Adam adam(4);
  for (int it = 0; it < cfg.polish_iterations; ++it) {
    const double s = std::exp(x[0]);
    const Vec3 t = x.tail<3>();
    double gl = 0;
    Vec3 gt;
    align_loss(su.Y, *su.tree, in.R_init, s, t, &gl, &gt);
    double gl2 = 0;
    Vec3 gt2 = Vec3::Zero();
    for (Eigen::Index i = 0; i < Vm.rows(); ++i) {
      const Vec3 p = s * (in.R_init * Vm.row(i).transpose());
      const Vec3 r = p + t - su.obs_tree->points().row(su.obs_tree->nearest(p + t)).transpose();
      const double d = r.norm();
      if (d > 1e-12) {
        gt2 += r / d;
        gl2 += r.dot(p) / d;
      }
    }
    gl2 /= double(Vm.rows());
    gt2 /= double(Vm.rows());
    Eigen::VectorXd g(4);
    g << 0.5 * (gl + gl2) + 2 * cfg.lambda * (x[0] - su.log_s_init), 0.5 * (gt + gt2).x(), 0.5 * (gt + gt2).y(),
        0.5 * (gt + gt2).z();
    const double decay = 1.0 - 0.9 * double(it) / double(std::max(1, cfg.polish_iterations - 1));
    adam.update(x, g, 0.25 * su.lr * decay, cfg.beta1, cfg.beta2, cfg.eps);
  }
  res.s = std::exp(x[0]);
  res.t = x.tail<3>();
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
  AlignSetup su;
  su.V.resize(in.canonical.rows(), 3);
  for (Eigen::Index i = 0; i < su.V.rows(); ++i) su.V.row(i) = in.canonical.row(i).cwiseProduct(in.shape.transpose());
  su.F = in.faces;
  densify(su.V, su.F, cfg.max_edge * std::max(1e-9, in.shape.maxCoeff()));
  const Points V0 = transform(su.V, Similarity{in.s_init, in.R_init, in.t_init});
  const double diag = (V0.colwise().maxCoeff() - V0.colwise().minCoeff()).norm();
  // Visibility once, at the initial pose.
  su.vis = visible_vertices(V0, su.F, in.K, cfg.visibility_tol * diag);
  res.visible_vertices = int64_t(su.vis.size());
  if (su.vis.size() < 3) {
    res.message = fmt::format("object {}: {} vertices visible at the initial pose (behind the camera or off the image?)",
                              in.id, su.vis.size());
    return res;
  }
  su.Vvis.resize(Eigen::Index(su.vis.size()), 3);
  for (size_t i = 0; i < su.vis.size(); ++i) su.Vvis.row(Eigen::Index(i)) = su.V.row(su.vis[i]);
  su.tree = std::make_unique<NearestNeighbors>(su.Vvis);
  su.Y = subsample(in.observed, cfg.max_points);
  res.points_used = su.Y.rows();
  su.obs_tree = std::make_unique<NearestNeighbors>(su.Y);
  const double obs_diag = (su.Y.colwise().maxCoeff() - su.Y.colwise().minCoeff()).norm();
  su.obs_mean_z = su.Y.col(2).mean();
  su.mask_n = in.mask.count();
  SIMU_CHECK(in.mask.width == in.K.width && in.mask.height == in.K.height,
             "align {}: mask is {}x{}, the image {}x{}", in.id, in.mask.width, in.mask.height, in.K.width, in.K.height);
  su.lr.resize(4);
  su.lr << cfg.lr_log_scale, cfg.lr_translation * obs_diag, cfg.lr_translation * obs_diag, cfg.lr_translation * obs_diag;
  su.log_s_init = std::log(in.s_init);
  // Multi-start from s_0 = rho_k * s_init, then align_select.
  for (double rho : cfg.rho) res.candidates.push_back(run_start(rho, in, cfg, su));
  select_candidate(res);
  res.s = res.s_selected = res.candidates[size_t(res.best)].s;
  res.t = res.t_selected = res.candidates[size_t(res.best)].t;
  if (cfg.polish_iterations > 0) polish(res, in, cfg, su);
  res.ok = true;
  return res;
}

}  // namespace simu::reconstruct
