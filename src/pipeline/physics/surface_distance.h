// Distances between surfaces for the 3D shape metrics (shape_metrics.h): deterministic area-uniform
// point samples on a triangle mesh, and exact point-to-surface distances through a bounding-volume
// hierarchy over the triangles (the closest point on each triangle, Voronoi regions of its vertices,
// edges and face; Ericson, "Real-Time Collision Detection", 5.1.5).
//
//   SurfaceDistance gt(gt_world);                        // builds the hierarchy once
//   Points p = sample_surface(pred_world, 10000, seed);  // [n, 3]
//   double d = gt.distance(p.row(0).transpose());        // metres to the nearest GT triangle
#pragma once

#include "pipeline/physics/geometry.h"
#include "pipeline/physics/scene.h"

#include <cstdint>
#include <vector>

namespace simu::physics {

// n points distributed uniformly by area over the mesh's triangles (a triangle picked with probability
// proportional to its area, then a uniform point in it: sqrt-barycentric), in a fixed order from `seed`
// (splitmix64-driven, the same on every platform). Degenerate (zero-area) triangles are never picked.
// Throws simu::Error when the mesh has no triangle of positive area or n < 1.
Points sample_surface(const Mesh& mesh, int64_t n, uint64_t seed);

// Total area of the mesh's triangles.
double surface_area(const Mesh& mesh);
// Area-weighted centroid of the surface (the mean of uniform surface samples as n -> infinity).
Vec3 surface_centroid(const Mesh& mesh);

// Closest point of triangle (a, b, c) to p.
Vec3 closest_point_on_triangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c);

// Point-to-surface distance queries against one mesh (thread-safe after construction).
class SurfaceDistance {
 public:
  // Builds the hierarchy (median splits along the longest axis, up to 4 triangles per leaf). Throws
  // simu::Error for a mesh without triangles or with a face index out of range.
  explicit SurfaceDistance(const Mesh& mesh);
  // Euclidean distance from p to the nearest point of any triangle (exact up to rounding).
  double distance(const Vec3& p) const;
  // distance() of every row of points.
  std::vector<double> distances(const Points& points) const;

 private:
  struct Node {
    Eigen::Vector3d lo, hi;  // bounds of the node's triangles
    int left = -1, right = -1;  // children (-1: leaf)
    int first = 0, count = 0;   // leaf: tris_[first, first + count)
  };
  int build(int first, int count, std::vector<Vec3>& centres);
  Mesh mesh_;
  std::vector<int> tris_;   // triangle order of the leaves
  std::vector<Node> nodes_;
};

}  // namespace simu::physics
