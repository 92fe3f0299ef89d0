// Pinhole camera projection helpers.
#include "pipeline/physics/camera.h"

namespace simu::physics {

Vec3 world_to_camera(const Camera& cam, const Vec3& p_world) {
  return cam.R_world_cam.transpose() * (p_world - cam.t_world_cam);
}

Vec3 camera_to_world(const Camera& cam, const Vec3& p_cam) { return cam.R_world_cam * p_cam + cam.t_world_cam; }

Projection project_camera(const Camera& cam, const Vec3& p) {
  Projection q;
  q.z = p.z();
  const double iz = p.z() != 0 ? 1.0 / p.z() : 0.0;
  q.u = cam.fx * p.x() * iz + cam.cx;
  q.v = cam.fy * p.y() * iz + cam.cy;
  return q;
}

Projection project(const Camera& cam, const Vec3& p_world) { return project_camera(cam, world_to_camera(cam, p_world)); }

Vec3 pixel_ray_camera(const Camera& cam, double u, double v) {
  return Vec3((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0);
}

Vec3 unproject(const Camera& cam, double u, double v, double z) {
  return camera_to_world(cam, pixel_ray_camera(cam, u, v) * z);
}

}  // namespace simu::physics
