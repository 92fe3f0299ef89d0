// Helpers of the reconstruct tests: primitive meshes and camera renders built from first principles.
#pragma once

#include "pipeline/reconstruct/types.h"
#include "pipeline/reconstruct/zbuffer.h"

#include <cmath>
#include <random>

namespace simu::reconstruct::testing {

// Axis-aligned box centred at the origin with the given full extents (8 vertices, 12 triangles).
inline void box_mesh(const Vec3& e, Points& V, Faces& F) {
  V.resize(8, 3);
  for (int i = 0; i < 8; ++i)
    V.row(i) << (i & 1 ? 0.5 : -0.5) * e.x(), (i & 2 ? 0.5 : -0.5) * e.y(), (i & 4 ? 0.5 : -0.5) * e.z();
  F.resize(12, 3);
  F << 0, 1, 3, 0, 3, 2, 4, 6, 7, 4, 7, 5, 0, 4, 5, 0, 5, 1, 2, 3, 7, 2, 7, 6, 0, 2, 6, 0, 6, 4, 1, 5, 7, 1, 7, 3;
}

// A camera of w x h pixels with focal f and the principal point at the centre.
inline Pinhole camera(int w = 320, int h = 240, double f = 300) { return Pinhole{f, f, (w - 1) / 2.0, (h - 1) / 2.0, w, h}; }

// The point map of a depth render (NaN where nothing is drawn).
inline PointMap unproject(const std::vector<float>& depth, const Pinhole& K) {
  PointMap m;
  m.width = K.width;
  m.height = K.height;
  m.p.assign(depth.size(), Vec3::Constant(std::nan("")));
  for (int r = 0; r < K.height; ++r)
    for (int c = 0; c < K.width; ++c) {
      const double z = depth[size_t(r) * K.width + c];
      if (std::isfinite(z)) m.p[size_t(r) * K.width + c] = Vec3((c - K.cx) / K.fx * z, (r - K.cy) / K.fy * z, z);
    }
  return m;
}

// Rotation about a unit axis by degrees.
inline Mat3 rot(const Vec3& axis, double deg) {
  return Eigen::AngleAxisd(deg * 3.14159265358979323846 / 180, axis.normalized()).toRotationMatrix();
}

}  // namespace simu::reconstruct::testing
