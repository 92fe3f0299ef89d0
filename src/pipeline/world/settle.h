// A short MuJoCo settle of a world scene through the probe's world (physics::evaluate_physics): the
// floor and the wall as planes, the table as a static box, every object free under gravity with one
// convex hull as its collider (the same hull the analytic rest poses come from). Used to check that
// rest poses are at rest, and (SceneConfig::settle) to let the physics place them.
#pragma once

#include "pipeline/world/scene.h"

#include <vector>

namespace simu::world {

struct SettleReport {
  bool ran = false;                   // false without MuJoCo (SIMU_HAVE_MUJOCO) or when nothing could settle
  std::vector<double> displacement;   // per object: |t_after - t_before| (m); 0 for removed objects
  std::vector<double> rotation_deg;   // per object: angle of R_after R_before^T
  std::vector<bool> simulated;        // per object: took part (false: removed, or the probe disabled it)
  double seconds = 0;                 // wall time
  std::string message;                // why it did not run, when it did not
};

// Settles s.objects (minus s.removed) for `seconds` of simulated time (it stops early once nothing
// moves by 0.1 mm over 0.25 s); with apply, the objects take their settled poses (the render is not
// redone: call render_scene). Meshes go through a temporary folder, removed afterwards.
SettleReport settle_scene(WorldScene& s, double seconds, bool apply);

}  // namespace simu::world
