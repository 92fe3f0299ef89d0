// Surface samples and exact point-to-surface distances (bounding-volume hierarchy over triangles).
#include "pipeline/physics/surface_distance.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "common/error.h"
#include "common/random.h"

namespace simu::physics {

namespace {

// Vertex k of triangle f.
Vec3 corner(const Mesh& m, int f, int k) { return m.V.row(m.F(f, k)).transpose(); }

double triangle_area(const Mesh& m, int f) {
  return 0.5 * (corner(m, f, 1) - corner(m, f, 0)).cross(corner(m, f, 2) - corner(m, f, 0)).norm();
}

// Throws when a face index is outside the vertex array.
void check_faces(const Mesh& m, const char* what) {
  SIMU_CHECK(m.F.rows() > 0, "{}: the mesh has no triangles", what);
  for (Eigen::Index f = 0; f < m.F.rows(); ++f)
    for (int k = 0; k < 3; ++k)
      SIMU_CHECK(m.F(f, k) >= 0 && m.F(f, k) < m.V.rows(), "{}: face {} index {} is outside the {} vertices", what, f,
                 m.F(f, k), m.V.rows());
}

// SplitMix64 stream: uniform doubles in [0, 1) with 53 random bits.
struct Uniform {
  uint64_t state;
  double operator()() {
    const uint64_t r = splitmix64(state);
    state += 0x9E3779B97F4A7C15ULL;
    return static_cast<double>(r >> 11) * 0x1.0p-53;
  }
};

// Squared distance from p to the box [lo, hi] (0 inside).
double box_distance2(const Vec3& p, const Vec3& lo, const Vec3& hi) {
  const Vec3 d = (lo - p).cwiseMax(Vec3::Zero()).cwiseMax(p - hi);
  return d.squaredNorm();
}

}  // namespace

double surface_area(const Mesh& mesh) {
  double a = 0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) a += triangle_area(mesh, static_cast<int>(f));
  return a;
}

Vec3 surface_centroid(const Mesh& mesh) {
  Vec3 c = Vec3::Zero();
  double area = 0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    const int i = static_cast<int>(f);
    const double a = triangle_area(mesh, i);
    c += a * (corner(mesh, i, 0) + corner(mesh, i, 1) + corner(mesh, i, 2)) / 3.0;
    area += a;
  }
  SIMU_CHECK(area > 0, "surface centroid: the mesh has no triangle of positive area");
  return c / area;
}

Points sample_surface(const Mesh& mesh, int64_t n, uint64_t seed) {
  SIMU_CHECK(n >= 1, "surface samples: n must be >= 1 (got {})", n);
  check_faces(mesh, "surface samples");
  // Cumulative areas: triangle f owns (cum[f-1], cum[f]]; zero-area triangles own an empty interval.
  std::vector<double> cum(mesh.F.rows());
  double total = 0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) cum[f] = total += triangle_area(mesh, static_cast<int>(f));
  SIMU_CHECK(total > 0, "surface samples: the mesh has no triangle of positive area");
  Uniform u{splitmix64(seed)};
  Points P(n, 3);
  for (int64_t i = 0; i < n; ++i) {
    const double pick = u() * total;
    // First triangle whose cumulative area exceeds pick (never a zero-area one: its interval is empty).
    const auto it = std::upper_bound(cum.begin(), cum.end(), pick);
    const int f = static_cast<int>(std::min<std::ptrdiff_t>(it - cum.begin(), cum.size() - 1));
    const double r1 = std::sqrt(u()), r2 = u();
    const Vec3 p = (1 - r1) * corner(mesh, f, 0) + r1 * (1 - r2) * corner(mesh, f, 1) + r1 * r2 * corner(mesh, f, 2);
    P.row(i) = p.transpose();
  }
  return P;
}

Vec3 closest_point_on_triangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c) {
  // Voronoi regions in turn: vertex a, b, c, edges ab, ac, bc, then the face (barycentric projection).
  const Vec3 ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const Vec3 bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return a + (d1 / (d1 - d3)) * ab;
  const Vec3 cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return a + (d2 / (d2 - d6)) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b);
  const double denom = va + vb + vc;
  if (!(denom > 0)) {
    // Degenerate (collinear) triangle: the nearest of its three edges.
    auto seg = [&](const Vec3& s, const Vec3& e) {
      const Vec3 d = e - s;
      const double len2 = d.squaredNorm();
      const double t = len2 > 0 ? std::clamp((p - s).dot(d) / len2, 0.0, 1.0) : 0.0;
      return Vec3(s + t * d);
    };
    Vec3 best = seg(a, b);
    for (const Vec3& q : {seg(a, c), seg(b, c)})
      if ((q - p).squaredNorm() < (best - p).squaredNorm()) best = q;
    return best;
  }
  return a + ab * (vb / denom) + ac * (vc / denom);
}

SurfaceDistance::SurfaceDistance(const Mesh& mesh) : mesh_(mesh) {
  check_faces(mesh_, "surface distance");
  const int n = static_cast<int>(mesh_.F.rows());
  tris_.resize(n);
  std::vector<Vec3> centres(n);
  for (int f = 0; f < n; ++f) {
    tris_[f] = f;
    centres[f] = (corner(mesh_, f, 0) + corner(mesh_, f, 1) + corner(mesh_, f, 2)) / 3.0;
  }
  nodes_.reserve(2 * n / 4 + 2);
  build(0, n, centres);
}

int SurfaceDistance::build(int first, int count, std::vector<Vec3>& centres) {
  Node node;
  node.lo = Vec3::Constant(std::numeric_limits<double>::infinity());
  node.hi = -node.lo;
  for (int i = first; i < first + count; ++i)
    for (int k = 0; k < 3; ++k) {
      node.lo = node.lo.cwiseMin(corner(mesh_, tris_[i], k));
      node.hi = node.hi.cwiseMax(corner(mesh_, tris_[i], k));
    }
  const int index = static_cast<int>(nodes_.size());
  nodes_.push_back(node);
  if (count <= 4) {
    nodes_[index].first = first;
    nodes_[index].count = count;
    return index;
  }
  // Median split of the triangle centres along the longest side of the node's box.
  int axis = 0;
  (node.hi - node.lo).maxCoeff(&axis);
  const int mid = first + count / 2;
  std::nth_element(tris_.begin() + first, tris_.begin() + mid, tris_.begin() + first + count,
                   [&](int a, int b) { return centres[a](axis) < centres[b](axis); });
  const int left = build(first, mid - first, centres);
  const int right = build(mid, first + count - mid, centres);
  nodes_[index].left = left;
  nodes_[index].right = right;
  return index;
}

double SurfaceDistance::distance(const Vec3& p) const {
  double best2 = std::numeric_limits<double>::infinity();
  // Depth-first, nearer child first, pruning boxes farther than the best triangle so far.
  int stack[128];
  int top = 0;
  stack[top++] = 0;
  while (top > 0) {
    const Node& node = nodes_[stack[--top]];
    if (box_distance2(p, node.lo, node.hi) >= best2) continue;
    if (node.left < 0) {
      for (int i = node.first; i < node.first + node.count; ++i) {
        const int f = tris_[i];
        const Vec3 q = closest_point_on_triangle(p, corner(mesh_, f, 0), corner(mesh_, f, 1), corner(mesh_, f, 2));
        best2 = std::min(best2, (q - p).squaredNorm());
      }
      continue;
    }
    const double dl = box_distance2(p, nodes_[node.left].lo, nodes_[node.left].hi);
    const double dr = box_distance2(p, nodes_[node.right].lo, nodes_[node.right].hi);
    // Push the farther child first so the nearer one is popped next.
    if (dl < dr) {
      stack[top++] = node.right;
      stack[top++] = node.left;
    } else {
      stack[top++] = node.left;
      stack[top++] = node.right;
    }
  }
  return std::sqrt(best2);
}

std::vector<double> SurfaceDistance::distances(const Points& points) const {
  std::vector<double> d(points.rows());
  for (Eigen::Index i = 0; i < points.rows(); ++i) d[i] = distance(points.row(i).transpose());
  return d;
}

}  // namespace simu::physics
