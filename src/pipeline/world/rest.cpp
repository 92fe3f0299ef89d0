// Stable rest facets of a convex hull.
#include "pipeline/world/rest.h"

#include "common/error.h"
#include "pipeline/physics/collision.h"

#include <Eigen/Geometry>

#include <algorithm>
#include <array>
#include <cmath>
#include <map>

namespace simu::world {

namespace {

// Solid angle of triangle (a, b, c) seen from the origin (Van Oosterom & Strackee 1983).
double solid_angle(const Vec3& a, const Vec3& b, const Vec3& c) {
  const double la = a.norm(), lb = b.norm(), lc = c.norm();
  const double num = std::abs(a.dot(b.cross(c)));
  const double den = la * lb * lc + a.dot(b) * lc + a.dot(c) * lb + b.dot(c) * la;
  return 2.0 * std::atan2(num, den);
}

// Distance from p to the segment [a, b].
double segment_distance(const Vec3& p, const Vec3& a, const Vec3& b) {
  const Vec3 d = b - a;
  const double t = std::clamp(d.squaredNorm() > 0 ? (p - a).dot(d) / d.squaredNorm() : 0.0, 0.0, 1.0);
  return (a + t * d - p).norm();
}

// Whether p (in the triangle's plane) lies in the closed triangle.
bool in_triangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c, const Vec3& n) {
  const double eps = -1e-12;
  return n.dot((b - a).cross(p - a)) >= eps && n.dot((c - b).cross(p - b)) >= eps && n.dot((a - c).cross(p - c)) >= eps;
}

}  // namespace

Mat3 put_down(const Vec3& n) { return Eigen::Quaterniond::FromTwoVectors(n.normalized(), Vec3::UnitY()).toRotationMatrix(); }

RestAnalysis analyse_rest(const Mesh& canonical, bool closed, double min_margin, double tip_ratio) {
  const Mesh hull = physics::convex_hull(canonical.V);
  RestAnalysis out;
  const physics::MassProps solid = physics::mass_properties({canonical}, 1.0);
  out.com = closed && solid.volume > 0 ? solid.com : physics::mass_properties({hull}, 1.0).com;
  // Join coplanar hull triangles (one facet per plane of a convex polytope): key by rounded normal and offset.
  std::map<std::array<long long, 4>, std::vector<Eigen::Index>> groups;
  std::vector<Vec3> normals(hull.F.rows());
  for (Eigen::Index f = 0; f < hull.F.rows(); ++f) {
    const Vec3 a = hull.V.row(hull.F(f, 0)), b = hull.V.row(hull.F(f, 1)), c = hull.V.row(hull.F(f, 2));
    const Vec3 n = (b - a).cross(c - a);
    if (!(n.norm() > 0)) continue;
    normals[f] = n.normalized();
    const double d = normals[f].dot(a);
    auto q = [](double x) { return (long long)std::llround(x * 1e7); };
    groups[{q(normals[f].x()), q(normals[f].y()), q(normals[f].z()), q(d)}].push_back(f);
  }
  double best_dot = std::cos(25.0 * 3.14159265358979323846 / 180.0);
  for (const auto& [key, tris] : groups) {
    RestFace face;
    Vec3 n = Vec3::Zero();
    for (auto f : tris) n += normals[f];
    face.normal = n.normalized();
    const Vec3 a0 = hull.V.row(hull.F(tris[0], 0));
    face.com_height = face.normal.dot(a0 - out.com);
    const Vec3 p = out.com + face.com_height * face.normal;  // the centre of mass projected onto the plane
    bool inside = false;
    std::map<std::pair<int, int>, int> edges;  // undirected edge -> uses within the facet
    for (auto f : tris) {
      const Vec3 a = hull.V.row(hull.F(f, 0)), b = hull.V.row(hull.F(f, 1)), c = hull.V.row(hull.F(f, 2));
      inside |= in_triangle(p, a, b, c, normals[f]);
      face.solid_angle += solid_angle(a - out.com, b - out.com, c - out.com);
      for (int k = 0; k < 3; ++k) {
        const int u = hull.F(f, k), v = hull.F(f, (k + 1) % 3);
        ++edges[{std::min(u, v), std::max(u, v)}];
      }
    }
    // Margin: distance to the facet's boundary (edges used once within it), negative outside.
    double margin = 1e300;
    for (const auto& [e, uses] : edges)
      if (uses == 1) margin = std::min(margin, segment_distance(p, hull.V.row(e.first).transpose(), hull.V.row(e.second).transpose()));
    face.margin = inside ? margin : -margin;
    face.stable = face.margin >= std::max(min_margin, tip_ratio * face.com_height);
    out.faces.push_back(face);
    if (face.stable && face.normal.y() > best_dot) best_dot = face.normal.y(), out.stand = int(out.faces.size()) - 1;
  }
  return out;
}

int pick_face(const RestAnalysis& a, double u, int exclude) {
  double total = 0;
  for (size_t i = 0; i < a.faces.size(); ++i)
    if (a.faces[i].stable && int(i) != exclude) total += a.faces[i].solid_angle;
  if (!(total > 0)) return -1;
  double x = u * total;
  int last = -1;
  for (size_t i = 0; i < a.faces.size(); ++i) {
    if (!a.faces[i].stable || int(i) == exclude) continue;
    last = int(i);
    if (x < a.faces[i].solid_angle) return int(i);
    x -= a.faces[i].solid_angle;
  }
  return last;
}

}  // namespace simu::world
