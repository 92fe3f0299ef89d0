// Closed mesh parts of the shape families and their placement.
#include "pipeline/world/parts.h"

#include "common/error.h"
#include "pipeline/physics/mesh.h"

#include <Eigen/Geometry>

#include <cmath>

namespace simu::world {

namespace {
constexpr double kTwoPi = 6.283185307179586476925;
}  // namespace

Mat3 rotation(double angle, const Vec3& axis) { return Eigen::AngleAxisd(angle, axis.normalized()).toRotationMatrix(); }

Mesh transformed(Mesh m, const Mat3& R, const Vec3& t) {
  m.V = (m.V * R.transpose()).rowwise() + t.transpose();
  return m;
}

Mesh scaled(Mesh m, const Vec3& s) {
  m.V = m.V * s.asDiagonal();
  return m;
}

Mesh merge(const std::vector<Mesh>& parts) {
  Eigen::Index nv = 0, nf = 0;
  for (const auto& p : parts) nv += p.V.rows(), nf += p.F.rows();
  Mesh m;
  m.V.resize(nv, 3);
  m.F.resize(nf, 3);
  Eigen::Index v = 0, f = 0;
  for (const auto& p : parts) {
    m.V.middleRows(v, p.V.rows()) = p.V;
    m.F.middleRows(f, p.F.rows()) = p.F.array() + int(v);
    v += p.V.rows(), f += p.F.rows();
  }
  return m;
}

Mesh outward(Mesh m) {
  if (physics::signed_volume(m) < 0) m.F.col(1).swap(m.F.col(2));
  return m;
}

Mesh box_part(const Vec3& e, const Vec3& c) { return transformed(physics::box_mesh(0.5 * e), Mat3::Identity(), c); }

Mesh revolve_part(const std::vector<std::pair<double, double>>& prof, int S) {
  return outward(physics::revolve_mesh(prof, S));
}

Mesh vessel_part(const std::vector<std::pair<double, double>>& outer, double wall, double floor, int S) {
  SIMU_CHECK(outer.size() >= 2 && wall > 0 && floor > 0, "vessel_part: need >= 2 outer points, wall and floor > 0");
  // One profile: inner pole -> inside (bottom to rim) -> outside (rim to bottom) -> outer pole.
  std::vector<std::pair<double, double>> prof;
  const size_t n = outer.size();
  prof.emplace_back(outer.front().first - floor, 0.0);
  for (size_t k = 0; k < n; ++k) {
    // The inside: radius less the wall, floor raised by `floor` at the bottom fading to 0 at the rim.
    const double a = double(k) / double(n - 1);
    const double r = outer[k].second - wall;
    SIMU_CHECK(r > 0, "vessel_part: wall {} thicker than the radius {}", wall, outer[k].second);
    prof.emplace_back(outer[k].first - floor * (1 - a), r);
  }
  for (size_t k = n; k-- > 0;) prof.emplace_back(outer[k]);
  prof.emplace_back(outer.front().first, 0.0);
  return outward(physics::revolve_mesh(prof, S));
}

Mesh torus_part(double R, double r, double a0, double a1, int nu, int nv) {
  SIMU_CHECK(R > r && r > 0 && nu >= 3 && nv >= 3 && a1 > a0, "torus_part: need R > r > 0, a1 > a0, >= 3 segments");
  const bool full = a1 - a0 >= kTwoPi - 1e-12;
  const int rings = full ? nu : nu + 1;  // centre-line samples
  Mesh m;
  m.V.resize(rings * nv + (full ? 0 : 2), 3);
  for (int i = 0; i < rings; ++i) {
    const double phi = a0 + (a1 - a0) * i / nu;
    for (int j = 0; j < nv; ++j) {
      const double th = kTwoPi * j / nv, rr = R + r * std::cos(th);
      m.V.row(i * nv + j) << rr * std::cos(phi), r * std::sin(th), rr * std::sin(phi);
    }
  }
  std::vector<Eigen::Vector3i> F;
  auto id = [&](int i, int j) { return (i % rings) * nv + (j % nv); };
  for (int i = 0; i < (full ? nu : nu); ++i)
    for (int j = 0; j < nv; ++j) {
      F.emplace_back(id(i, j), id(i, j + 1), id(i + 1, j + 1));
      F.emplace_back(id(i, j), id(i + 1, j + 1), id(i + 1, j));
    }
  if (!full) {
    // Flat caps: fans around the centre-line points of both ends.
    const int c0 = rings * nv, c1 = c0 + 1;
    m.V.row(c0) << R * std::cos(a0), 0, R * std::sin(a0);
    m.V.row(c1) << R * std::cos(a1), 0, R * std::sin(a1);
    for (int j = 0; j < nv; ++j) {
      F.emplace_back(c0, id(0, j + 1), id(0, j));
      F.emplace_back(c1, id(rings - 1, j), id(rings - 1, j + 1));
    }
  }
  m.F.resize(Eigen::Index(F.size()), 3);
  for (size_t k = 0; k < F.size(); ++k) m.F.row(Eigen::Index(k)) = F[k].transpose();
  return outward(m);
}

Mesh rod_part(const Vec3& a, const Vec3& b, double r, int S) {
  const double len = (b - a).norm();
  SIMU_CHECK(len > 0 && r > 0, "rod_part: zero length or radius");
  const Mesh c = revolve_part({{-0.5 * len, r}, {0.5 * len, r}}, S);
  // Canonical y -> the rod's direction.
  const Mat3 R = Eigen::Quaterniond::FromTwoVectors(Vec3::UnitY(), (b - a) / len).toRotationMatrix();
  return transformed(c, R, 0.5 * (a + b));
}

}  // namespace simu::world
