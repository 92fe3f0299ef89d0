// Pinhole projection through the scene camera (scene.h Camera: OpenCV axes x right, y down,
// z forward; p_world = R_world_cam p_cam + t_world_cam).
//
// Pixel convention (OpenCV): pixel (col, row) has its centre at (u, v) = (col, row) and covers
// [col - 0.5, col + 0.5) x [row - 0.5, row + 0.5). u = fx x / z + cx, v = fy y / z + cy.
#pragma once

#include "pipeline/physics/scene.h"

namespace simu::physics {

// A world point projected into the image: pixel coordinates and depth z along the optical axis.
struct Projection {
  double u = 0, v = 0;  // pixel coordinates (centre of pixel (c, r) is (c, r))
  double z = 0;         // camera-frame depth (metres); <= 0 means behind the camera
  bool in_front() const { return z > 0; }
};

// World -> camera frame.
Vec3 world_to_camera(const Camera& cam, const Vec3& p_world);
// Camera frame -> world.
Vec3 camera_to_world(const Camera& cam, const Vec3& p_cam);
// Projects a camera-frame point (z must be > 0 for a meaningful u, v).
Projection project_camera(const Camera& cam, const Vec3& p_cam);
// Projects a world point.
Projection project(const Camera& cam, const Vec3& p_world);
// The camera-frame ray direction (z = 1) through pixel coordinates (u, v).
Vec3 pixel_ray_camera(const Camera& cam, double u, double v);
// The world point at depth z on the ray through pixel coordinates (u, v).
Vec3 unproject(const Camera& cam, double u, double v, double z);
// The camera centre in the world.
inline Vec3 camera_center(const Camera& cam) { return cam.t_world_cam; }

}  // namespace simu::physics
