// Collision geometry of the probe: convex decomposition of a canonical mesh (CoACD's C library
// from its PyPI wheel when built with it, else one convex hull), re-hulled with qhull so every part
// is a closed, outward-wound convex mesh; flat/tiny parts filtered; results cached per mesh
// content; mass and inertia from the hulls by the divergence theorem.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "pipeline/physics/scene.h"

namespace simu::physics {

struct CollisionConfig {
  bool use_coacd = true;         // false (or built without CoACD): one convex hull per mesh
  double threshold = 0.05;       // CoACD concavity threshold (canonical units)
  int max_hulls = 12;            // CoACD max_convex_hull (-1 = unlimited)
  int resolution = 1000;         // CoACD sampling resolution
  int mcts_iterations = 60;      // CoACD MCTS iterations
  int mcts_nodes = 20;
  int mcts_depth = 3;
  int max_hull_vertices = 64;    // CoACD per-hull vertex cap (decimation)
  int seed = 0;
  double min_thickness = 2e-3;   // canonical units: thinner hulls are dropped (flat) ...
  double min_volume_fraction = 1e-4;  // ... as are hulls below this fraction of the total volume
  // Shortcut: a closed, consistently wound mesh whose volume is within this fraction of its convex
  // hull's is convex and becomes its own single hull (no decomposition). < 0 disables it.
  double convex_tolerance = 1e-3;
  // Meshes decomposed in parallel by the probe (0 = one thread per hardware core; CoACD itself
  // runs one mesh at a time and uses OpenMP inside: OMP_NUM_THREADS limits it).
  int threads = 0;
  std::string cache_dir;         // "" = in-memory cache only
};

// A convex part: a closed triangle mesh wound outward.
struct CollisionShape {
  std::vector<Mesh> hulls;  // canonical frame
  std::string method;       // "convex" (the mesh is its own hull), "coacd", "hull", "hull+thickened"
  int dropped = 0;          // hulls filtered as flat or tiny
};

// Convex hull of points with qhull; faces wound outward. Throws simu::Error for fewer than 4
// non-coplanar points.
Mesh convex_hull(const Eigen::Matrix<double, -1, 3, Eigen::RowMajor>& points);

// Decomposes a canonical mesh into convex hulls (cached by mesh content and config, on disk when
// cfg.cache_dir is set, always in memory). Never returns zero hulls: a flat mesh is thickened to
// cfg.min_thickness. Throws simu::Error for an unusable mesh (mesh_problem()).
CollisionShape decompose(const Mesh& canonical, const CollisionConfig& cfg = {});

// True when every edge of the mesh is shared by exactly two faces traversing it in opposite
// directions (closed and consistently wound).
bool is_closed_oriented(const Mesh& mesh);

// The collision shape of `after` when it is an affine image (x -> A x + b, fitted to the vertices;
// same vertex order) of `before`, whose shape is given: every hull mapped and re-hulled, no new
// decomposition (a convex part stays convex under an affine map). nullopt when `after` is not such
// an image or a mapped hull comes out flatter than cfg.min_thickness.
std::optional<CollisionShape> map_shape(const Mesh& before, const Mesh& after, const CollisionShape& shape,
                                        const CollisionConfig& cfg = {});

// Mass properties of a solid of uniform density bounded by closed outward-wound meshes.
struct MassProps {
  double volume = 0;
  double mass = 0;
  Vec3 com = Vec3::Zero();
  Mat3 inertia = Mat3::Zero();  // about the centre of mass, in the meshes' frame
};
MassProps mass_properties(const std::vector<Mesh>& closed_meshes, double density);

// Applies x -> linear * x to every hull (e.g. the object's per-axis scale).
std::vector<Mesh> transform_hulls(const std::vector<Mesh>& hulls, const Mat3& linear);

}  // namespace simu::physics
