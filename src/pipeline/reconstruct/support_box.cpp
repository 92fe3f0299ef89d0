#include "pipeline/reconstruct/support_box.h"

#include "common/error.h"
#include "pipeline/physics/geometry.h"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

namespace simu::reconstruct {

namespace {
using V2 = Eigen::Vector2d;

// The q-quantile of v (sorted copy, nearest rank).
double quantile(std::vector<double> v, double q) {
  std::sort(v.begin(), v.end());
  const size_t i = size_t(std::clamp(std::llround(q * double(v.size() - 1)), 0LL, (long long)(v.size() - 1)));
  return v[i];
}
}  // namespace

double min_area_rectangle_angle(const std::vector<V2>& pts) {
  // The physics library's rotating calipers (the OBB's), on the points in the z = 0 plane.
  Points P(Eigen::Index(pts.size()), 3);
  for (size_t i = 0; i < pts.size(); ++i) P.row(Eigen::Index(i)) << pts[i].x(), pts[i].y(), 0.0;
  Mat3 F;
  if (!physics::caliper_frame(P, Vec3::UnitZ(), &F))
    return pts.size() >= 2 ? std::atan2((pts.back() - pts.front()).y(), (pts.back() - pts.front()).x()) : 0.0;
  return std::atan2(F(1, 0), F(0, 0));
}

SupportBoxResult fit_support_box(const TabletopInput& in, const TabletopConfig& tabletop, const SupportBoxConfig& config) {
  SupportBoxResult r;
  std::string why;
  const auto top = table_support_plane(in, tabletop, &why);
  if (!top) {
    r.message = why;
    return r;
  }
  r.top = *top;
  const Vec3 n = top->normal.normalized();
  const Vec3 e1 = n.unitOrthogonal(), e2 = n.cross(e1);
  const double h_top = n.dot(top->point);
  // Footprint: the mask's valid points at or below the top band, in plane coordinates.
  const PointMap& map = *in.points;
  std::vector<V2> uv;
  double h_low = h_top;
  for (int row = 0; row < map.height; ++row)
    for (int c = 0; c < map.width; ++c) {
      const Vec3& p = map.at(row, c);
      if (!in.mask.at(row, c) || !PointMap::valid(p)) continue;
      const double h = n.dot(p);
      if (h > h_top + tabletop.band) continue;  // clutter above the top
      uv.emplace_back(e1.dot(p), e2.dot(p));
      h_low = std::min(h_low, h);
    }
  r.points = int64_t(uv.size());
  if (uv.size() < 3) {
    r.message = fmt::format("footprint: {} mask points at or below the top plane", uv.size());
    return r;
  }
  const double ang = min_area_rectangle_angle(uv);
  const V2 a(std::cos(ang), std::sin(ang)), b(-a.y(), a.x());
  std::vector<double> pa(uv.size()), pb(uv.size());
  for (size_t i = 0; i < uv.size(); ++i) pa[i] = a.dot(uv[i]), pb[i] = b.dot(uv[i]);
  const double q = config.footprint_trim;
  const double a0 = quantile(pa, q), a1 = quantile(pa, 1 - q), b0 = quantile(pb, q), b1 = quantile(pb, 1 - q);
  // Height: down to the floor (along the box's up) when fitted, else to the lowest mask point.
  const Vec3 top_centre_plane = (0.5 * (a0 + a1) * a.x() + 0.5 * (b0 + b1) * b.x()) * e1 +
                                (0.5 * (a0 + a1) * a.y() + 0.5 * (b0 + b1) * b.y()) * e2 + h_top * n;
  double height = h_top - h_low;
  if (in.floor) {
    const double along = in.floor->normal.dot(n);
    if (std::abs(along) > 1e-6) height = std::abs(in.floor->distance(top_centre_plane) / along);
  }
  height = std::max(height, config.min_height);
  r.extents = Vec3(a1 - a0, b1 - b0, height);
  if (r.extents.x() <= 0 || r.extents.y() <= 0) {
    r.message = fmt::format("footprint: degenerate rectangle {:.3f} x {:.3f} m", r.extents.x(), r.extents.y());
    return r;
  }
  r.yaw_deg = ang * 180 / 3.14159265358979323846;
  // Axes: side a, side b, up (a right-handed frame: (a x b) = n).
  const Vec3 A = a.x() * e1 + a.y() * e2, B = b.x() * e1 + b.y() * e2;
  r.R.col(0) = A;
  r.R.col(1) = B;
  r.R.col(2) = n;
  r.t = top_centre_plane - 0.5 * height * n;
  r.scale = r.extents;
  r.canonical.resize(8, 3);
  for (int i = 0; i < 8; ++i) r.canonical.row(i) << (i & 1 ? 0.5 : -0.5), (i & 2 ? 0.5 : -0.5), (i & 4 ? 0.5 : -0.5);
  r.faces.resize(12, 3);
  r.faces << 0, 1, 3, 0, 3, 2, 4, 6, 7, 4, 7, 5, 0, 4, 5, 0, 5, 1, 2, 3, 7, 2, 7, 6, 0, 2, 6, 0, 6, 4, 1, 5, 7, 1, 7, 3;
  r.ok = true;
  return r;
}

}  // namespace simu::reconstruct
