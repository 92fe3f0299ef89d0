// Triangle mesh files (OBJ, PLY, GLB/glTF, STL through assimp) and small mesh utilities.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "pipeline/physics/scene.h"

namespace simu::physics {

// Reads every triangle of a mesh file (node transforms baked in, polygons triangulated, identical
// vertices joined). Throws simu::Error naming the file when it is missing or unreadable, has no
// vertices or no triangles, a non-finite vertex or a face index outside its vertex array. A PLY file's
// header is checked first (formats, types, counts against the file size): assimp 5.2 hangs on some.
Mesh read_mesh(const std::string& path);
// Writes a mesh atomically; the format follows the extension (.obj, .ply, .glb, .gltf, .stl).
void write_mesh(const Mesh& mesh, const std::string& path);

// Axis-aligned bounds of the vertices (min, max); zeros for an empty mesh.
struct Aabb {
  Vec3 min = Vec3::Zero();
  Vec3 max = Vec3::Zero();
  Vec3 center() const { return 0.5 * (min + max); }
  Vec3 size() const { return max - min; }
};
Aabb mesh_aabb(const Mesh& mesh);

// Problems that make a mesh unusable for simulation ("" when none): no vertices or faces,
// non-finite coordinates, face indices out of range, zero extent.
std::string mesh_problem(const Mesh& mesh);
// Drops faces with repeated indices or zero area (below area_eps) and unreferenced vertices.
Mesh clean_mesh(const Mesh& mesh, double area_eps = 1e-14);
// Moves the AABB centre to the origin and scales the longest side to 1 (SAM3D canonical frame).
// Returns the factor applied (new = (old - centre) * factor).
double canonicalize(Mesh& mesh);
// Number of undirected edges shared by more than two faces (non-manifold edges; open boundaries,
// used by one face, are not counted).
int nonmanifold_edges(const Mesh& mesh);
// Signed volume by the divergence theorem (positive for outward-wound closed meshes).
double signed_volume(const Mesh& mesh);
// An axis-aligned box mesh with the given half extents centred at the origin (outward winding).
Mesh box_mesh(const Vec3& half_extents);
// A closed prism: a simple counter-clockwise polygon in the xy plane (star-shaped about its first
// vertex) extruded over z in [-half_height, half_height], wound outward.
Mesh prism_mesh(const std::vector<Eigen::Vector2d>& polygon, double half_height);
// A planar quadrilateral a, b, c, d as two triangles (a, b, c), (a, c, d) (floors and walls of pictures).
Mesh quad_mesh(const Vec3& a, const Vec3& b, const Vec3& c, const Vec3& d);
// A closed surface of revolution about the y axis from a profile of (y, radius) pairs: a polyline
// from one end to the other, drawn from the top (smaller y; the world is y-down) down the outside. An
// end with radius 0 is a pole on the axis; an end with radius > 0 is closed by a flat cap around a
// centre vertex; interior radii must be > 0. Faces wind outward, also for hollow shapes whose profile
// runs from an inner pole up the inside, over the rim and down the outside (a bowl). Vertex 0 is the
// top centre / pole, then one ring of `segments` vertices per non-pole profile point (ring vertex i at
// angle 2 pi i / segments from +x towards +z), then the bottom centre / pole. Throws simu::Error for
// fewer than 2 points, segments < 3, a negative or non-finite value or an interior radius of 0.
Mesh revolve_mesh(const std::vector<std::pair<double, double>>& y_radius, int segments);
// 64-bit FNV-1a hash of bytes (used to key caches by mesh content).
uint64_t fnv1a64(const void* data, size_t n, uint64_t seed = 1469598103934665603ULL);
uint64_t mesh_hash(const Mesh& mesh);

}  // namespace simu::physics
