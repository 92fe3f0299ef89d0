// The procedural families: random proportions per instance, built from closed parts (parts.h).
// Units are arbitrary (make_shape normalises); y is down, so the top of a standing object is at -y.
#include "pipeline/world/families.h"

#include "common/error.h"
#include "pipeline/physics/mesh.h"

#include <cmath>
#include <fmt/ranges.h>

namespace simu::world {

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr int kSeg = 32;  // segments around a surface of revolution

// Box: three independent side ratios.
// (Draws are separate statements throughout: the order of a call's argument evaluation is unspecified.)
Mesh build_box(Rng& r) {
  const double b = r.uniform(0.15, 1.0), c = r.uniform(0.15, 1.0);
  return box_part(Vec3(1.0, b, c));
}

// Cylinder: radius 1, height 0.2 (disc) to 4 (rod).
Mesh build_cylinder(Rng& r) {
  const double h = r.log_uniform(0.2, 4.0);
  return revolve_part({{-0.5 * h, 1.0}, {0.5 * h, 1.0}}, kSeg);
}

// Sphere: a mildly squashed ellipsoid (axis ratios 0.8..1).
Mesh build_sphere(Rng& r) {
  const double ay = r.uniform(0.8, 1.0), az = r.uniform(0.8, 1.0);
  std::vector<std::pair<double, double>> prof;
  const int n = 16;
  for (int k = 0; k <= n; ++k) {
    const double phi = kPi * k / n;
    prof.emplace_back(-ay * std::cos(phi), k == 0 || k == n ? 0.0 : std::sin(phi));
  }
  return scaled(revolve_part(prof, kSeg), Vec3(1, 1, az));
}

// Cone: apex or frustum top (40%), height 0.5 to 3 base radii.
Mesh build_cone(Rng& r) {
  const double h = r.uniform(0.5, 3.0), top = r.chance(0.4) ? r.uniform(0.1, 0.5) : 0.0;
  return revolve_part({{-0.5 * h, top}, {0.5 * h, 1.0}}, kSeg);
}

// Capsule: radius 1, straight part 0.3 to 3.
Mesh build_capsule(Rng& r) {
  const double L = r.uniform(0.3, 3.0);
  std::vector<std::pair<double, double>> prof;
  const int n = 8;
  for (int k = 0; k <= n; ++k) {
    const double phi = 0.5 * kPi * k / n;
    prof.emplace_back(-0.5 * L - std::cos(phi), k == 0 ? 0.0 : std::sin(phi));
  }
  for (int k = 0; k <= n; ++k) {
    const double phi = 0.5 * kPi + 0.5 * kPi * k / n;
    prof.emplace_back(0.5 * L - std::cos(phi), k == n ? 0.0 : std::sin(phi));
  }
  return revolve_part(prof, kSeg);
}

// Torus lying flat: centre-line radius 1, tube 0.12 to 0.5, tube squashed vertically 0.6..1.
Mesh build_torus(Rng& r) {
  const double tube = r.uniform(0.12, 0.5);
  return scaled(torus_part(1.0, tube, 0, 2 * kPi, 40, 16), Vec3(1, r.uniform(0.6, 1.0), 1));
}

// Bowl: rim radius 1, depth 0.3..0.7, flat foot 0.3..0.55, wall 3..8%.
Mesh build_bowl(Rng& r) {
  const double h = r.uniform(0.3, 0.7), foot = r.uniform(0.3, 0.55), wall = r.uniform(0.03, 0.08);
  const double flare = r.uniform(0.6, 1.4);  // curvature of the side
  std::vector<std::pair<double, double>> outer;
  const int n = 10;
  for (int k = 0; k <= n; ++k) {
    const double s = double(k) / n;
    outer.emplace_back(0.5 * h - h * (1 - std::cos(0.5 * kPi * s)), foot + (1 - foot) * std::pow(std::sin(0.5 * kPi * s), flare));
  }
  return vessel_part(outer, wall, std::max(wall, 0.05 * h), kSeg);
}

// Bottle: body radius 1, height 2.5..5 radii, neck 0.2..0.45, rounded shoulder, lip at the top.
Mesh build_bottle(Rng& r) {
  const double h = r.uniform(2.5, 5.0), neck = r.uniform(0.2, 0.45), neck_len = r.uniform(0.3, 0.25 * h);
  const double shoulder = r.uniform(0.4, 1.2);
  const double top = -0.5 * h, y_neck = top + neck_len, y_body = y_neck + shoulder;
  std::vector<std::pair<double, double>> prof = {{top, neck * 1.15}, {top + 0.06, neck * 1.15}, {top + 0.08, neck}, {y_neck, neck}};
  const int n = 6;
  for (int k = 1; k <= n; ++k) {
    const double s = double(k) / n;
    prof.emplace_back(y_neck + shoulder * s, neck + (1 - neck) * std::sin(0.5 * kPi * s));
  }
  if (y_body < 0.5 * h - 0.1) prof.emplace_back(0.5 * h - 0.1, 1.0);
  prof.emplace_back(0.5 * h, 0.92);
  return revolve_part(prof, kSeg);
}

// A straight or tapered cup body: rim radius 1, bottom radius taper, height h.
Mesh cup_body(double h, double taper, double wall) {
  return vessel_part({{0.5 * h, taper}, {0.0, 0.5 * (1 + taper)}, {-0.5 * h, 1.0}}, wall, 2 * wall, kSeg);
}

// Mug (body + handle): height 0.8..1.5 diameters, a half-torus handle on +x entering the wall.
Mesh build_mug(Rng& r) {
  const double h = r.uniform(1.6, 3.0), wall = r.uniform(0.06, 0.1);
  const Mesh body = cup_body(h, r.uniform(0.85, 1.0), wall);
  const double Rh = r.uniform(0.22, 0.36) * h, rh = r.uniform(0.07, 0.13);
  // Handle arc in the xy plane: torus about y rotated to about z; its ends sit in the wall at x = 1 - wall / 2,
  // between the rim and the floor (the mug stands on its bottom).
  const double room = std::max(0.0, 0.5 * h - 2 * wall - Rh - rh);
  const Mesh arc = torus_part(Rh, rh, -0.5 * kPi, 0.5 * kPi, 20, 10);
  const Mesh handle = transformed(arc, rotation(-0.5 * kPi, Vec3::UnitX()), Vec3(1 - 0.5 * wall, r.uniform(-room, room), 0));
  return merge({body, handle});
}

// Cup / tumbler: height 0.6..3 diameters, tapered.
Mesh build_cup(Rng& r) {
  const double h = r.uniform(1.2, 6.0), taper = r.uniform(0.6, 1.0), wall = r.uniform(0.04, 0.1);
  return cup_body(h, taper, wall);
}

// Vase: a solid smooth profile (two random harmonics), height 2..5 radii.
Mesh build_vase(Rng& r) {
  const double h = r.uniform(2.0, 5.0), a1 = r.uniform(0.1, 0.35), a2 = r.uniform(-0.15, 0.15), p = r.uniform(0, 2 * kPi);
  const double mouth = r.uniform(0.45, 0.8);
  std::vector<std::pair<double, double>> prof;
  const int n = 14;
  for (int k = 0; k <= n; ++k) {
    const double s = double(k) / n;  // 0 top, 1 bottom
    const double base = mouth + (0.7 - mouth) * s;
    prof.emplace_back(-0.5 * h + h * s, base + a1 * std::sin(kPi * s) + a2 * std::sin(2 * kPi * s + p) + 0.3 * std::sin(kPi * s));
  }
  return revolve_part(prof, kSeg);
}

// Wedge: a right-triangular prism (ramp), lying on its long face.
Mesh build_wedge(Rng& r) {
  const double a = 1.0, b = r.uniform(0.2, 0.8), w = r.uniform(0.3, 1.0);
  // Triangle in the x-(-y) plane: (0,0), (a,0), (0,-b): the slope faces up.
  Mesh m = physics::prism_mesh({{0, 0}, {a, 0}, {0, -b}}, 0.5 * w);
  return outward(m);
}

// L-bracket: an L profile (legs 1 and 0.4..1, thickness 0.08..0.25) extruded 0.2..1.
Mesh build_l_bracket(Rng& r) {
  const double a = 1.0, b = r.uniform(0.4, 1.0), t = r.uniform(0.08, 0.25), w = r.uniform(0.2, 1.0);
  // Base leg along +x on the bottom (y = 0), the upright leg up (-y) at x = 0.
  Mesh m = physics::prism_mesh({{0, 0}, {a, 0}, {a, -t}, {t, -t}, {t, -b}, {0, -b}}, 0.5 * w);
  return outward(m);
}

// Book stack: 1..5 books (width 1, depth 0.6..0.8, thickness 0.06..0.2), each slightly turned and shifted.
Mesh build_book_stack(Rng& r) {
  const int n = 1 + r.below(5);
  std::vector<Mesh> books;
  double y = 0;
  for (int i = 0; i < n; ++i) {
    const double ex = r.uniform(0.8, 1.0), ey = r.uniform(0.06, 0.2), ez = r.uniform(0.55, 0.8);
    const double yaw = r.uniform(-0.25, 0.25), dx = r.uniform(-0.06, 0.06), dz = r.uniform(-0.06, 0.06);
    const Vec3 e(ex, ey, ez);
    books.push_back(transformed(box_part(e), rotation(yaw, Vec3::UnitY()), Vec3(dx, y - 0.5 * e.y(), dz)));
    y -= e.y();
  }
  return merge(books);
}

// Legs under a top: 3 or 4 rods from the corners / rim of the top's underside to the floor, splayed out.
std::vector<Mesh> legs(int n, double spread_x, double spread_z, double y_top, double y_floor, double leg_r,
                       double splay, bool round) {
  std::vector<Mesh> out;
  for (int i = 0; i < n; ++i) {
    Vec3 dir;
    if (round) {
      const double a = 2 * kPi * i / n + 0.25 * kPi;
      dir = Vec3(std::cos(a), 0, std::sin(a));
    } else {
      dir = Vec3((i & 1) ? 1 : -1, 0, (i & 2) ? 1 : -1);
    }
    const Vec3 top(dir.x() * spread_x, y_top, dir.z() * spread_z);
    const Vec3 bottom = top + Vec3(dir.x() * splay, y_floor - y_top, dir.z() * splay);
    out.push_back(round ? rod_part(top, bottom, leg_r, 12) : box_part(Vec3(2 * leg_r, y_floor - y_top, 2 * leg_r), 0.5 * (top + bottom)));
  }
  return out;
}

// Stool: round seat (radius 1, thickness 0.08..0.16), 3 or 4 splayed round legs, height 1.2..2.6.
Mesh build_stool(Rng& r) {
  const double h = r.uniform(1.2, 2.6), t = r.uniform(0.08, 0.16), leg = r.uniform(0.05, 0.09);
  const int n = r.chance(0.5) ? 3 : 4;
  std::vector<Mesh> parts = {revolve_part({{-0.5 * h, 1.0}, {-0.5 * h + t, 1.0}}, kSeg)};
  const double spread = r.uniform(0.55, 0.75);
  for (auto& l : legs(n, spread, spread, -0.5 * h + 0.5 * t, 0.5 * h, leg, r.uniform(0.0, 0.2), true)) parts.push_back(l);
  return merge(parts);
}

// Table: rectangular top (1 x 0.5..1, thickness 0.03..0.08), four square legs, height 0.5..1.1.
Mesh build_table(Rng& r) {
  const double d = r.uniform(0.5, 1.0), h = r.uniform(0.5, 1.1), t = r.uniform(0.03, 0.08), leg = r.uniform(0.025, 0.05);
  std::vector<Mesh> parts = {box_part(Vec3(1.0, t, d), Vec3(0, -0.5 * h + 0.5 * t, 0))};
  const double inset = r.uniform(0.02, 0.08);
  for (auto& l : legs(4, 0.5 - inset - leg, 0.5 * d - inset - leg, -0.5 * h + 0.5 * t, 0.5 * h, leg, 0.0, false))
    parts.push_back(l);
  return merge(parts);
}

// Chair: square seat, four legs, a backrest on the -z side (slats or a board), seat at 0.45..0.6 of the height.
Mesh build_chair(Rng& r) {
  const double w = 1.0, d = r.uniform(0.85, 1.1), H = r.uniform(1.6, 2.2), seat_h = r.uniform(0.45, 0.6) * H;
  const double t = r.uniform(0.06, 0.1), leg = r.uniform(0.035, 0.06);
  const double y_floor = 0.5 * H, y_seat = y_floor - seat_h;
  std::vector<Mesh> parts = {box_part(Vec3(w, t, d), Vec3(0, y_seat - 0.5 * t, 0))};
  for (auto& l : legs(4, 0.5 * w - leg, 0.5 * d - leg, y_seat - 0.5 * t, y_floor, leg, 0.0, false)) parts.push_back(l);
  // Back posts from the seat to the top, and a back board.
  const double y_top = -0.5 * H, bz = -0.5 * d + leg;
  for (const double x : {-0.5 * w + leg, 0.5 * w - leg})
    parts.push_back(box_part(Vec3(2 * leg, y_seat - t - y_top, 2 * leg), Vec3(x, 0.5 * (y_seat - t + y_top), bz)));
  const double board = r.uniform(0.15, 0.45) * (y_seat - y_top);
  parts.push_back(box_part(Vec3(w - 4 * leg, board, 1.5 * leg), Vec3(0, y_top + 0.5 * board + 0.02, bz)));
  return merge(parts);
}

std::vector<FamilySpec> make_specs() {
  return {
      {"box", 0.02, 0.40, true, build_box},
      {"cylinder", 0.03, 0.35, false, build_cylinder},
      {"sphere", 0.02, 0.30, false, build_sphere},
      {"cone", 0.04, 0.35, false, build_cone},
      {"capsule", 0.04, 0.30, false, build_capsule},
      {"torus", 0.05, 0.30, false, build_torus},
      {"bowl", 0.08, 0.35, false, build_bowl},
      {"bottle", 0.10, 0.40, false, build_bottle},
      {"mug", 0.07, 0.16, false, build_mug},
      {"cup", 0.06, 0.18, false, build_cup},
      {"vase", 0.10, 0.50, false, build_vase},
      {"wedge", 0.04, 0.35, false, build_wedge},
      {"l_bracket", 0.03, 0.30, false, build_l_bracket},
      {"book_stack", 0.12, 0.35, true, build_book_stack},
      {"stool", 0.25, 0.60, false, build_stool},
      {"table", 0.25, 0.60, false, build_table},
      {"chair", 0.30, 0.60, true, build_chair},
  };
}

}  // namespace

const std::vector<FamilySpec>& family_specs() {
  static const std::vector<FamilySpec> specs = make_specs();
  return specs;
}

const FamilySpec& family_spec(const std::string& name) {
  for (const auto& s : family_specs())
    if (s.name == name) return s;
  std::vector<std::string> names;
  for (const auto& s : family_specs()) names.push_back(s.name);
  throw Error(fmt::format("shape world: unknown family '{}' (families: {})", name, fmt::join(names, ", ")));
}

}  // namespace simu::world
