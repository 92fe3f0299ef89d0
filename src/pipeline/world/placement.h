// Placing objects at rest in a world scene (scene.cpp's inner steps): supports (the table top, the
// floor), rest orientations, footprints, collision-free positions the camera sees, and occluders put
// in front of target objects to reach a visible fraction.
#pragma once

#include "pipeline/world/rest.h"
#include "pipeline/world/rng.h"
#include "pipeline/world/scene.h"

#include <optional>
#include <vector>

namespace simu::world::detail {

// The table against the back wall: x in [x0, x1], z in [-depth, 0] (wall at z = 0), top at y = -height.
struct Table {
  double x0 = 0, x1 = 0, depth = 0, height = 0;
};

// An instance in a rest orientation: its vertices relative to t and its horizontal footprint disc.
struct Oriented {
  Rest rest = Rest::Stand;
  Mat3 R = Mat3::Identity();
  physics::Mesh offsets;       // R (scale .* c): world vertices minus t
  double lowest = 0;           // max y of the offsets (the contact height below t)
  double wall_reach = 0;       // max z of the offsets
  double contact_z = 0;        // z of the lowest vertex (lean: where it stands on the floor / table)
  Eigen::Vector2d centre = Eigen::Vector2d::Zero();  // footprint disc centre (x, z) relative to t
  double radius = 0;
};

// A placed object's footprint: support (floor or table) and disc in world (x, z).
struct Footprint {
  bool floor = false;
  Eigen::Vector2d centre = Eigen::Vector2d::Zero();
  double radius = 0;
};

// A random rest orientation of inst with its rest analysis (weights from cfg over the modes the
// instance allows; lean only for families that can). nullopt when it has no stable facet at all.
std::optional<Oriented> orient(const ShapeInstance& inst, const RestAnalysis& a, const SceneConfig& cfg, Rng& rng);
// The same with a fixed mode; nullopt when the instance has no such pose.
std::optional<Oriented> orient_as(const ShapeInstance& inst, const RestAnalysis& a, Rest rest, Rng& rng);

// Tries to place an oriented instance on a support at a random position the camera sees, free of the
// given footprints; returns its t and footprint. `floor`: the floor (else the table top).
std::optional<std::pair<Vec3, Footprint>> place_on_support(const Oriented& o, bool floor, const Table& table,
                                                           const physics::Camera& cam,
                                                           const std::vector<Footprint>& taken, Rng& rng,
                                                           int attempts);
// Whether an oriented instance at t fits on its support free of `taken` and is seen by the camera:
// whole_in_view, its world AABB's corners project into the image (2% margin); else its centre does.
bool footprint_ok(const Oriented& o, const Vec3& t, bool floor, const Table& table, const physics::Camera& cam,
                  const std::vector<Footprint>& taken, bool whole_in_view = true);

// The world position of an object whose footprint centre is at (x, z) on the support.
Vec3 position_at(const Oriented& o, double x, double z, bool floor, const Table& table);

// A random instance of the split from the families (sizes above max_size_m redrawn, at most 8 times).
ShapeInstance draw_instance(const std::vector<std::string>& families, Split split, const SceneConfig& cfg, Rng& rng);
// Appends an object at pose (o, t) to the scene (id "obj<k>_<family or external name>").
void add_object(WorldScene& s, ShapeInstance inst, const Oriented& o, const Vec3& t, bool floor);

// occlusion.cpp: puts an occluder between the camera and object `ti` (footprint taken[ti]) so that a
// visible fraction near `goal` (and within cfg's [visible_min, visible_max]) of it stays visible: a new
// instance of the split, standing (or lying) on the same support in front of the target along the
// line of sight, shifted sideways by a bisection on the visible fraction. Appends it (and its
// footprint) and returns true; false when no instance fits within 12 draws.
bool place_occluder(WorldScene& s, int ti, double goal, const std::vector<std::string>& families, Split split,
                    const SceneConfig& cfg, const Table& table, std::vector<Footprint>& taken, Rng& rng);

}  // namespace simu::world::detail
