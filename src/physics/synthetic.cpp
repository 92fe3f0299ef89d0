// Synthetic scene generator: layouts, primitive meshes, injected errors, rendered masks, writer.
#include "physics/synthetic.h"

#include "common/error.h"
#include "common/fs.h"
#include "physics/camera.h"
#include "physics/mesh.h"
#include "physics/metrics.h"
#include "physics/overlay.h"
#include "physics/probe.h"

#include <Eigen/Geometry>

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
  r.field("max_hanging", c.max_hanging);
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
// Surface of revolution in metres (not normalised).
Mesh lathe_raw(const std::vector<std::pair<double, double>>& prof, int S) {
  SIMU_CHECK(prof.size() >= 2 && S >= 3, "lathe_mesh: need >= 2 profile points and >= 3 segments");
  const int K = int(prof.size());
  Mesh m;
  m.V.resize(2 + K * S, 3);
  m.V.row(0) << 0, prof.front().first, 0;  // top centre
  for (int k = 0; k < K; ++k)
    for (int i = 0; i < S; ++i) {
      const double th = 2 * kPi * i / S;
      m.V.row(1 + k * S + i) << prof[k].second * std::cos(th), prof[k].first, prof[k].second * std::sin(th);
    }
  const int bottom = 1 + K * S;
  m.V.row(bottom) << 0, prof.back().first, 0;
  std::vector<Eigen::Vector3i> F;
  auto ring = [&](int k, int i) { return 1 + k * S + (i % S); };
  // Caps (outward: top faces -y, bottom +y) and side quads (outward radial).
  for (int i = 0; i < S; ++i) {
    F.emplace_back(0, ring(0, i), ring(0, i + 1));
    F.emplace_back(bottom, ring(K - 1, i + 1), ring(K - 1, i));
    for (int k = 0; k + 1 < K; ++k) {
      F.emplace_back(ring(k, i), ring(k + 1, i), ring(k + 1, i + 1));
      F.emplace_back(ring(k, i), ring(k + 1, i + 1), ring(k, i + 1));
    }
  }
  m.F.resize(F.size(), 3);
  for (size_t f = 0; f < F.size(); ++f) m.F.row(f) = F[f].transpose();
  return m;
}
}  // namespace

void write_obj(const std::string& path, const Mesh& m) {
  std::ostringstream os;
  os.precision(9);
  os << "# simuscene synthetic mesh\n";
  for (Eigen::Index i = 0; i < m.V.rows(); ++i) os << "v " << m.V(i, 0) << ' ' << m.V(i, 1) << ' ' << m.V(i, 2) << '\n';
  for (Eigen::Index f = 0; f < m.F.rows(); ++f)
    os << "f " << m.F(f, 0) + 1 << ' ' << m.F(f, 1) + 1 << ' ' << m.F(f, 2) + 1 << '\n';
  const auto parent = std::filesystem::path(path).parent_path();
  if (!parent.empty()) std::filesystem::create_directories(parent);
  simu::fs::atomic_write(path, os.str());
}

SyntheticScene generate_scene(const SyntheticConfig& cfg, uint64_t seed, const std::string& name) {
  SIMU_CHECK(cfg.min_objects >= 0 && cfg.max_objects >= cfg.min_objects, "synthetic: bad object counts {}..{}",
             cfg.min_objects, cfg.max_objects);
  std::mt19937_64 rng(seed * 0x9E3779B97F4A7C15ULL + 12345);
  std::uniform_real_distribution<double> U(0, 1);
  auto R = [&](double a, double b) { return a + (b - a) * U(rng); };

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

  // Fixed bases and the support rectangles objects stand on.
  std::vector<Support> supports;
  double wall_z;
  if (s.layout == "tabletop") {
    wall_z = 2.6;
    SyntheticBase table;
    table.id = "table";
    const Vec3 e(1.4, 0.75, 0.9);
    table.mesh = canonical_box_mesh(e);
    table.scale = Vec3::Constant(e.maxCoeff());
    table.t = Vec3(0, floor_y - e.y() / 2, 1.9);
    s.bases.push_back(table);
    supports.push_back({-0.6, 0.6, 1.55, 2.25, floor_y - e.y()});
  } else {
    wall_z = 2.2;
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
  }
  s.walls.push_back({"back", Vec3(0, 0, wall_z), Vec3(0, 0, -1)});

  // Free objects: rejection-sampled footprints on the supports.
  const int n_free = cfg.min_objects + int(U(rng) * (cfg.max_objects - cfg.min_objects + 1));
  std::vector<std::array<double, 4>> placed;  // x, z, radius, support index
  const double wsum = cfg.w_none + cfg.w_hover + cfg.w_sink + cfg.w_cut + cfg.w_scale + cfg.w_rotation;
  for (int i = 0; i < n_free; ++i) {
    const Shape shape = random_free_shape(rng);
    const double rad = footprint(shape);
    bool ok = false;
    double x = 0, z = 0;
    int si = 0;
    for (int attempt = 0; attempt < 60 && !ok; ++attempt) {
      si = int(U(rng) * supports.size());
      const Support& sp = supports[si];
      if (sp.x1 - sp.x0 < 2 * rad || sp.z1 - sp.z0 < 2 * rad) continue;
      x = R(sp.x0 + rad, sp.x1 - rad), z = R(sp.z0 + rad, sp.z1 - rad);
      ok = true;
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
    const double h = shape.height();
    o.gt_scale = Vec3::Constant(size);
    o.gt_R = rot(R(-kPi, kPi), Vec3::UnitY());
    o.gt_t = Vec3(x, o.support_y - h / 2, z);
    // Injected error.
    double pick = U(rng) * wsum;
    const double w[6] = {cfg.w_none, cfg.w_hover, cfg.w_sink, cfg.w_cut, cfg.w_scale, cfg.w_rotation};
    int e = 0;
    while (e < 5 && pick >= w[e]) pick -= w[e], ++e;
    o.error = InjectedError(e);
    o.pred_mesh = o.gt_mesh, o.pred_scale = o.gt_scale, o.pred_R = o.gt_R, o.pred_t = o.gt_t;
    switch (o.error) {
      case InjectedError::None: break;
      case InjectedError::Hover:
      case InjectedError::Sink: {
        o.magnitude = R(cfg.hover_min, cfg.hover_max) * h;
        o.pred_t.y() += o.error == InjectedError::Hover ? -o.magnitude : o.magnitude;
        break;
      }
      case InjectedError::BottomCut: {
        o.magnitude = R(cfg.cut_min, cfg.cut_max);
        o.pred_mesh = shape.cut_bottom(o.magnitude).mesh();
        o.pred_scale = Vec3::Constant(normalise_canonical(o.pred_mesh));
        o.pred_t.y() -= o.magnitude * h / 2;  // top kept where it was
        break;
      }
      case InjectedError::Scale: {
        o.magnitude = R(cfg.scale_min, cfg.scale_max);
        o.pred_scale = o.gt_scale * o.magnitude;
        break;
      }
      case InjectedError::Rotation: {
        o.magnitude = R(1.0, cfg.rotation_max_deg);
        const double az = R(-kPi, kPi);
        o.pred_R = rot(o.magnitude * kPi / 180, Vec3(std::cos(az), 0, std::sin(az))) * o.gt_R;
        break;
      }
    }
    s.objects.push_back(std::move(o));
  }

  // Hanging objects on the back wall: frames (two pins) and clocks (one pin).
  const int n_hang = cfg.max_hanging > 0 ? int(U(rng) * (cfg.max_hanging + 1)) : 0;
  const double hang_y = s.layout == "tabletop" ? 0.15 : 0.1;
  for (int i = 0; i < n_hang; ++i) {
    SyntheticObject o;
    const bool frame = U(rng) < 0.6;
    Shape shape;
    if (frame) {
      shape.kind = "frame";
      shape.extents = Vec3(R(0.2, 0.35), R(0.15, 0.25), R(0.02, 0.03));
      o.dof = PoseDof::LineAnchored;
    } else {
      shape.kind = "clock";
      const double r = R(0.08, 0.13), d = R(0.03, 0.05);
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
    const double x = (i - 0.5 * (n_hang - 1)) * 0.45 + R(-0.05, 0.05);
    o.gt_t = Vec3(x, hang_y + R(-0.05, 0.05), wall_z - depth / 2 - 0.003);
    o.pred_mesh = o.gt_mesh, o.pred_scale = o.gt_scale, o.pred_R = o.gt_R, o.pred_t = o.gt_t;
    if (U(rng) < 0.5) {
      o.error = InjectedError::Rotation;
      o.magnitude = R(1.0, cfg.rotation_max_deg);
      o.pred_R = rot(o.magnitude * kPi / 180, Vec3::UnitZ()) * o.gt_R;
    }
    s.objects.push_back(std::move(o));
  }

  // Ground truth render: bases first, then objects; modal masks are the visible ground truth, with
  // the removed bottom hidden (as by an occluder) for BottomCut objects.
  std::vector<Mesh> world;
  for (const auto& b : s.bases) world.push_back(place(b.mesh, b.scale, b.R, b.t));
  for (const auto& o : s.objects) world.push_back(place(o.gt_mesh, o.gt_scale, o.gt_R, o.gt_t));
  std::vector<const Mesh*> ptrs;
  for (const auto& m : world) ptrs.push_back(&m);
  const LabelImage img = render_labels(s.camera, ptrs);
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
  return s;
}

namespace {
nlohmann::json mat_json(const Mat3& R) {
  return nlohmann::json::array({{R(0, 0), R(0, 1), R(0, 2)}, {R(1, 0), R(1, 1), R(1, 2)}, {R(2, 0), R(2, 1), R(2, 2)}});
}
nlohmann::json vec_json(const Vec3& v) { return nlohmann::json::array({v.x(), v.y(), v.z()}); }
}  // namespace

Scene to_probe_scene(const SyntheticScene& s, const std::string& dir) {
  namespace sfs = std::filesystem;
  Scene sc;
  sc.path = (sfs::path(dir) / "scene.json").string();
  sc.image_path = (sfs::path(dir) / "rgb.png").string();
  if (!s.depth.empty()) sc.depth_path = (sfs::path(dir) / "depth.png").string();
  sc.camera = s.camera;
  sc.gravity = s.gravity;
  sc.floor = s.floor;
  sc.walls = s.walls;
  for (const auto& b : s.bases) {
    BaseBody bb;
    bb.id = b.id;
    bb.mesh_path = (sfs::path(dir) / "meshes" / (b.id + ".obj")).string();
    bb.scale = b.scale, bb.R = b.R, bb.t = b.t;
    sc.bases.push_back(bb);
  }
  for (const auto& o : s.objects) {
    SceneObject so;
    so.id = o.id;
    so.label = o.label;
    so.mesh_path = (sfs::path(dir) / "meshes" / (o.id + ".obj")).string();
    so.mask_path = (sfs::path(dir) / "masks" / (o.id + ".png")).string();
    so.scale = o.pred_scale, so.R = o.pred_R, so.t = o.pred_t;
    so.dof = o.dof;
    so.wall_id = o.wall_id;
    so.gt_box = o.gt_box;
    nlohmann::json syn;
    syn["error"] = to_string(o.error);
    syn["magnitude"] = o.magnitude;
    if (o.dof == PoseDof::Free) syn["expected_branch"] = to_string(expected_branch(o.error));
    syn["support_y"] = o.support_y;
    syn["gt"] = {{"mesh", "meshes/" + o.id + "_gt.obj"},
                 {"scale", vec_json(o.gt_scale)},
                 {"R", mat_json(o.gt_R)},
                 {"t", vec_json(o.gt_t)}};
    so.extra["synthetic"] = syn;
    sc.objects.push_back(so);
  }
  sc.extra["synthetic_layout"] = s.layout;
  return sc;
}

void write_scene_dir(const SyntheticScene& s, const std::string& dir_in) {
  namespace sfs = std::filesystem;
  // Absolute, so that the scene file's paths are written relative to it.
  const std::string dir = sfs::absolute(dir_in).lexically_normal().string();
  sfs::create_directories(sfs::path(dir) / "meshes");
  sfs::create_directories(sfs::path(dir) / "masks");
  for (const auto& b : s.bases) write_obj((sfs::path(dir) / "meshes" / (b.id + ".obj")).string(), b.mesh);
  for (const auto& o : s.objects) {
    write_obj((sfs::path(dir) / "meshes" / (o.id + ".obj")).string(), o.pred_mesh);
    write_obj((sfs::path(dir) / "meshes" / (o.id + "_gt.obj")).string(), o.gt_mesh);
    write_mask((sfs::path(dir) / "masks" / (o.id + ".png")).string(), o.modal_mask);
  }
#ifdef SIMU_HAVE_OPENCV
  // A flat-shaded picture of the ground truth (labels coloured, darker with depth) as the "image".
  {
    std::vector<Mesh> world;
    for (const auto& b : s.bases) world.push_back(place(b.mesh, b.scale, b.R, b.t));
    for (const auto& o : s.objects) world.push_back(place(o.gt_mesh, o.gt_scale, o.gt_R, o.gt_t));
    std::vector<const Mesh*> ptrs;
    for (const auto& m : world) ptrs.push_back(&m);
    const LabelImage img = render_labels(s.camera, ptrs);
    cv::Mat rgb(s.camera.height, s.camera.width, CV_8UC3, cv::Scalar(200, 200, 200));
    for (int r = 0; r < img.height; ++r)
      for (int c = 0; c < img.width; ++c) {
        const int l = img.label[size_t(r) * img.width + c];
        if (l < 0) continue;
        const double shade = std::clamp(1.3 - 0.2 * img.depth[size_t(r) * img.width + c], 0.4, 1.0);
        std::array<uint8_t, 3> col = l < int(s.bases.size()) ? std::array<uint8_t, 3>{60, 100, 140}
                                                             : overlay_color(l - int(s.bases.size()));
        rgb.at<cv::Vec3b>(r, c) = cv::Vec3b(uint8_t(col[0] * shade), uint8_t(col[1] * shade), uint8_t(col[2] * shade));
      }
    std::vector<uchar> buf;
    cv::imencode(".png", rgb, buf);
    simu::fs::atomic_write((sfs::path(dir) / "rgb.png").string(),
                           std::string_view(reinterpret_cast<const char*>(buf.data()), buf.size()));
    if (!s.depth.empty()) {
      cv::Mat d(s.camera.height, s.camera.width, CV_16U);
      for (int r = 0; r < d.rows; ++r)
        for (int c = 0; c < d.cols; ++c) {
          const float z = s.depth[size_t(r) * d.cols + c];
          d.at<uint16_t>(r, c) = std::isfinite(z) ? uint16_t(std::min(65535.0, std::round(z * 1000.0))) : 0;
        }
      cv::imencode(".png", d, buf);
      simu::fs::atomic_write((sfs::path(dir) / "depth.png").string(),
                             std::string_view(reinterpret_cast<const char*>(buf.data()), buf.size()));
    }
  }
#endif
  save_scene(to_probe_scene(s, dir), (sfs::path(dir) / "scene.json").string());
}

SyntheticScene load_synthetic_scene(const std::string& scene_json) {
  namespace sfs = std::filesystem;
  const Scene sc = load_scene(scene_json);
  const sfs::path dir = sfs::absolute(scene_json).parent_path();
  SyntheticScene s;
  s.name = dir.filename().string();
  s.layout = sc.extra.value("synthetic_layout", std::string());
  s.camera = sc.camera;
  s.gravity = sc.gravity;
  SIMU_CHECK(sc.floor.has_value(), "{}: a synthetic scene needs a floor", scene_json);
  s.floor = *sc.floor;
  s.walls = sc.walls;
  for (const BaseBody& b : sc.bases) {
    SIMU_CHECK(b.error.empty(), "{}: base {}: {}", scene_json, b.id, b.error);
    SyntheticBase sb;
    sb.id = b.id, sb.mesh = read_mesh(b.mesh_path), sb.scale = b.scale, sb.R = b.R, sb.t = b.t;
    s.bases.push_back(std::move(sb));
  }
  auto vec = [&](const nlohmann::json& j, const std::string& what) {
    SIMU_CHECK(j.is_array() && j.size() == 3, "{}: {} is not a 3-vector", scene_json, what);
    return Vec3(j[0].get<double>(), j[1].get<double>(), j[2].get<double>());
  };
  for (const SceneObject& so : sc.objects) {
    SIMU_CHECK(so.error.empty(), "{}: object {}: {}", scene_json, so.id, so.error);
    SIMU_CHECK(so.extra.contains("synthetic"), "{}: object {} has no \"synthetic\" record", scene_json, so.id);
    const nlohmann::json& syn = so.extra["synthetic"];
    const std::string what = "object " + so.id + ".synthetic";
    SyntheticObject o;
    o.id = so.id, o.label = so.label, o.dof = so.dof, o.wall_id = so.wall_id;
    o.pred_mesh = read_mesh(so.mesh_path);
    o.pred_scale = so.scale, o.pred_R = so.R, o.pred_t = so.t;
    const auto err = parse_injected_error(syn.value("error", std::string("none")));
    SIMU_CHECK(err.has_value(), "{}: {}.error: unknown value {}", scene_json, what, syn.value("error", std::string()));
    o.error = *err;
    o.magnitude = syn.value("magnitude", 0.0);
    o.support_y = syn.value("support_y", 0.0);
    SIMU_CHECK(syn.contains("gt"), "{}: {}.gt missing", scene_json, what);
    const nlohmann::json& gt = syn["gt"];
    o.gt_mesh = read_mesh((dir / gt.at("mesh").get<std::string>()).string());
    o.gt_scale = vec(gt.at("scale"), what + ".gt.scale");
    for (int r = 0; r < 3; ++r) o.gt_R.row(r) = vec(gt.at("R").at(r), what + ".gt.R").transpose();
    o.gt_t = vec(gt.at("t"), what + ".gt.t");
    if (so.gt_box) o.gt_box = *so.gt_box;
    else o.gt_box = world_aabb(place(o.gt_mesh, o.gt_scale, o.gt_R, o.gt_t));
    o.modal_mask = read_mask(so.mask_path);
    SIMU_CHECK(o.modal_mask.width == s.camera.width && o.modal_mask.height == s.camera.height,
               "{}: mask {} is {}x{}, the camera {}x{}", scene_json, so.mask_path, o.modal_mask.width,
               o.modal_mask.height, s.camera.width, s.camera.height);
    s.objects.push_back(std::move(o));
  }
  return s;
}

std::optional<ResampleProxy> parse_resample_proxy(const std::string& s) {
  if (s == "stretch") return ResampleProxy::Stretch;
  if (s == "drop") return ResampleProxy::Drop;
  if (s == "keep") return ResampleProxy::Keep;
  return std::nullopt;
}

Displacement oracle_displacement(const SyntheticScene& s, const SyntheticObject& o) {
  const Mesh w = place(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t);
  const Vec3 g = s.gravity.normalized();
  // Gap along gravity between the lowest point (max g.x) and the support plane y = support_y.
  const double lowest = (w.V * g).maxCoeff();
  const double support = g.dot(Vec3(0, o.support_y, 0));
  const double d = support - lowest;
  Displacement out;
  if (d > 0) out.dt_grv = d * g;
  else out.dt_pen = d * g;
  return out;
}

SceneEvaluation evaluate_corrected(const SyntheticScene& s, const std::vector<CorrectedObject>& after_objs) {
  SIMU_CHECK(after_objs.size() == s.objects.size(), "evaluate_corrected: {} corrected objects for {} scene objects",
             after_objs.size(), s.objects.size());
  SceneEvaluation ev;
  const Vec3 g = s.gravity.normalized();
  std::vector<Mesh> before, after;
  std::vector<Box3> gt_boxes;
  std::vector<BinaryMask> gt_masks;
  std::vector<MetricCategory> cats;
  std::vector<bool> valid_after;
  for (size_t i = 0; i < s.objects.size(); ++i) {
    const SyntheticObject& o = s.objects[i];
    const CorrectedObject& c = after_objs[i];
    before.push_back(place(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t));
    after.push_back(place(c.mesh.V.rows() > 0 ? c.mesh : o.pred_mesh, c.scale, c.R, c.t));
    gt_boxes.push_back(o.gt_box);
    gt_masks.push_back(o.modal_mask);
    cats.push_back(metric_category(o.dof));
    valid_after.push_back(c.valid);
    if (o.dof != PoseDof::Free) continue;
    // Free objects: the decision against the injected error and the support gaps.
    ObjectOutcome oc;
    oc.id = o.id, oc.error = o.error, oc.expected = expected_branch(o.error);
    oc.got = c.branch, oc.decided = c.decided, oc.rho = c.rho, oc.eta = c.eta, oc.flags = c.flags;
    const double support = g.dot(Vec3(0, o.support_y, 0));
    oc.support_gap_before = std::abs((before.back().V * g).maxCoeff() - support);
    oc.support_gap_after = std::abs((after.back().V * g).maxCoeff() - support);
    ev.objects.push_back(oc);
  }
  // Overlap metrics: the objects rendered jointly with the bases placed after them as occluders
  // (their masks are not scored).
  std::vector<Mesh> bases;
  for (const auto& b : s.bases) bases.push_back(place(b.mesh, b.scale, b.R, b.t));
  auto score = [&](const std::vector<Mesh>& objs, const std::vector<bool>& valid, OverlapMetrics* mask,
                   OverlapMetrics* box) {
    std::vector<const Mesh*> ptrs;
    for (const auto& m : objs) ptrs.push_back(&m);
    for (const auto& b : bases) ptrs.push_back(&b);
    const LabelImage img = render_labels(s.camera, ptrs);
    std::vector<std::vector<double>> iou(objs.size(), std::vector<double>(objs.size(), 0.0));
    for (size_t j = 0; j < objs.size(); ++j) {
      const BinaryMask pj = img.mask_of(int(j));
      for (size_t i = 0; i < objs.size(); ++i) iou[i][j] = mask_iou(gt_masks[i], pj);
    }
    *mask = overlap_metrics(iou, valid, cats);
    ptrs.resize(objs.size());
    *box = box_metrics(ptrs, gt_boxes, valid, cats);
  };
  score(before, std::vector<bool>(before.size(), true), &ev.mask_before, &ev.box_before);
  score(after, valid_after, &ev.mask_after, &ev.box_after);
  return ev;
}

SceneEvaluation evaluate_scene(const SyntheticScene& s, const CorrectionConfig& config,
                               const std::vector<Displacement>& displacements, ResampleProxy proxy) {
  const Vec3 g = s.gravity.normalized();
  std::vector<CorrectedObject> after;
  for (size_t i = 0; i < s.objects.size(); ++i) {
    const SyntheticObject& o = s.objects[i];
    CorrectedObject c;
    c.mesh = o.pred_mesh, c.scale = o.pred_scale, c.R = o.pred_R, c.t = o.pred_t;
    if (o.dof == PoseDof::Free) {
      // Diagnose with the measured (or oracle) displacement and apply the chosen correction.
      const Displacement d = i < displacements.size() ? displacements[i] : oracle_displacement(s, o);
      const Obb obb = object_obb(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t, g);
      const Diagnosis dg = diagnose(obb, g, d.dt_pen, d.dt_grv, config);
      c.branch = dg.branch, c.rho = dg.rho, c.eta = dg.eta;
      if (dg.branch == Branch::Stretch || proxy == ResampleProxy::Stretch) {
        const StretchResult r = gravity_axis_stretch(o.pred_mesh.V, o.pred_scale, o.pred_R, o.pred_t, o.pred_R, dg, config);
        c.mesh.V = r.canonical;
        c.scale = r.scale, c.R = r.R, c.t = r.t;
      } else if (proxy == ResampleProxy::Drop) {
        c.t = o.pred_t + d.dt_pen + d.dt_grv;
      }
    }
    after.push_back(std::move(c));
  }
  return evaluate_corrected(s, after);
}

std::vector<CorrectedObject> probe_output_objects(const SyntheticScene& s, const ProbeResult& r) {
  SIMU_CHECK(r.scene.objects.size() == s.objects.size() && r.diagnostics.size() == s.objects.size(),
             "probe_output_objects: the probe result has {} objects ({} diagnostics), the synthetic scene {}",
             r.scene.objects.size(), r.diagnostics.size(), s.objects.size());
  std::vector<CorrectedObject> out;
  for (size_t i = 0; i < s.objects.size(); ++i) {
    const SyntheticObject& o = s.objects[i];
    const SceneObject& so = r.scene.objects[i];
    const Diagnostics& d = r.diagnostics[i];
    SIMU_CHECK(so.id == o.id, "probe_output_objects: object {} is '{}' in the probe result, '{}' in the scene", i,
               so.id, o.id);
    CorrectedObject c;
    const bool has_mesh = i < r.meshes.size() && r.meshes[i].V.rows() > 0;
    if (has_mesh) {
      // The corrected scene as the probe writes it: final pose and scale, the mesh it used.
      c.mesh = r.meshes[i];
      c.scale = so.scale, c.R = so.R, c.t = so.t;
    } else {
      // No usable mesh: the probe left the object out; the input reconstruction where it was.
      c.mesh = o.pred_mesh;
      c.scale = o.pred_scale, c.R = o.pred_R, c.t = o.pred_t;
    }
    c.valid = has_mesh && !d.physics_disabled;
    c.rho = d.diagnosis.rho, c.eta = d.diagnosis.eta;
    c.decided = d.branch == ProbeBranch::Stretch || d.branch == ProbeBranch::Resample;
    c.branch = d.branch == ProbeBranch::Resample ? Branch::Resample : Branch::Stretch;
    c.flags = d.flags;
    out.push_back(std::move(c));
  }
  return out;
}

SceneEvaluation evaluate_probe_output(const SyntheticScene& s, const ProbeResult& r) {
  return evaluate_corrected(s, probe_output_objects(s, r));
}

ResampleFn stretch_resampler(const SyntheticScene& s, const CorrectionConfig& config) {
  return [&s, config](const std::vector<ProbeResampleRequest>& requests) {
    const Vec3 g = s.gravity.normalized();
    std::vector<ProbeResampleResult> results;
    for (const ProbeResampleRequest& q : requests) {
      ProbeResampleResult res;
      try {
        SIMU_CHECK(q.object_index >= 0 && size_t(q.object_index) < s.objects.size(), "object index {} out of range",
                   q.object_index);
        const SyntheticObject& o = s.objects[q.object_index];
        // The input object's OBB and the stretch that turns it into the target B_str (same axes; only
        // the side along gravity differs).
        const Obb obb = object_obb(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t, g);
        const GravityAxis ax = gravity_axis(obb, g);
        const double eta = q.target_obb.extents(ax.index) / ax.length - 1.0;
        const Diagnosis dg = diagnose(obb, g, Vec3::Zero(), eta * ax.length * g, config);
        const StretchResult st = gravity_axis_stretch(o.pred_mesh.V, o.pred_scale, o.pred_R, o.pred_t, o.pred_R, dg, config);
        res.mesh = o.pred_mesh;
        res.mesh.V = st.canonical;
        res.R = st.R;
        res.scale = st.scale;
        res.ok = true;
        res.message = fmt::format("stretch proxy (eta {:.3f})", eta);
      } catch (const std::exception& e) {
        res.ok = false;
        res.message = std::string("stretch proxy: ") + e.what();
      }
      results.push_back(std::move(res));
    }
    return results;
  };
}

}  // namespace simu::physics
