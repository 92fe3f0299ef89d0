// The family table behind shapes.h: per family its size range, whether it may lean on a wall, and
// its mesh builder (any units, y-down with -y up; make_shape normalises).
#pragma once

#include "pipeline/world/parts.h"
#include "pipeline/world/rng.h"

#include <string>
#include <vector>

namespace simu::world {

struct FamilySpec {
  std::string name;
  double size_min = 0.02, size_max = 0.6;  // longest metric side (m), drawn log-uniformly
  bool can_lean = false;                   // stands with a straight bottom edge: may lean on the wall
  Mesh (*build)(Rng&) = nullptr;           // random proportions from the rng
};

// Every family, in families() order.
const std::vector<FamilySpec>& family_specs();
// The spec of a family; throws simu::Error naming it (with the list) when unknown.
const FamilySpec& family_spec(const std::string& name);

}  // namespace simu::world
