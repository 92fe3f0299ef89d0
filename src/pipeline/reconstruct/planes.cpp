#include "pipeline/reconstruct/planes.h"

#include "common/error.h"

#include <fmt/format.h>

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <limits>
#include <cmath>
#include <numeric>
#include <random>

namespace simu::reconstruct {

namespace {
constexpr double kPi = 3.14159265358979323846;
double deg(double rad) { return rad * 180.0 / kPi; }

// Least-squares plane through points (centroid, smallest principal axis).
PlaneFit fit_lsq(const Points& P, const std::vector<int64_t>& idx) {
  Vec3 c = Vec3::Zero();
  for (int64_t i : idx) c += P.row(i).transpose();
  c /= double(idx.size());
  Mat3 C = Mat3::Zero();
  for (int64_t i : idx) {
    const Vec3 d = P.row(i).transpose() - c;
    C += d * d.transpose();
  }
  Eigen::SelfAdjointEigenSolver<Mat3> es(C);
  PlaneFit f;
  f.point = c;
  f.normal = es.eigenvectors().col(0).normalized();
  return f;
}
}  // namespace

double angle_deg(const Vec3& a, const Vec3& b) {
  return deg(std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)));
}
double line_angle_deg(const Vec3& a, const Vec3& b) {
  return deg(std::acos(std::clamp(std::abs(a.normalized().dot(b.normalized())), 0.0, 1.0)));
}

std::optional<PlaneFit> ransac_plane(const Points& P, const RansacConfig& cfg) {
  const int64_t n = P.rows();
  if (n < std::max<int64_t>(3, cfg.min_inliers)) return std::nullopt;
  std::mt19937_64 rng(cfg.seed);
  std::uniform_int_distribution<int64_t> pick(0, n - 1);
  const bool constrained = cfg.axis.norm() > 0 && cfg.max_angle_deg < 90;
  const double cos_max = std::cos(cfg.max_angle_deg * kPi / 180.0);
  int64_t best_count = -1;
  Vec3 best_n = Vec3::Zero(), best_p = Vec3::Zero();
  for (int it = 0; it < cfg.iterations; ++it) {
    const Vec3 a = P.row(pick(rng)).transpose(), b = P.row(pick(rng)).transpose(), c = P.row(pick(rng)).transpose();
    Vec3 nrm = (b - a).cross(c - a);
    if (nrm.norm() < 1e-12) continue;
    nrm.normalize();
    if (constrained && std::abs(nrm.dot(cfg.axis.normalized())) < cos_max) continue;
    int64_t count = 0;
    for (int64_t i = 0; i < n; ++i) count += std::abs(nrm.dot(P.row(i).transpose() - a)) <= cfg.threshold;
    if (count > best_count) {
      best_count = count;
      best_n = nrm;
      best_p = a;
    }
  }
  if (best_count < cfg.min_inliers) return std::nullopt;
  // Refit on the inliers twice (the refit can gather a few more).
  PlaneFit f;
  f.point = best_p;
  f.normal = best_n;
  for (int pass = 0; pass < 2; ++pass) {
    std::vector<int64_t> in;
    for (int64_t i = 0; i < n; ++i)
      if (std::abs(f.distance(P.row(i).transpose())) <= cfg.threshold) in.push_back(i);
    if (int64_t(in.size()) < std::max<int64_t>(3, cfg.min_inliers)) break;
    PlaneFit g = fit_lsq(P, in);
    if (constrained && std::abs(g.normal.dot(cfg.axis.normalized())) < cos_max) break;
    f = g;
  }
  std::vector<int64_t> in;
  double ss = 0;
  for (int64_t i = 0; i < n; ++i) {
    const double d = f.distance(P.row(i).transpose());
    if (std::abs(d) <= cfg.threshold) {
      in.push_back(i);
      ss += d * d;
    }
  }
  f.inliers = int64_t(in.size());
  f.rms = in.empty() ? 0 : std::sqrt(ss / double(in.size()));
  if (f.inliers < cfg.min_inliers) return std::nullopt;
  return f;
}

std::vector<int> dbscan_directions(const std::vector<Vec3>& dirs, double eps_deg, int min_points) {
  const size_t n = dirs.size();
  std::vector<int> label(n, -2);  // -2 unvisited, -1 noise
  auto neighbours = [&](size_t i) {
    std::vector<size_t> out;
    for (size_t j = 0; j < n; ++j)
      if (line_angle_deg(dirs[i], dirs[j]) <= eps_deg) out.push_back(j);
    return out;
  };
  int cluster = 0;
  for (size_t i = 0; i < n; ++i) {
    if (label[i] != -2) continue;
    auto nb = neighbours(i);
    if (int(nb.size()) < min_points) {
      label[i] = -1;
      continue;
    }
    label[i] = cluster;
    std::vector<size_t> queue(nb.begin(), nb.end());
    for (size_t q = 0; q < queue.size(); ++q) {
      const size_t j = queue[q];
      if (label[j] == -1) label[j] = cluster;
      if (label[j] != -2) continue;
      label[j] = cluster;
      auto nb2 = neighbours(j);
      if (int(nb2.size()) >= min_points) queue.insert(queue.end(), nb2.begin(), nb2.end());
    }
    ++cluster;
  }
  return label;
}

PlanesResult fit_planes(const Points& floor_points, const std::vector<WallInput>& walls, const Points& all_points,
                        const Vec3& mesh_up, const PlanesConfig& cfg) {
  PlanesResult res;
  const Vec3 cam_up = -Vec3::UnitY();
  // Floor: 5 cm RANSAC, normal within max_floor_tilt of the camera's up, oriented up.
  if (floor_points.rows() > 0) {
    RansacConfig rc;
    rc.threshold = cfg.floor_threshold;
    rc.iterations = cfg.iterations;
    rc.seed = cfg.seed;
    rc.min_inliers = cfg.min_support;
    rc.axis = cam_up;
    rc.max_angle_deg = cfg.max_floor_tilt_deg;
    if (auto f = ransac_plane(floor_points, rc)) {
      if (f->normal.dot(cam_up) < 0) f->normal = -f->normal;
      res.floor = NamedPlane{"floor", *f};
    } else {
      res.messages.push_back(fmt::format("floor: no plane with >= {} inliers within {} deg of the camera's up among "
                                         "{} floor points (degenerate fit): floor mask ignored",
                                         cfg.min_support, cfg.max_floor_tilt_deg, floor_points.rows()));
    }
  }
  // Walls: 1 cm RANSAC each, normals into the room (towards the camera at the origin).
  std::vector<NamedPlane> fitted;
  for (const auto& w : walls) {
    RansacConfig rc;
    rc.threshold = cfg.wall_threshold;
    rc.iterations = cfg.iterations;
    rc.seed = cfg.seed + 1 + fitted.size();
    rc.min_inliers = cfg.min_support;
    auto f = ransac_plane(w.points, rc);
    if (!f) {
      res.messages.push_back(fmt::format("wall {}: no plane with >= {} inliers among {} points (degenerate fit): skipped",
                                         w.id, cfg.min_support, w.points.rows()));
      continue;
    }
    if (f->normal.dot(-f->point) < 0) f->normal = -f->normal;
    if (res.floor && line_angle_deg(f->normal, res.floor->plane.normal) < 90 - cfg.max_floor_tilt_deg) {
      res.messages.push_back(fmt::format("wall {}: its plane is within {:.1f} deg of the floor's: not a wall, skipped", w.id,
                                         line_angle_deg(f->normal, res.floor->plane.normal)));
      continue;
    }
    fitted.push_back({w.id, *f});
  }
  // Orientation clusters (DBSCAN), orthogonality to the best-covered cluster, top walls by coverage.
  if (!fitted.empty()) {
    std::vector<Vec3> dirs;
    for (auto& w : fitted) dirs.push_back(w.plane.normal);
    const std::vector<int> lab = dbscan_directions(dirs, cfg.dbscan_eps_deg, 1);
    const int nc = *std::max_element(lab.begin(), lab.end()) + 1;
    std::vector<int64_t> cover(size_t(nc), 0);
    std::vector<Vec3> mean(size_t(nc), Vec3::Zero());
    for (size_t i = 0; i < fitted.size(); ++i) {
      cover[size_t(lab[i])] += fitted[i].plane.inliers;
      const Vec3& ref = dirs[size_t(std::find(lab.begin(), lab.end(), lab[i]) - lab.begin())];
      mean[size_t(lab[i])] += double(fitted[i].plane.inliers) * (dirs[i].dot(ref) < 0 ? -dirs[i] : dirs[i]);
    }
    const int main = int(std::max_element(cover.begin(), cover.end()) - cover.begin());
    std::vector<NamedPlane> kept;
    for (size_t i = 0; i < fitted.size(); ++i) {
      const int c = lab[i];
      const double a = line_angle_deg(mean[size_t(c)], mean[size_t(main)]);
      if (c != main && std::abs(a - 90) > cfg.orthogonality_tol_deg) {
        res.messages.push_back(fmt::format("wall {}: its orientation cluster is {:.1f} deg from the main one "
                                           "(not orthogonal within {} deg): dropped",
                                           fitted[i].id, a, cfg.orthogonality_tol_deg));
        continue;
      }
      kept.push_back(fitted[i]);
    }
    std::stable_sort(kept.begin(), kept.end(),
                     [](const NamedPlane& a, const NamedPlane& b) { return a.plane.inliers > b.plane.inliers; });
    if (int(kept.size()) > cfg.max_walls) {
      for (size_t i = size_t(cfg.max_walls); i < kept.size(); ++i)
        res.messages.push_back(fmt::format("wall {}: not among the top {} walls by coverage: dropped", kept[i].id,
                                           cfg.max_walls));
      kept.resize(size_t(cfg.max_walls));
    }
    res.walls = kept;
  }
  // Fallback floor: the lowest upward-facing plane of the point map with enough support.
  if (!res.floor && floor_points.rows() == 0 && all_points.rows() > 0) {
    Points rest = all_points;
    std::vector<PlaneFit> found;
    for (int k = 0; k < cfg.fallback_planes && rest.rows() >= cfg.min_support; ++k) {
      RansacConfig rc;
      rc.threshold = cfg.floor_threshold;
      rc.iterations = cfg.iterations;
      rc.seed = cfg.seed + 100 + k;
      rc.min_inliers = cfg.min_support;
      rc.axis = cam_up;
      rc.max_angle_deg = cfg.max_floor_tilt_deg;
      auto f = ransac_plane(rest, rc);
      if (!f) break;
      if (f->normal.dot(cam_up) < 0) f->normal = -f->normal;
      found.push_back(*f);
      Points next(rest.rows(), 3);
      Eigen::Index m = 0;
      for (Eigen::Index i = 0; i < rest.rows(); ++i)
        if (std::abs(f->distance(rest.row(i).transpose())) > cfg.floor_threshold) next.row(m++) = rest.row(i);
      rest = next.topRows(m);
    }
    if (!found.empty()) {
      auto low = std::min_element(found.begin(), found.end(), [&](const PlaneFit& a, const PlaneFit& b) {
        return a.point.dot(cam_up) < b.point.dot(cam_up);
      });
      res.floor = NamedPlane{"floor", *low};
      res.fallback = true;
      res.messages.push_back(fmt::format("no floor mask: the floor is the lowest supported plane of the point map "
                                         "({} inliers, {} upward planes found)", low->inliers, found.size()));
    } else {
      res.messages.push_back("no floor mask and no upward-facing plane in the point map: no floor");
    }
  }
  // Manhattan rectification: up from two orthogonal walls, else the floor, else the mesh-derived up.
  const Vec3 ref = res.floor ? res.floor->plane.normal : cam_up;
  bool have_up = false;
  for (size_t i = 0; i < res.walls.size() && !have_up; ++i)
    for (size_t j = i + 1; j < res.walls.size() && !have_up; ++j) {
      const Vec3& a = res.walls[i].plane.normal;
      const Vec3& b = res.walls[j].plane.normal;
      if (std::abs(line_angle_deg(a, b) - 90) <= cfg.orthogonality_tol_deg) {
        Vec3 u = a.cross(b).normalized();
        if (u.dot(ref) < 0) u = -u;
        res.up = u;
        res.up_source = "walls";
        have_up = true;
      }
    }
  if (!have_up && res.floor) {
    res.up = res.floor->plane.normal;
    res.up_source = "floor";
    have_up = true;
  }
  if (!have_up && mesh_up.norm() > 0) {
    res.up = mesh_up.normalized();
    res.up_source = "mesh";
    have_up = true;
  }
  if (!have_up) {
    res.up = cam_up;
    res.up_source = "camera";
    res.messages.push_back("no wall pair, floor or mesh up: up is the camera's -y");
  }
  for (auto& w : res.walls) {
    Vec3 n = w.plane.normal - w.plane.normal.dot(res.up) * res.up;
    if (n.norm() < 1e-6) continue;
    w.plane.normal = n.normalized();
  }
  if (res.floor) res.floor->plane.normal = res.up;
  return res;
}

double snap_floor_to_meshes(PlanesResult& planes, const std::vector<Points>& meshes, double max_snap) {
  double low = std::numeric_limits<double>::infinity();
  Vec3 at = Vec3::Zero();
  for (const auto& M : meshes)
    for (Eigen::Index i = 0; i < M.rows(); ++i) {
      const double h = planes.up.dot(M.row(i).transpose());
      if (h < low) {
        low = h;
        at = M.row(i).transpose();
      }
    }
  if (!std::isfinite(low)) return 0;
  if (!planes.floor) {
    planes.floor = NamedPlane{"floor", PlaneFit{at, planes.up, 0, 0}};
    planes.messages.push_back("no floor plane: the floor is placed at the lowest vertex of the fitted meshes");
    return 0;
  }
  const double before = planes.up.dot(planes.floor->plane.point);
  if (std::abs(low - before) > max_snap) {
    planes.messages.push_back(fmt::format("floor snap refused: the lowest fitted-mesh vertex is {:+.3f} m from the fitted "
                                          "floor (more than {} m): the floor plane is kept",
                                          low - before, max_snap));
    return 0;
  }
  planes.floor->plane.point = planes.floor->plane.point + (low - before) * planes.up;
  planes.floor->plane.normal = planes.up;
  return low - before;
}

}  // namespace simu::reconstruct
