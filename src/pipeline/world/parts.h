// Building blocks of the shape families (families.cpp): closed parts (boxes, surfaces of revolution,
// hollow vessels, torus arcs, prisms) placed by rigid transforms and merged into one mesh. Every part
// is a closed, outward-wound component; a merged mesh is a union of such components (they may
// interpenetrate: a mug's handle enters its wall), which voxelize_filled fills as the union of solids.
#pragma once

#include "pipeline/physics/scene.h"

#include <utility>
#include <vector>

namespace simu::world {

using physics::Mat3;
using physics::Mesh;
using physics::Vec3;

// Rotation by angle (radians) about an axis.
Mat3 rotation(double angle, const Vec3& axis);
// x -> R x + t applied to every vertex.
Mesh transformed(Mesh m, const Mat3& R, const Vec3& t);
// x -> s .* x applied to every vertex (s > 0 per axis keeps the winding).
Mesh scaled(Mesh m, const Vec3& s);
// Concatenates meshes (face indices offset).
Mesh merge(const std::vector<Mesh>& parts);
// Flips the faces of a closed component whose signed volume is negative (so every part winds outward
// whatever its builder's orientation).
Mesh outward(Mesh m);

// An axis-aligned box of full extents e centred at c.
Mesh box_part(const Vec3& extents, const Vec3& centre = Vec3::Zero());
// A solid of revolution about y (physics::revolve_mesh) from (y, radius) points, top first.
Mesh revolve_part(const std::vector<std::pair<double, double>>& y_radius, int segments);
// A hollow vessel about y (bowl, cup, mug body): the outer profile (y, radius) runs from the bottom
// centre's ring up to the rim (y decreasing: up is -y); the inside is the outer surface moved in by
// `wall` (radially) and its floor up by `floor` (along -y). Closed: the rim joins inside and outside.
Mesh vessel_part(const std::vector<std::pair<double, double>>& outer_bottom_to_rim, double wall, double floor,
                 int segments);
// A torus (arc) about y: centre-line radius R in the xz plane, tube radius r, from angle a0 to a1
// (radians, from +x towards +z); a partial arc is closed by flat caps at its ends.
Mesh torus_part(double R, double r, double a0, double a1, int major_segments, int minor_segments);
// A cylinder of radius r between points a and b (capped).
Mesh rod_part(const Vec3& a, const Vec3& b, double r, int segments);

}  // namespace simu::world
