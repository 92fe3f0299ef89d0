// Plain geometry types of the reconstruct front end (torch-free, Eigen only).
//
// Frame: every function of src/pipeline/reconstruct works in the OpenCV camera frame of the photo (x right,
// y down, z forward, metres). The scene handed to the probe uses this frame as its world frame
// (Camera::R_world_cam = I) with gravity = -up, up from the plane step (docs/reconstruct.md).
//
// Pose convention (the same as the probe's scene.h): world = R * (s .* c) + t for a canonical vertex c
// (AABB-centred, longest side 1). The alignment and tabletop steps change an isotropic factor of s.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

#include <string>
#include <vector>

namespace simu::reconstruct {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
// Row-major [n, 3] point set (the layout of physics::Mesh::V).
using Points = Eigen::Matrix<double, -1, 3, Eigen::RowMajor>;
// Row-major [m, 3] triangle vertex indices (the layout of physics::Mesh::F).
using Faces = Eigen::Matrix<int, -1, 3, Eigen::RowMajor>;

// Pinhole intrinsics and image size (OpenCV: pixel (c, r) has its centre at (u, v) = (c, r)).
struct Pinhole {
  double fx = 0, fy = 0, cx = 0, cy = 0;
  int width = 0, height = 0;
  bool valid() const { return fx > 0 && fy > 0 && width > 0 && height > 0; }
};

// A binary mask, row-major, non-zero = inside.
struct Mask {
  int width = 0, height = 0;
  std::vector<uint8_t> data;
  Mask() = default;
  Mask(int w, int h) : width(w), height(h), data(size_t(w) * size_t(h), 0) {}
  uint8_t at(int r, int c) const { return data[size_t(r) * width + c]; }
  uint8_t& at(int r, int c) { return data[size_t(r) * width + c]; }
  int64_t count() const;
};

// A point map [H, W] of camera-frame points (row-major); NaN = invalid.
struct PointMap {
  int width = 0, height = 0;
  std::vector<Vec3> p;
  const Vec3& at(int r, int c) const { return p[size_t(r) * width + c]; }
  static bool valid(const Vec3& x) { return x.allFinite() && x.z() > 0; }
};

// The valid points of `map` under `mask` (same size; throws simu::Error otherwise).
Points masked_points(const PointMap& map, const Mask& mask, const std::string& what);

// A plane {x : n.(x - point) = 0}; n unit, pointing into free space (up for the floor, into the room
// for a wall).
struct PlaneFit {
  Vec3 point = Vec3::Zero();
  Vec3 normal = Vec3::UnitZ();
  int64_t inliers = 0;    // RANSAC inlier count (the coverage of a wall)
  double rms = 0;         // RMS inlier residual (m)
  double distance(const Vec3& x) const { return normal.dot(x - point); }
};

// A similarity transform x -> s * R * x + t.
struct Similarity {
  double s = 1;
  Mat3 R = Mat3::Identity();
  Vec3 t = Vec3::Zero();
  Vec3 apply(const Vec3& x) const { return s * (R * x) + t; }
};

// Applies a similarity to every row.
Points transform(const Points& P, const Similarity& T);
// Places canonical vertices with an object pose: R * (s .* c) + t.
Points place(const Points& canonical, const Vec3& scale, const Mat3& R, const Vec3& t);

// Deterministic subsample of at most `max_n` rows (evenly strided); all rows when max_n <= 0.
Points subsample(const Points& P, int64_t max_n);

// Splits every triangle edge longer than max_edge (midpoint subdivision, repeated) so that vertex-based
// losses see a dense surface, as marching-cubes meshes are. Shared edges stay watertight.
void densify(Points& V, Faces& F, double max_edge);

}  // namespace simu::reconstruct
