// Stable rest orientations of an object on a horizontal support (world y down), from its convex hull:
// a hull facet can be put down when the centre of mass projects onto it along its normal with a
// margin (quasi-static rest, the object then rests on that facet's plane); the chance of landing on a
// facet is taken as its solid angle seen from the centre of mass (a dropped object's quasi-static
// estimate). "Stand" is the stable facet facing canonical +y (the canonical bottom).
#pragma once

#include "pipeline/physics/scene.h"

#include <vector>

namespace simu::world {

using physics::Mat3;
using physics::Mesh;
using physics::Vec3;

struct RestFace {
  Vec3 normal = Vec3::UnitY();  // outward facet normal, canonical frame (the direction put down)
  double solid_angle = 0;       // of the facet seen from the centre of mass (all facets sum to 4 pi)
  double margin = 0;            // distance of the projected centre of mass to the facet's boundary (canonical units)
  double com_height = 0;        // distance of the centre of mass above the facet's plane
  bool stable = false;          // margin >= max(min_margin, tip_ratio * com_height)
};

struct RestAnalysis {
  Vec3 com = Vec3::Zero();      // centre of mass (canonical): the closed mesh's solid, else its hull's
  std::vector<RestFace> faces;  // one per hull facet (coplanar hull triangles joined)
  int stand = -1;               // the stable facet whose normal is closest to +y when within 25 degrees; -1 none
};

// Analyses a canonical mesh (closed: the centre of mass of its solid; else of its hull). The margin
// thresholds are in canonical units (longest side 1). Throws simu::Error for a flat mesh (no hull).
RestAnalysis analyse_rest(const Mesh& canonical, bool closed, double min_margin = 0.01, double tip_ratio = 0.08);

// The smallest rotation taking the canonical direction n to world down (+y).
Mat3 put_down(const Vec3& n);

// Picks a stable facet other than `exclude` with probability proportional to its solid angle from
// u in [0, 1); -1 when there is none.
int pick_face(const RestAnalysis& a, double u, int exclude = -1);

}  // namespace simu::world
