// Rest orientations, footprints and positions of objects in a world scene.
#include "pipeline/world/placement.h"

#include "pipeline/physics/camera.h"
#include "pipeline/physics/geometry.h"
#include "pipeline/world/families.h"
#include "pipeline/world/parts.h"

#include <algorithm>
#include <cmath>

namespace simu::world::detail {

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kGap = 0.01;          // m between footprints
constexpr double kWallGap = 0.0005;    // m between a leaning object and the wall
constexpr double kFloorExtent = 2.5;   // the floor region: |x| <= this, z in [-kFloorDepth, 0]
constexpr double kFloorDepth = 3.0;

// Fills the derived geometry of an orientation.
Oriented make_oriented(const ShapeInstance& inst, Rest rest, const Mat3& R) {
  Oriented o;
  o.rest = rest;
  o.R = R;
  o.offsets = transformed(inst.mesh, R * Mat3(inst.scale().asDiagonal()), Vec3::Zero());
  const auto& V = o.offsets.V;
  Eigen::Index low = 0;
  o.lowest = V.col(1).maxCoeff(&low);
  o.wall_reach = V.col(2).maxCoeff();
  o.contact_z = V(low, 2);
  const double x0 = V.col(0).minCoeff(), x1 = V.col(0).maxCoeff(), z0 = V.col(2).minCoeff(), z1 = V.col(2).maxCoeff();
  o.centre = Eigen::Vector2d(0.5 * (x0 + x1), 0.5 * (z0 + z1));
  double r2 = 0;
  for (Eigen::Index i = 0; i < V.rows(); ++i) r2 = std::max(r2, (Eigen::Vector2d(V(i, 0), V(i, 2)) - o.centre).squaredNorm());
  o.radius = std::sqrt(r2);
  return o;
}

// Whether a disc meets the rectangle [x0, x1] x [z0, z1].
bool disc_meets_rect(const Eigen::Vector2d& c, double r, double x0, double x1, double z0, double z1) {
  const double dx = std::max({x0 - c.x(), 0.0, c.x() - x1}), dz = std::max({z0 - c.y(), 0.0, c.y() - z1});
  return dx * dx + dz * dz < r * r;
}

}  // namespace

std::optional<Oriented> orient_as(const ShapeInstance& inst, const RestAnalysis& a, Rest rest, Rng& rng) {
  const double yaw = rng.uniform(-kPi, kPi);
  switch (rest) {
    case Rest::Stand:
      if (a.stand < 0) return std::nullopt;
      return make_oriented(inst, rest, rotation(yaw, Vec3::UnitY()) * put_down(a.faces[a.stand].normal));
    case Rest::Lie: {
      const int f = pick_face(a, rng.unit(), a.stand);
      if (f < 0) return std::nullopt;
      return make_oriented(inst, rest, rotation(yaw, Vec3::UnitY()) * put_down(a.faces[f].normal));
    }
    case Rest::Lean: {
      if (a.stand < 0) return std::nullopt;
      // Standing, turned by the quarter yaw whose side towards the wall gives the smallest tipping
      // angle (a straight bottom edge parallel to the wall), then tipped towards the wall (+z) about x
      // past that angle: the centre of mass passes the bottom edge nearest the wall, so gravity holds
      // it against the wall. Too squat (tipping angle > 35 deg): no lean.
      Mat3 best_up = Mat3::Identity();
      double tip = 1e300;
      for (int q = 0; q < 4; ++q) {
        const Mat3 up = rotation(0.5 * kPi * q, Vec3::UnitY()) * put_down(a.faces[a.stand].normal);
        const physics::Mesh standing = transformed(inst.mesh, up * Mat3(inst.scale().asDiagonal()), Vec3::Zero());
        const Vec3 com = up * inst.scale().cwiseProduct(a.com);
        const double bottom = standing.V.col(1).maxCoeff();
        double edge_z = -1e300;  // the bottom's edge nearest the wall
        for (Eigen::Index i = 0; i < standing.V.rows(); ++i)
          if (standing.V(i, 1) >= bottom - 1e-9 * inst.size_m) edge_z = std::max(edge_z, standing.V(i, 2));
        const double angle = std::atan2(edge_z - com.z(), bottom - com.y());
        if (angle < tip - 1e-9) tip = angle, best_up = up;
      }
      if (tip > 35.0 * kPi / 180) return std::nullopt;
      const double tilt = tip + rng.uniform(4.0, 12.0) * kPi / 180;
      return make_oriented(inst, rest, rotation(-tilt, Vec3::UnitX()) * best_up);
    }
  }
  return std::nullopt;
}

std::optional<Oriented> orient(const ShapeInstance& inst, const RestAnalysis& a, const SceneConfig& cfg, Rng& rng) {
  const bool lean_ok = inst.family != "external" && is_family(inst.family) && family_spec(inst.family).can_lean;
  const double w[3] = {a.stand >= 0 ? cfg.w_stand : 0.0, cfg.w_lie, lean_ok && a.stand >= 0 ? cfg.w_lean : 0.0};
  const double total = w[0] + w[1] + w[2];
  double u = rng.unit() * total;
  Rest order[3] = {Rest::Stand, Rest::Lie, Rest::Lean};
  int pick = 0;
  while (pick < 2 && u >= w[pick]) u -= w[pick], ++pick;
  // The chosen mode first, then the others as fallbacks (an instance with one kind of rest only).
  for (int k = 0; k < 3; ++k) {
    const Rest r = order[(pick + k) % 3];
    if (r == Rest::Lean && !lean_ok) continue;
    if (auto o = orient_as(inst, a, r, rng)) return o;
  }
  return std::nullopt;
}

Vec3 position_at(const Oriented& o, double x, double z, bool floor, const Table& table) {
  const double support_y = floor ? 0.0 : -table.height;
  return Vec3(x - o.centre.x(), support_y - o.lowest, z - o.centre.y());
}

bool footprint_ok(const Oriented& o, const Vec3& t, bool floor, const Table& table, const physics::Camera& cam,
                  const std::vector<Footprint>& taken, bool whole_in_view) {
  const Eigen::Vector2d c(t.x() + o.centre.x(), t.z() + o.centre.y());
  const double r = o.radius;
  // On the support (a leaning object's disc may reach the wall).
  const double back = o.rest == Rest::Lean ? r : 0.0;
  if (floor) {
    if (c.x() - r < -kFloorExtent || c.x() + r > kFloorExtent || c.y() - r < -kFloorDepth || c.y() + r > back) return false;
    if (disc_meets_rect(c, r + kGap, table.x0, table.x1, -table.depth, 0.0)) return false;
  } else {
    if (c.x() - r < table.x0 || c.x() + r > table.x1 || c.y() - r < -table.depth || c.y() + r > back) return false;
    if (o.rest == Rest::Lean && t.z() + o.contact_z < -table.depth + 0.01) return false;
  }
  // Beyond the wall (only leaning objects touch it).
  if (t.z() + o.wall_reach > 0) return false;
  for (const auto& f : taken)
    if (f.floor == floor && (f.centre - c).norm() < f.radius + r + kGap) return false;
  // Seen: the centre (whole_in_view: every corner of the world AABB) projects inside the image in
  // front of the camera, and for floor objects the line of sight to the centre misses the table.
  auto in_view = [&](const Vec3& p, double margin) {
    const physics::Projection q = physics::project(cam, p);
    return q.z > 0.1 && q.u >= margin * cam.width && q.u <= (1 - margin) * cam.width && q.v >= margin * cam.height &&
           q.v <= (1 - margin) * cam.height;
  };
  if (!in_view(t, 0.05)) return false;
  if (whole_in_view) {
    const Vec3 lo = t + o.offsets.V.colwise().minCoeff().transpose(), hi = t + o.offsets.V.colwise().maxCoeff().transpose();
    for (int k = 0; k < 8; ++k)
      if (!in_view(Vec3(k & 1 ? hi.x() : lo.x(), k & 2 ? hi.y() : lo.y(), k & 4 ? hi.z() : lo.z()), 0.02)) return false;
  }
  if (floor && !physics::segment_misses_box(physics::camera_center(cam), t, Vec3(table.x0, -table.height, -table.depth),
                                   Vec3(table.x1, 0, 0)))
    return false;
  return true;
}

std::optional<std::pair<Vec3, Footprint>> place_on_support(const Oriented& o, bool floor, const Table& table,
                                                           const physics::Camera& cam,
                                                           const std::vector<Footprint>& taken, Rng& rng,
                                                           int attempts) {
  const double support_y = floor ? 0.0 : -table.height;
  const Vec3 c = physics::camera_center(cam);
  for (int k = 0; k < attempts; ++k) {
    // A point of the support plane the camera sees: the ray through a random pixel (5% margin).
    const double u = rng.uniform(0.05, 0.95) * cam.width, v = rng.uniform(0.05, 0.95) * cam.height;
    const Vec3 dir = cam.R_world_cam * physics::pixel_ray_camera(cam, u, v);
    if (!(dir.y() > 1e-6)) continue;  // the ray never comes down to the support
    const Vec3 hit = c + (support_y - c.y()) / dir.y() * dir;
    const double x = hit.x(), z = hit.z();
    Vec3 t = position_at(o, x, z, floor, table);
    // Leaning objects touch the wall: z from the wall, x as drawn.
    if (o.rest == Rest::Lean) t.z() = -kWallGap - o.wall_reach;
    if (!footprint_ok(o, t, floor, table, cam, taken)) continue;
    Footprint f;
    f.floor = floor;
    f.centre = Eigen::Vector2d(t.x() + o.centre.x(), t.z() + o.centre.y());
    f.radius = o.radius;
    return std::make_pair(t, f);
  }
  return std::nullopt;
}

}  // namespace simu::world::detail
