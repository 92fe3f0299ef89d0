// Synthetic scene generator: layouts, primitive meshes, injected errors, rendered masks, writer.
#include "pipeline/physics/synthetic.h"

#include "common/error.h"
#include "common/fs.h"
#include "pipeline/physics/camera.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/metrics.h"
#include "pipeline/physics/overlay.h"
#include "pipeline/physics/probe.h"

#include <Eigen/Geometry>

#include <array>
#include <cmath>
#include <filesystem>
#include <fmt/format.h>
#include <limits>
#include <sstream>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#endif

namespace simu::physics {

namespace {

constexpr double kPi = 3.14159265358979323846;

Mat3 rot(double angle, const Vec3& axis) { return Eigen::AngleAxisd(angle, axis.normalized()).toRotationMatrix(); }

// Places a canonical mesh in the world: x = R (s .* v) + t.
Mesh place(const Mesh& m, const Vec3& s, const Mat3& R, const Vec3& t) {
  Mesh w = m;
  w.V = (m.V * (R * s.asDiagonal()).transpose()).rowwise() + t.transpose();
  return w;
}

Mesh lathe_raw(const std::vector<std::pair<double, double>>& prof, int S);

// A shape in metres before normalisation: a box (extents) or a lathe profile (y down, top first).
struct Shape {
  std::string kind;  // box | cylinder | bottle | bowl | frame | clock
  Vec3 extents = Vec3::Zero();
  std::vector<std::pair<double, double>> profile;
  double height() const { return kind == "box" || kind == "frame" ? extents.y() : profile.back().first - profile.front().first; }
  // The same shape with the bottom fraction c removed (top kept).
  Shape cut_bottom(double c) const {
    Shape s = *this;
    if (kind == "box" || kind == "frame") {
      s.extents.y() *= (1 - c);
      return s;
    }
    const double y_cut = profile.front().first + (1 - c) * height();
    s.profile.clear();
    for (size_t k = 0; k < profile.size(); ++k) {
      if (profile[k].first <= y_cut) s.profile.push_back(profile[k]);
      if (k + 1 < profile.size() && profile[k].first < y_cut && profile[k + 1].first > y_cut) {
        const double a = (y_cut - profile[k].first) / (profile[k + 1].first - profile[k].first);
        s.profile.emplace_back(y_cut, profile[k].second + a * (profile[k + 1].second - profile[k].second));
      }
    }
    return s;
  }
  // Real-size mesh (not normalised).
  Mesh mesh() const {
    if (kind == "box" || kind == "frame") {
      Obb b;
      b.extents = extents;
      return b.to_mesh();
    }
    return lathe_raw(profile, 24);
  }
};

// Random shape of a free object, heights 0.07-0.28 m.
Shape random_free_shape(std::mt19937_64& rng) {
  std::uniform_real_distribution<double> U(0, 1);
  auto R = [&](double a, double b) { return a + (b - a) * U(rng); };
  Shape s;
  const int k = int(U(rng) * 4);
  if (k == 0) {
    s.kind = "box";
    s.extents = Vec3(R(0.06, 0.22), R(0.07, 0.28), R(0.06, 0.2));
  } else if (k == 1) {
    s.kind = "cylinder";
    const double r = R(0.03, 0.08), h = R(0.08, 0.26);
    s.profile = {{0, r}, {h, r}};
  } else if (k == 2) {
    s.kind = "bottle";
    const double r = R(0.03, 0.055), h = R(0.16, 0.28), neck = R(0.012, 0.02);
    s.profile = {{0, neck}, {0.22 * h, neck}, {0.4 * h, r}, {h, r}};
  } else {
    s.kind = "bowl";
    const double r = R(0.06, 0.11), h = R(0.07, 0.1);
    s.profile = {{0, r}, {0.5 * h, 0.85 * r}, {h, 0.5 * r}};
  }
  return s;
}

// Horizontal footprint radius of a shape (metres).
double footprint(const Shape& s) {
  if (s.kind == "box") return 0.5 * std::hypot(s.extents.x(), s.extents.z());
  double r = 0;
  for (const auto& p : s.profile) r = std::max(r, p.second);
  return r;
}

// A support rectangle: x in [x0, x1], z in [z0, z1], top surface at y.
struct Support {
  double x0, x1, z0, z1, y;
  bool floor = false;  // a floor strip (placements must be in view, floor_visible)
};

}  // namespace

const char* to_string(InjectedError e) {
  switch (e) {
    case InjectedError::None: return "none";
    case InjectedError::Hover: return "hover";
    case InjectedError::Sink: return "sink";
    case InjectedError::BottomCut: return "bottom_cut";
    case InjectedError::Scale: return "scale";
    case InjectedError::Rotation: return "rotation";
  }
  return "none";
}

std::optional<InjectedError> parse_injected_error(const std::string& s) {
  for (InjectedError e : {InjectedError::None, InjectedError::Hover, InjectedError::Sink, InjectedError::BottomCut,
                          InjectedError::Scale, InjectedError::Rotation})
    if (s == to_string(e)) return e;
  return std::nullopt;
}

Branch expected_branch(InjectedError e) { return e == InjectedError::BottomCut ? Branch::Resample : Branch::Stretch; }

SyntheticConfig SyntheticConfig::from(simu::config::Reader& r) {
  SyntheticConfig c;
  r.field("layout", c.layout);
  r.field("min_objects", c.min_objects);
  r.field("max_objects", c.max_objects);
  r.field("min_hanging", c.min_hanging);
  r.field("max_hanging", c.max_hanging);
  r.field("placement_attempts", c.placement_attempts);
  r.field("floor_supports", c.floor_supports);
  r.field("width", c.width);
  r.field("height", c.height);
  r.field("fx", c.fx);
  r.field("camera_pitch_deg", c.camera_pitch_deg);
  r.field("write_depth", c.write_depth);
  r.field("w_none", c.w_none);
  r.field("w_hover", c.w_hover);
  r.field("w_sink", c.w_sink);
  r.field("w_cut", c.w_cut);
  r.field("w_scale", c.w_scale);
  r.field("w_rotation", c.w_rotation);
  r.field("hover_min", c.hover_min);
  r.field("hover_max", c.hover_max);
  r.field("cut_min", c.cut_min);
  r.field("cut_max", c.cut_max);
  r.field("scale_min", c.scale_min);
  r.field("scale_max", c.scale_max);
  r.field("rotation_max_deg", c.rotation_max_deg);
  r.finish();
  return c;
}

double normalise_canonical(Mesh& m) {
  SIMU_CHECK(m.V.rows() > 0, "normalise_canonical: empty mesh");
  const Vec3 lo = m.V.colwise().minCoeff().transpose(), hi = m.V.colwise().maxCoeff().transpose();
  const double longest = (hi - lo).maxCoeff();
  SIMU_CHECK(longest > 0, "normalise_canonical: degenerate mesh");
  m.V = (m.V.rowwise() - (0.5 * (lo + hi)).transpose()) / longest;
  return longest;
}

Mesh canonical_box_mesh(const Vec3& extents) {
  Obb b;
  b.extents = extents;
  Mesh m = b.to_mesh();
  normalise_canonical(m);
  return m;
}

Mesh lathe_mesh(const std::vector<std::pair<double, double>>& prof, int S) {
  Mesh m = lathe_raw(prof, S);
  normalise_canonical(m);
  return m;
}

namespace {
// Surface of revolution in metres (not normalised): the capped lathe (both ends on radius > 0).
Mesh lathe_raw(const std::vector<std::pair<double, double>>& prof, int S) {
  SIMU_CHECK(prof.size() >= 2 && S >= 3, "lathe_mesh: need >= 2 profile points and >= 3 segments");
  return revolve_mesh(prof, S);
}
}  // namespace


namespace {
using Rng = std::mt19937_64;
double uniform(Rng& rng, double a, double b) { return a + (b - a) * std::uniform_real_distribution<double>(0, 1)(rng); }
double unit(Rng& rng) { return std::uniform_real_distribution<double>(0, 1)(rng); }

// The layout's fixed bases and the support rectangles objects stand on; returns the back wall's z.
double make_layout(SyntheticScene& s, std::vector<Support>& supports, double floor_y, const SyntheticConfig& cfg) {
  if (s.layout == "tabletop") {
    SyntheticBase table;
    table.id = "table";
    const Vec3 e(1.4, 0.75, 0.9);
    table.mesh = canonical_box_mesh(e);
    table.scale = Vec3::Constant(e.maxCoeff());
    table.t = Vec3(0, floor_y - e.y() / 2, 1.9);
    s.bases.push_back(table);
    supports.push_back({-0.6, 0.6, 1.55, 2.25, floor_y - e.y()});
    // Floor strips left and right of the table; much of them is hidden behind the table from the
    // camera, so place_free_objects keeps only floor placements the camera sees (floor_visible).
    if (cfg.floor_supports) {
      supports.push_back({-1.08, -0.72, 1.6, 2.55, floor_y, true});
      supports.push_back({0.72, 1.45, 1.6, 2.55, floor_y, true});
    }
    return 2.6;
  }
  const double wall_z = 2.2;
  for (int b = 0; b < 2; ++b) {
    SyntheticBase board;
    board.id = fmt::format("shelf_{}", b);
    const Vec3 e(1.2, 0.03, 0.35);
    board.mesh = canonical_box_mesh(e);
    board.scale = Vec3::Constant(e.maxCoeff());
    const double top = b == 0 ? 0.9 : 0.5;
    board.t = Vec3(0, top + e.y() / 2, wall_z - e.z() / 2);
    s.bases.push_back(board);
    supports.push_back({-0.55, 0.55, wall_z - e.z() + 0.04, wall_z - 0.04, top});
  }
  return wall_z;
}

// Draws the injected error of a free object (ground truth already set) and applies it to its prediction.
void inject_error(SyntheticObject& o, const Shape& shape, const SyntheticConfig& cfg, Rng& rng) {
  const double h = shape.height();
  const double wsum = cfg.w_none + cfg.w_hover + cfg.w_sink + cfg.w_cut + cfg.w_scale + cfg.w_rotation;
  double pick = unit(rng) * wsum;
  const double w[6] = {cfg.w_none, cfg.w_hover, cfg.w_sink, cfg.w_cut, cfg.w_scale, cfg.w_rotation};
  int e = 0;
  while (e < 5 && pick >= w[e]) pick -= w[e], ++e;
  o.error = InjectedError(e);
  o.pred_mesh = o.gt_mesh, o.pred_scale = o.gt_scale, o.pred_R = o.gt_R, o.pred_t = o.gt_t;
  switch (o.error) {
    case InjectedError::None: break;
    case InjectedError::Hover:
    case InjectedError::Sink: {
      o.magnitude = uniform(rng, cfg.hover_min, cfg.hover_max) * h;
      o.pred_t.y() += o.error == InjectedError::Hover ? -o.magnitude : o.magnitude;
      break;
    }
    case InjectedError::BottomCut: {
      o.magnitude = uniform(rng, cfg.cut_min, cfg.cut_max);
      o.pred_mesh = shape.cut_bottom(o.magnitude).mesh();
      o.pred_scale = Vec3::Constant(normalise_canonical(o.pred_mesh));
      o.pred_t.y() -= o.magnitude * h / 2;  // top kept where it was
      break;
    }
    case InjectedError::Scale: {
      o.magnitude = uniform(rng, cfg.scale_min, cfg.scale_max);
      o.pred_scale = o.gt_scale * o.magnitude;
      break;
    }
    case InjectedError::Rotation: {
      o.magnitude = uniform(rng, 1.0, cfg.rotation_max_deg);
      const double az = uniform(rng, -kPi, kPi);
      o.pred_R = rot(o.magnitude * kPi / 180, Vec3(std::cos(az), 0, std::sin(az))) * o.gt_R;
      break;
    }
  }
}

// A floor placement the camera sees: the object's top centre and mid-height centre project inside the
// image (5% margin) and no base's box lies between them and the camera.
bool floor_visible(const SyntheticScene& s, double x, double z, double support_y, double height) {
  for (const double f : {1.0, 0.5}) {
    const Vec3 p(x, support_y - f * height, z);
    const Projection pr = project(s.camera, p);
    const double mu = 0.05 * s.camera.width, mv = 0.05 * s.camera.height;
    if (!pr.in_front() || pr.u < mu || pr.u > s.camera.width - mu || pr.v < mv || pr.v > s.camera.height - mv) return false;
    for (const auto& b : s.bases) {
      const Vec3 half = 0.5 * b.scale.cwiseProduct(b.mesh.V.colwise().maxCoeff().transpose() - b.mesh.V.colwise().minCoeff().transpose());
      if (!segment_misses_box(camera_center(s.camera), p, b.t - half, b.t + half)) return false;
    }
  }
  return true;
}

// Free objects: rejection-sampled footprints on the supports (placement_attempts tries each; an object
// that does not fit is left out). With floor_supports, a floor placement must also be in view (floor_visible).
void place_free_objects(SyntheticScene& s, const std::vector<Support>& supports, const SyntheticConfig& cfg, Rng& rng) {
  const int n_free = cfg.min_objects + int(unit(rng) * (cfg.max_objects - cfg.min_objects + 1));
  std::vector<std::array<double, 4>> placed;  // x, z, radius, support index
  for (int i = 0; i < n_free; ++i) {
    const Shape shape = random_free_shape(rng);
    const double rad = footprint(shape);
    bool ok = false;
    double x = 0, z = 0;
    int si = 0;
    for (int attempt = 0; attempt < cfg.placement_attempts && !ok; ++attempt) {
      si = int(unit(rng) * supports.size());
      const Support& sp = supports[si];
      if (sp.x1 - sp.x0 < 2 * rad || sp.z1 - sp.z0 < 2 * rad) continue;
      x = uniform(rng, sp.x0 + rad, sp.x1 - rad), z = uniform(rng, sp.z0 + rad, sp.z1 - rad);
      ok = !sp.floor || floor_visible(s, x, z, sp.y, shape.height());
      for (const auto& p : placed)
        if (int(p[3]) == si && std::hypot(p[0] - x, p[1] - z) < p[2] + rad + 0.01) ok = false;
    }
    if (!ok) continue;
    placed.push_back({x, z, rad, double(si)});
    SyntheticObject o;
    o.id = fmt::format("obj{:02d}_{}", i, shape.kind);
    o.label = shape.kind;
    o.dof = PoseDof::Free;
    o.support_y = supports[si].y;
    // Ground truth: canonical mesh, yaw, resting on the support.
    o.gt_mesh = shape.mesh();
    const double size = normalise_canonical(o.gt_mesh);
    o.gt_scale = Vec3::Constant(size);
    o.gt_R = rot(uniform(rng, -kPi, kPi), Vec3::UnitY());
    o.gt_t = Vec3(x, o.support_y - shape.height() / 2, z);
    inject_error(o, shape, cfg, rng);
    s.objects.push_back(std::move(o));
  }
}

// Hanging objects on the back wall: frames (two pins) and clocks (one pin).
void place_hanging(SyntheticScene& s, double wall_z, const SyntheticConfig& cfg, Rng& rng) {
  const int n_hang = cfg.max_hanging > 0 ? cfg.min_hanging + int(unit(rng) * (cfg.max_hanging - cfg.min_hanging + 1)) : 0;
  const double hang_y = s.layout == "tabletop" ? 0.15 : 0.1;
  for (int i = 0; i < n_hang; ++i) {
    SyntheticObject o;
    const bool frame = unit(rng) < 0.6;
    Shape shape;
    if (frame) {
      shape.kind = "frame";
      // (one expression, as before the split: the draws' order is the compiler's argument order)
      shape.extents = Vec3(uniform(rng, 0.2, 0.35), uniform(rng, 0.15, 0.25), uniform(rng, 0.02, 0.03));
      o.dof = PoseDof::LineAnchored;
    } else {
      shape.kind = "clock";
      const double r = uniform(rng, 0.08, 0.13), d = uniform(rng, 0.03, 0.05);
      shape.profile = {{0, r}, {d, r}};
      o.dof = PoseDof::PointAnchored;
    }
    o.id = fmt::format("hang{:02d}_{}", i, shape.kind);
    o.label = shape.kind;
    o.wall_id = "back";
    o.gt_mesh = shape.mesh();
    o.gt_scale = Vec3::Constant(normalise_canonical(o.gt_mesh));
    // Clocks: canonical y (the lathe axis) -> world z (towards the wall).
    o.gt_R = frame ? Mat3::Identity() : rot(kPi / 2, Vec3::UnitX());
    const double depth = frame ? shape.extents.z() : shape.profile.back().first;
    const double x = (i - 0.5 * (n_hang - 1)) * 0.45 + uniform(rng, -0.05, 0.05);
    const double y = hang_y + uniform(rng, -0.05, 0.05);
    o.gt_t = Vec3(x, y, wall_z - depth / 2 - 0.003);
    o.pred_mesh = o.gt_mesh, o.pred_scale = o.gt_scale, o.pred_R = o.gt_R, o.pred_t = o.gt_t;
    if (unit(rng) < 0.5) {
      o.error = InjectedError::Rotation;
      o.magnitude = uniform(rng, 1.0, cfg.rotation_max_deg);
      o.pred_R = rot(o.magnitude * kPi / 180, Vec3::UnitZ()) * o.gt_R;
    }
    s.objects.push_back(std::move(o));
  }
}

}  // namespace

LabelImage render_truth_labels(const SyntheticScene& s, std::vector<Mesh>* world) {
  std::vector<Mesh> placed;
  for (const auto& b : s.bases) placed.push_back(place(b.mesh, b.scale, b.R, b.t));
  for (const auto& o : s.objects) placed.push_back(place(o.gt_mesh, o.gt_scale, o.gt_R, o.gt_t));
  std::vector<const Mesh*> ptrs;
  for (const auto& m : placed) ptrs.push_back(&m);
  LabelImage img = render_labels(s.camera, ptrs);
  if (world) *world = std::move(placed);
  return img;
}

namespace {

// Ground truth render: bases first, then objects; modal masks are the visible ground truth, with the
// removed bottom hidden (as by an occluder) for BottomCut objects.
void render_truth(SyntheticScene& s, const SyntheticConfig& cfg) {
  std::vector<Mesh> world;
  const LabelImage img = render_truth_labels(s, &world);
  for (size_t i = 0; i < s.objects.size(); ++i) {
    SyntheticObject& o = s.objects[i];
    const Mesh& wm = world[s.bases.size() + i];
    o.gt_box = {wm.V.colwise().minCoeff().transpose(), wm.V.colwise().maxCoeff().transpose()};
    o.modal_mask = img.mask_of(int(s.bases.size() + i));
    if (o.error == InjectedError::BottomCut) {
      const BinaryMask vis = render_silhouette(s.camera, place(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t));
      for (size_t k = 0; k < vis.data.size(); ++k) o.modal_mask.data[k] &= vis.data[k];
    }
  }
  if (cfg.write_depth) s.depth = img.depth;
}
}  // namespace

SyntheticScene generate_scene(const SyntheticConfig& cfg, uint64_t seed, const std::string& name) {
  SIMU_CHECK(cfg.min_objects >= 0 && cfg.max_objects >= cfg.min_objects, "synthetic: bad object counts {}..{}",
             cfg.min_objects, cfg.max_objects);
  SIMU_CHECK(cfg.min_hanging >= 0 && cfg.max_hanging >= cfg.min_hanging, "synthetic: bad hanging counts {}..{}",
             cfg.min_hanging, cfg.max_hanging);
  SIMU_CHECK(cfg.placement_attempts > 0, "synthetic: placement_attempts {} must be positive", cfg.placement_attempts);
  Rng rng(seed * 0x9E3779B97F4A7C15ULL + 12345);
  SyntheticScene s;
  s.name = name;
  s.layout = cfg.layout == "mixed" ? (seed % 2 ? "shelf" : "tabletop") : cfg.layout;
  SIMU_CHECK(s.layout == "tabletop" || s.layout == "shelf", "synthetic: unknown layout '{}' (tabletop, shelf, mixed)",
             cfg.layout);
  // Camera at the origin, pitched down; world y down.
  s.camera.fx = s.camera.fy = cfg.fx;
  s.camera.width = cfg.width, s.camera.height = cfg.height;
  s.camera.cx = cfg.width / 2.0, s.camera.cy = cfg.height / 2.0;
  s.camera.R_world_cam = rot(-cfg.camera_pitch_deg * kPi / 180, Vec3::UnitX());
  const double floor_y = 1.3;
  s.floor.id = "floor", s.floor.point = Vec3(0, floor_y, 0), s.floor.normal = Vec3(0, -1, 0);
  std::vector<Support> supports;
  const double wall_z = make_layout(s, supports, floor_y, cfg);
  s.walls.push_back({"back", Vec3(0, 0, wall_z), Vec3(0, 0, -1)});
  place_free_objects(s, supports, cfg, rng);
  place_hanging(s, wall_z, cfg, rng);
  render_truth(s, cfg);
  return s;
}
}  // namespace simu::physics
