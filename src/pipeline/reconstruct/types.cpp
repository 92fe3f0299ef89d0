#include "pipeline/reconstruct/types.h"

#include "common/error.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <utility>

namespace simu::reconstruct {

int64_t Mask::count() const {
  int64_t n = 0;
  for (uint8_t v : data) n += v != 0;
  return n;
}

Points masked_points(const PointMap& map, const Mask& mask, const std::string& what) {
  SIMU_CHECK(mask.width == map.width && mask.height == map.height,
             "{}: mask is {}x{}, the point map {}x{} (width x height)", what, mask.width, mask.height, map.width,
             map.height);
  std::vector<Vec3> out;
  for (int r = 0; r < map.height; ++r)
    for (int c = 0; c < map.width; ++c)
      if (mask.at(r, c) && PointMap::valid(map.at(r, c))) out.push_back(map.at(r, c));
  Points P(Eigen::Index(out.size()), 3);
  for (size_t i = 0; i < out.size(); ++i) P.row(Eigen::Index(i)) = out[i].transpose();
  return P;
}

Points transform(const Points& P, const Similarity& T) {
  Points out(P.rows(), 3);
  const Mat3 A = T.s * T.R;
  for (Eigen::Index i = 0; i < P.rows(); ++i) out.row(i) = (A * P.row(i).transpose() + T.t).transpose();
  return out;
}

Points place(const Points& canonical, const Vec3& scale, const Mat3& R, const Vec3& t) {
  Points out(canonical.rows(), 3);
  for (Eigen::Index i = 0; i < canonical.rows(); ++i)
    out.row(i) = (R * scale.cwiseProduct(canonical.row(i).transpose()) + t).transpose();
  return out;
}

Points subsample(const Points& P, int64_t max_n) {
  if (max_n <= 0 || P.rows() <= max_n) return P;
  Points out(max_n, 3);
  const double step = double(P.rows()) / double(max_n);
  for (int64_t i = 0; i < max_n; ++i) out.row(i) = P.row(Eigen::Index(std::floor(i * step)));
  return out;
}

void densify(Points& V, Faces& F, double max_edge) {
  SIMU_CHECK(max_edge > 0, "densify: max_edge must be positive, got {}", max_edge);
  std::vector<Vec3> verts(size_t(V.rows()));
  for (Eigen::Index i = 0; i < V.rows(); ++i) verts[size_t(i)] = V.row(i).transpose();
  std::vector<std::array<int, 3>> tris(size_t(F.rows()));
  for (Eigen::Index i = 0; i < F.rows(); ++i) tris[size_t(i)] = {F(i, 0), F(i, 1), F(i, 2)};
  const double m2 = max_edge * max_edge;
  for (int pass = 0; pass < 12; ++pass) {
    // Split every long edge at its midpoint (one vertex per edge, shared by both triangles), then
    // re-triangulate each triangle by how many of its edges were split.
    std::map<std::pair<int, int>, int> mid;
    auto key = [](int a, int b) { return a < b ? std::make_pair(a, b) : std::make_pair(b, a); };
    for (auto& t : tris)
      for (int e = 0; e < 3; ++e) {
        int a = t[e], b = t[(e + 1) % 3];
        if ((verts[a] - verts[b]).squaredNorm() > m2 && !mid.count(key(a, b))) {
          mid[key(a, b)] = int(verts.size());
          verts.push_back(0.5 * (verts[a] + verts[b]));
        }
      }
    if (mid.empty()) break;
    std::vector<std::array<int, 3>> next;
    next.reserve(tris.size() * 4);
    for (auto& t : tris) {
      int m[3];
      int n = 0;
      for (int e = 0; e < 3; ++e) {
        auto it = mid.find(key(t[e], t[(e + 1) % 3]));
        m[e] = it == mid.end() ? -1 : it->second;
        n += m[e] >= 0;
      }
      if (n == 0) {
        next.push_back(t);
      } else if (n == 3) {
        next.push_back({t[0], m[0], m[2]});
        next.push_back({m[0], t[1], m[1]});
        next.push_back({m[2], m[1], t[2]});
        next.push_back({m[0], m[1], m[2]});
      } else {
        // Fan from each split midpoint: rotate so that edge 0 is split, then split the rest.
        int r = 0;
        while (m[r] < 0) ++r;
        int a = t[r], b = t[(r + 1) % 3], c = t[(r + 2) % 3];
        int mab = m[r], mbc = m[(r + 1) % 3], mca = m[(r + 2) % 3];
        if (n == 1) {
          next.push_back({a, mab, c});
          next.push_back({mab, b, c});
        } else if (mbc >= 0) {  // ab and bc split
          next.push_back({a, mab, c});
          next.push_back({mab, b, mbc});
          next.push_back({mab, mbc, c});
        } else {  // ab and ca split
          next.push_back({a, mab, mca});
          next.push_back({mab, b, c});
          next.push_back({mab, c, mca});
        }
      }
    }
    tris.swap(next);
  }
  V.resize(Eigen::Index(verts.size()), 3);
  for (size_t i = 0; i < verts.size(); ++i) V.row(Eigen::Index(i)) = verts[i].transpose();
  F.resize(Eigen::Index(tris.size()), 3);
  for (size_t i = 0; i < tris.size(); ++i) F.row(Eigen::Index(i)) << tris[i][0], tris[i][1], tris[i][2];
}

}  // namespace simu::reconstruct
