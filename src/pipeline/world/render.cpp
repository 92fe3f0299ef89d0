// Rendering a world scene: one z-buffer pass for labels, depth and face ids (physics::render_faces),
// Lambert shading of per-object albedo under a directional light (with a shadow map) plus ambient, a faint tile pattern
// on floor and wall, amodal silhouettes, visible fractions and occluders.
#include "pipeline/world/scene.h"

#include "common/error.h"
#include "pipeline/physics/camera.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace simu::world {

namespace {

// Unit face normals of a mesh.
std::vector<Vec3> face_normals(const physics::Mesh& m) {
  std::vector<Vec3> n(size_t(m.F.rows()));
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    const Vec3 a = m.V.row(m.F(f, 0)), b = m.V.row(m.F(f, 1)), c = m.V.row(m.F(f, 2));
    const Vec3 x = (b - a).cross(c - a);
    n[size_t(f)] = x.norm() > 0 ? Vec3(x.normalized()) : Vec3::Zero();
  }
  return n;
}

// A shadow map of the directional light: the casters seen from far along -light_dir (a narrow
// perspective view 30 m away stands in for an orthographic one), size x size texels over a square of
// half_width metres around centre.
struct ShadowMap {
  physics::Camera cam;
  std::vector<float> depth;
  double bias = 0;

  ShadowMap(const Vec3& light_dir, const Vec3& centre, double half_width, int size,
            const std::vector<const physics::Mesh*>& casters) {
    const double dist = 30.0;
    const Vec3 fwd = light_dir.normalized();
    const Vec3 hint = std::abs(fwd.z()) < 0.9 ? Vec3::UnitZ() : Vec3::UnitX();
    const Vec3 right = hint.cross(fwd).normalized(), down = fwd.cross(right);
    cam.width = cam.height = size;
    cam.fx = cam.fy = 0.5 * size * dist / half_width;
    cam.cx = cam.cy = 0.5 * size;
    cam.R_world_cam.col(0) = right, cam.R_world_cam.col(1) = down, cam.R_world_cam.col(2) = fwd;
    cam.t_world_cam = centre - dist * fwd;
    depth = physics::render_labels(cam, casters).depth;
    const double texel = 2.0 * half_width / size;
    bias = 1.5 * texel + 0.002;  // 1.5 texels of slope plus 2 mm
    normal_offset = 1.5 * texel;  // lookups start off the surface along its normal (no acne on grazing faces)
  }
  double normal_offset = 0;
  // Fraction of the 3 x 3 texels around the world point that see it lit (percentage-closer filtering).
  double lit(const Vec3& pw) const {
    const physics::Projection q = physics::project(cam, pw);
    const int c = int(std::floor(q.u + 0.5)), r = int(std::floor(q.v + 0.5));
    double sum = 0;
    for (int dr = -1; dr <= 1; ++dr)
      for (int dc = -1; dc <= 1; ++dc) {
        const int rr = r + dr, cc = c + dc;
        const bool blocked = rr >= 0 && rr < cam.height && cc >= 0 && cc < cam.width &&
                             depth[size_t(rr) * cam.width + cc] < q.z - bias;
        sum += blocked ? 0.0 : 1.0;
      }
    return sum / 9.0;
  }
};

// Linear [0, 1] -> 8-bit sRGB-like (gamma 2.2), through a 4096-entry table.
uint8_t encode(double x) {
  static const std::vector<uint8_t> table = [] {
    std::vector<uint8_t> t(4097);
    for (int i = 0; i <= 4096; ++i) t[size_t(i)] = uint8_t(std::lround(255.0 * std::pow(i / 4096.0, 1.0 / 2.2)));
    return t;
  }();
  return table[size_t(std::clamp(x, 0.0, 1.0) * 4096.0 + 0.5)];
}

}  // namespace

void render_scene(WorldScene& s) {
  const physics::Camera& cam = s.camera;
  SIMU_CHECK(cam.valid(), "render_scene: scene {} has an invalid camera", s.name);
  const int W = cam.width, H = cam.height;
  const size_t N = size_t(W) * H;
  std::vector<bool> removed(s.objects.size(), false);
  for (int i : s.removed) removed.at(size_t(i)) = true;
  // World meshes: environment first (labels 1..3), then the objects present.
  std::vector<physics::Mesh> world(s.objects.size());
  std::vector<const physics::Mesh*> ptrs;
  for (const auto& e : s.environment) ptrs.push_back(&e);
  for (size_t i = 0; i < s.objects.size(); ++i) {
    if (!removed[i]) world[i] = object_world_mesh(s.objects[i]);
    ptrs.push_back(removed[i] ? nullptr : &world[i]);
  }
  const physics::FaceImage img = physics::render_faces(cam, ptrs);
  std::vector<std::vector<Vec3>> normals(ptrs.size());
  for (size_t k = 0; k < ptrs.size(); ++k)
    if (ptrs[k]) normals[k] = face_normals(*ptrs[k]);
  const size_t n_env = s.environment.size();
  // Shadows cast by the objects present and the table (environment index 2) over 2 m around the objects.
  std::vector<const physics::Mesh*> casters;
  Vec3 centre = Vec3::Zero();
  int present = 0;
  for (size_t k = 2; k < ptrs.size(); ++k)
    if (ptrs[k]) casters.push_back(ptrs[k]);
  for (const auto& o : s.objects) centre += o.t, ++present;  // removed ones too: the same map for an edited render
  if (present > 0) centre /= present;
  const ShadowMap shadow(s.light_dir, centre, 2.0, 512, casters);
  // Per pixel: label, depth, point, shade.
  s.labels.assign(N, 0);
  s.depth = img.labels.depth;
  s.rgb.assign(N * 3, 0);
  s.pointmap.width = W, s.pointmap.height = H;
  s.pointmap.xyz.assign(N * 3, std::numeric_limits<float>::quiet_NaN());
  const Vec3 eye = physics::camera_center(cam);
  for (int r = 0; r < H; ++r)
    for (int c = 0; c < W; ++c) {
      const size_t i = size_t(r) * W + c;
      const int k = img.labels.label[i];
      if (k < 0) continue;
      s.labels[i] = k < int(n_env) ? k + 1 : kFirstObjectLabel + (k - int(n_env));
      const double z = s.depth[i];
      const Vec3 pc((c - cam.cx) / cam.fx * z, (r - cam.cy) / cam.fy * z, z);
      s.pointmap.xyz[i * 3 + 0] = float(pc.x()), s.pointmap.xyz[i * 3 + 1] = float(pc.y()), s.pointmap.xyz[i * 3 + 2] = float(pc.z());
      // Lambert: the face normal turned towards the viewer (closed or not), light from -light_dir.
      const Vec3 pw = physics::camera_to_world(cam, pc);
      Vec3 n = normals[size_t(k)][size_t(img.face[i])];
      if (n.dot(eye - pw) < 0) n = -n;
      const double lambert = std::max(0.0, -n.dot(s.light_dir));
      const double direct = lambert > 0 ? lambert * shadow.lit(pw + shadow.normal_offset * n) : 0.0;
      Vec3 albedo = k < int(n_env) ? s.environment_albedo[size_t(k)] : s.objects[size_t(k - int(n_env))].shape.albedo;
      if (k < 2) {
        // Floor boards / wall tiles: a faint brightness pattern from the world position.
        const double u = k == 0 ? pw.x() / 0.25 : pw.x() / 0.5, v = k == 0 ? pw.z() / 1.2 : pw.y() / 0.5;
        const double tile = (int(std::floor(u)) + int(std::floor(v + 0.5 * std::floor(u)))) & 1;
        albedo *= 0.93 + 0.07 * tile;
      }
      const Vec3 lit = albedo * (s.ambient + s.light * direct);
      for (int ch = 0; ch < 3; ++ch) s.rgb[i * 3 + ch] = encode(lit[ch]);
    }
  // Per object: modal (its label), amodal (silhouette alone), visible fraction, occluders.
  for (size_t i = 0; i < s.objects.size(); ++i) {
    WorldObject& o = s.objects[i];
    o.label = kFirstObjectLabel + int(i);
    o.modal = physics::BinaryMask(W, H);
    o.occluders.clear();
    o.occluded_by_table = false;
    if (removed[i]) {
      o.amodal = physics::BinaryMask(W, H);
      o.modal_pixels = o.amodal_pixels = 0, o.visible_fraction = 0, o.usable = false;
      continue;
    }
    o.amodal = physics::render_silhouette(cam, world[i]);
    std::vector<bool> occ(s.objects.size(), false);
    int64_t modal = 0, amodal = 0;
    // Only the pixels of the projected vertices' bounding box can be set (all vertices in front).
    int r0 = 0, r1 = H - 1, c0 = 0, c1 = W - 1;
    if ((world[i].V.rowwise() - cam.t_world_cam.transpose()).operator*(cam.R_world_cam).col(2).minCoeff() > 1e-3) {
      double u0 = 1e300, u1 = -1e300, v0 = 1e300, v1 = -1e300;
      for (Eigen::Index k = 0; k < world[i].V.rows(); ++k) {
        const physics::Projection q = physics::project(cam, world[i].V.row(k).transpose());
        u0 = std::min(u0, q.u), u1 = std::max(u1, q.u), v0 = std::min(v0, q.v), v1 = std::max(v1, q.v);
      }
      c0 = std::max(0, int(std::floor(u0))), c1 = std::min(W - 1, int(std::ceil(u1)));
      r0 = std::max(0, int(std::floor(v0))), r1 = std::min(H - 1, int(std::ceil(v1)));
    }
    for (int r = r0; r <= r1; ++r)
      for (int c = c0; c <= c1; ++c) {
      const size_t p = size_t(r) * W + c;
      if (!o.amodal.data[p]) continue;
      ++amodal;
      const int l = s.labels[p];
      if (l == o.label) {
        o.modal.data[p] = 1, ++modal;
      } else if (l >= kFirstObjectLabel) {
        occ[size_t(l - kFirstObjectLabel)] = true;
      } else if (l == kLabelTable) {
        o.occluded_by_table = true;
      }
      }
    for (size_t j = 0; j < occ.size(); ++j)
      if (occ[j]) o.occluders.push_back(int(j));
    o.modal_pixels = modal, o.amodal_pixels = amodal;
    o.visible_fraction = amodal > 0 ? double(modal) / double(amodal) : 0.0;
    o.usable = modal >= s.min_pixels && o.visible_fraction >= s.min_visible;
  }
  // Camera-frame poses.
  const Mat3 Rcw = cam.R_world_cam.transpose();
  for (auto& o : s.objects) o.R_cam = Rcw * o.R, o.t_cam = Rcw * (o.t - cam.t_world_cam);
}

}  // namespace simu::world
