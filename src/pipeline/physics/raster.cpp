// Z-buffer triangle rasteriser (pixel-centre sampling, near-plane clipping, perspective-correct z).
#include "pipeline/physics/raster.h"

#include "common/error.h"
#include "pipeline/physics/camera.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>

namespace simu::physics {

int64_t BinaryMask::count() const {
  int64_t n = 0;
  for (uint8_t v : data) n += v != 0;
  return n;
}

void BinaryMask::unite(const BinaryMask& other) {
  SIMU_CHECK(other.width == width && other.height == height, "mask union: size {}x{} vs {}x{}", other.width,
             other.height, width, height);
  for (size_t i = 0; i < data.size(); ++i) data[i] = (data[i] || other.data[i]) ? 1 : 0;
}

std::array<int, 4> BinaryMask::bbox() const {
  std::array<int, 4> b{-1, -1, -1, -1};
  for (int r = 0; r < height; ++r)
    for (int c = 0; c < width; ++c)
      if (at(r, c)) {
        if (b[0] < 0) b = {c, r, c, r};
        b[0] = std::min(b[0], c), b[1] = std::min(b[1], r), b[2] = std::max(b[2], c), b[3] = std::max(b[3], r);
      }
  return b;
}

BinaryMask LabelImage::mask_of(int index) const {
  BinaryMask m(width, height);
  for (size_t i = 0; i < label.size(); ++i) m.data[i] = label[i] == index ? 1 : 0;
  return m;
}

namespace {

// Calls fn(pixel_index, z) for every pixel centre covered by the camera-frame triangle.
template <class Fn>
void raster_triangle(const Camera& cam, const Vec3 (&tri)[3], double near, Fn&& fn) {
  // Clip the polygon against z >= near (Sutherland-Hodgman with one plane).
  Vec3 poly[4];
  int n = 0;
  for (int i = 0; i < 3; ++i) {
    const Vec3& a = tri[i];
    const Vec3& b = tri[(i + 1) % 3];
    const bool ina = a.z() >= near, inb = b.z() >= near;
    if (ina) poly[n++] = a;
    if (ina != inb) {
      const double s = (near - a.z()) / (b.z() - a.z());
      poly[n++] = a + s * (b - a);
    }
  }
  if (n < 3) return;
  // Fan-triangulate and scan each piece over the pixel centres of its bounding box.
  for (int k = 1; k + 1 < n; ++k) {
    const Vec3* P[3] = {&poly[0], &poly[k], &poly[k + 1]};
    double u[3], v[3], iz[3];
    for (int j = 0; j < 3; ++j) {
      const Projection q = project_camera(cam, *P[j]);
      u[j] = q.u, v[j] = q.v, iz[j] = 1.0 / q.z;
    }
    const double area = (u[1] - u[0]) * (v[2] - v[0]) - (v[1] - v[0]) * (u[2] - u[0]);
    if (!(std::abs(area) > 1e-12) || !std::isfinite(area)) continue;
    const int c0 = std::max(0, int(std::ceil(std::min({u[0], u[1], u[2]}))));
    const int c1 = std::min(cam.width - 1, int(std::floor(std::max({u[0], u[1], u[2]}))));
    const int r0 = std::max(0, int(std::ceil(std::min({v[0], v[1], v[2]}))));
    const int r1 = std::min(cam.height - 1, int(std::floor(std::max({v[0], v[1], v[2]}))));
    const double inv = 1.0 / area;
    for (int r = r0; r <= r1; ++r)
      for (int c = c0; c <= c1; ++c) {
        // Barycentric weights of the pixel centre (c, r) from the edge functions.
        const double w0 = ((u[1] - c) * (v[2] - r) - (v[1] - r) * (u[2] - c)) * inv;
        const double w1 = ((u[2] - c) * (v[0] - r) - (v[2] - r) * (u[0] - c)) * inv;
        const double w2 = 1.0 - w0 - w1;
        const double eps = -1e-12;
        if (w0 < eps || w1 < eps || w2 < eps) continue;
        const double z = 1.0 / (w0 * iz[0] + w1 * iz[1] + w2 * iz[2]);
        fn(size_t(r) * cam.width + c, z);
      }
  }
}

// Camera-frame triangles of a world mesh, fn(tri, face index) for each valid face.
template <class Fn>
void for_each_camera_triangle(const Camera& cam, const Mesh& m, Fn&& fn) {
  std::vector<Vec3> pc(m.V.rows());
  for (Eigen::Index i = 0; i < m.V.rows(); ++i) pc[i] = world_to_camera(cam, m.V.row(i).transpose());
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    Vec3 tri[3];
    bool ok = true;
    for (int j = 0; j < 3; ++j) {
      const int idx = m.F(f, j);
      if (idx < 0 || idx >= m.V.rows() || !pc[idx].allFinite()) { ok = false; break; }
      tri[j] = pc[idx];
    }
    if (ok) fn(tri, f);
  }
}

void check_camera(const Camera& cam) {
  SIMU_CHECK(cam.width > 0 && cam.height > 0 && cam.fx > 0 && cam.fy > 0,
             "raster: invalid camera (fx {}, fy {}, size {}x{})", cam.fx, cam.fy, cam.width, cam.height);
}

}  // namespace

LabelImage render_labels(const Camera& cam, const std::vector<const Mesh*>& meshes, double near) {
  return std::move(render_faces(cam, meshes, near).labels);
}

ShadedImage render_shaded(const Camera& cam, const std::vector<const Mesh*>& meshes, double ambient, double near) {
  check_camera(cam);
  ShadedImage img;
  LabelImage& L = img.labels;
  L.width = cam.width, L.height = cam.height;
  L.label.assign(size_t(cam.width) * cam.height, -1);
  L.depth.assign(L.label.size(), std::numeric_limits<float>::infinity());
  img.shade.assign(L.label.size(), 0.f);
  std::vector<double> zbuf(L.label.size(), std::numeric_limits<double>::infinity());
  for (size_t k = 0; k < meshes.size(); ++k) {
    if (!meshes[k] || meshes[k]->empty()) continue;
    for_each_camera_triangle(cam, *meshes[k], [&](const Vec3(&tri)[3], Eigen::Index) {
      // Headlight: brightness from the angle between the face normal and the ray to its centre.
      const Vec3 n = (tri[1] - tri[0]).cross(tri[2] - tri[0]);
      const Vec3 ray = (tri[0] + tri[1] + tri[2]) / 3.0;
      const double cosang = n.norm() > 0 && ray.norm() > 0 ? std::abs(n.normalized().dot(ray.normalized())) : 0.0;
      const float shade = float(ambient + (1.0 - ambient) * cosang);
      raster_triangle(cam, tri, near, [&](size_t i, double z) {
        if (z < zbuf[i]) zbuf[i] = z, L.label[i] = int32_t(k), L.depth[i] = float(z), img.shade[i] = shade;
      });
    });
  }
  return img;
}

FaceImage render_faces(const Camera& cam, const std::vector<const Mesh*>& meshes, double near) {
  check_camera(cam);
  FaceImage img;
  LabelImage& L = img.labels;
  L.width = cam.width, L.height = cam.height;
  L.label.assign(size_t(cam.width) * cam.height, -1);
  L.depth.assign(L.label.size(), std::numeric_limits<float>::infinity());
  img.face.assign(L.label.size(), -1);
  std::vector<double> zbuf(L.label.size(), std::numeric_limits<double>::infinity());
  for (size_t k = 0; k < meshes.size(); ++k) {
    if (!meshes[k] || meshes[k]->empty()) continue;
    for_each_camera_triangle(cam, *meshes[k], [&](const Vec3(&tri)[3], Eigen::Index f) {
      raster_triangle(cam, tri, near, [&](size_t i, double z) {
        if (z < zbuf[i]) zbuf[i] = z, L.label[i] = int32_t(k), L.depth[i] = float(z), img.face[i] = int32_t(f);
      });
    });
  }
  return img;
}

BinaryMask render_silhouette(const Camera& cam, const Mesh& m, double near) {
  check_camera(cam);
  BinaryMask mask(cam.width, cam.height);
  for_each_camera_triangle(cam, m, [&](const Vec3(&tri)[3], Eigen::Index) {
    raster_triangle(cam, tri, near, [&](size_t i, double) { mask.data[i] = 1; });
  });
  return mask;
}

BinaryMask auxiliary_crop_mask(const Camera& cam, const BinaryMask& modal, const Diagnosis& d,
                               const CorrectionConfig& config) {
  check_camera(cam);
  SIMU_CHECK(modal.width == cam.width && modal.height == cam.height,
             "auxiliary_crop_mask: modal mask is {}x{}, camera image is {}x{}", modal.width, modal.height, cam.width,
             cam.height);
  BinaryMask out = modal;
  if (auto slab = lowest_part(d, config)) out.unite(render_silhouette(cam, slab->to_mesh()));
  return out;
}

}  // namespace simu::physics
