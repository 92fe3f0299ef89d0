#include "pipeline/reconstruct/zbuffer.h"

#include "common/error.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace simu::reconstruct {

std::vector<float> render_depth(const Points& V, const Faces& F, const Pinhole& K, double near,
                                std::vector<int32_t>* face_id) {
  SIMU_CHECK(K.valid(), "render_depth: invalid intrinsics ({}x{}, fx {}, fy {})", K.width, K.height, K.fx, K.fy);
  std::vector<float> depth(size_t(K.width) * size_t(K.height), std::numeric_limits<float>::infinity());
  if (face_id) face_id->assign(depth.size(), -1);
  for (Eigen::Index f = 0; f < F.rows(); ++f) {
    Vec3 p[3];
    double u[3], v[3], iz[3];
    bool ok = true;
    for (int k = 0; k < 3; ++k) {
      p[k] = V.row(F(f, k)).transpose();
      if (!(p[k].z() > near)) { ok = false; break; }
      iz[k] = 1.0 / p[k].z();
      u[k] = K.fx * p[k].x() * iz[k] + K.cx;
      v[k] = K.fy * p[k].y() * iz[k] + K.cy;
    }
    if (!ok) continue;
    const double area = (u[1] - u[0]) * (v[2] - v[0]) - (u[2] - u[0]) * (v[1] - v[0]);
    if (std::abs(area) < 1e-12) continue;
    const int c0 = std::max(0, int(std::ceil(std::min({u[0], u[1], u[2]}))));
    const int c1 = std::min(K.width - 1, int(std::floor(std::max({u[0], u[1], u[2]}))));
    const int r0 = std::max(0, int(std::ceil(std::min({v[0], v[1], v[2]}))));
    const int r1 = std::min(K.height - 1, int(std::floor(std::max({v[0], v[1], v[2]}))));
    for (int r = r0; r <= r1; ++r)
      for (int c = c0; c <= c1; ++c) {
        // Barycentric weights of the pixel centre (c, r); inside or on an edge.
        const double w0 = ((u[1] - c) * (v[2] - r) - (u[2] - c) * (v[1] - r)) / area;
        const double w1 = ((u[2] - c) * (v[0] - r) - (u[0] - c) * (v[2] - r)) / area;
        const double w2 = 1.0 - w0 - w1;
        if (w0 < -1e-9 || w1 < -1e-9 || w2 < -1e-9) continue;
        const double z = 1.0 / (w0 * iz[0] + w1 * iz[1] + w2 * iz[2]);
        float& d = depth[size_t(r) * K.width + c];
        if (z < d) {
          d = float(z);
          if (face_id) (*face_id)[size_t(r) * K.width + c] = int32_t(f);
        }
      }
  }
  return depth;
}

std::vector<int64_t> visible_vertices(const Points& V, const Faces& F, const Pinhole& K, double tol) {
  std::vector<int32_t> fid;
  const std::vector<float> depth = render_depth(V, F, K, 1e-3, &fid);
  std::vector<uint8_t> vis(size_t(V.rows()), 0);
  for (int32_t f : fid)
    if (f >= 0)
      for (int k = 0; k < 3; ++k) vis[size_t(F(f, k))] = 1;
  for (Eigen::Index i = 0; i < V.rows(); ++i) {
    const double z = V(i, 2);
    if (vis[size_t(i)] || !(z > 0)) continue;
    const int c = int(std::lround(K.fx * V(i, 0) / z + K.cx)), r = int(std::lround(K.fy * V(i, 1) / z + K.cy));
    if (c < 0 || r < 0 || c >= K.width || r >= K.height) continue;
    if (z <= double(depth[size_t(r) * K.width + c]) + tol) vis[size_t(i)] = 1;
  }
  std::vector<int64_t> out;
  for (Eigen::Index i = 0; i < V.rows(); ++i)
    if (vis[size_t(i)]) out.push_back(i);
  return out;
}

Mask silhouette(const std::vector<float>& depth, const Pinhole& K) {
  Mask m(K.width, K.height);
  for (size_t i = 0; i < depth.size() && i < m.data.size(); ++i) m.data[i] = std::isfinite(depth[i]) ? 1 : 0;
  return m;
}

}  // namespace simu::reconstruct
