// Rest poses are at rest: a short MuJoCo settle (the probe's world, one convex hull per object) of
// generated scenes moves no object by more than 1 cm (a fifth of the paper's 5 cm stability
// threshold) and turns none by more than 3 degrees; most move less than 2 mm (contact compliance).
#include "pipeline/world/settle.h"

#include "test_files.h"

#include <gtest/gtest.h>

#include <algorithm>

using namespace simu::world;

TEST(WorldSettle, RestPosesStay) {
#ifndef SIMU_HAVE_MUJOCO
  GTEST_SKIP() << "built without MuJoCo";
#endif
  std::vector<double> moves;
  int lean = 0, lie = 0, stand = 0;
  // Four scenes of every family, three of boxes and cones leaning wherever they can.
  SceneConfig mixed, leaning;
  leaning.families = {"box", "cone"};
  leaning.w_lean = 30.0;
  for (uint64_t k = 0; k < 7; ++k) {
    WorldScene s = make_scene(k < 4 ? mixed : leaning, next_scene_seed(Split::Train, 700 + 29 * k), Split::Train);
    const SettleReport r = settle_scene(s, 0.5, false);
    ASSERT_TRUE(r.ran) << r.message;
    for (size_t i = 0; i < s.objects.size(); ++i) {
      const WorldObject& o = s.objects[i];
      lean += o.rest == Rest::Lean, lie += o.rest == Rest::Lie, stand += o.rest == Rest::Stand;
      EXPECT_TRUE(r.simulated[i]) << s.name << " " << o.id;
      EXPECT_LT(r.displacement[i], 0.01) << s.name << " " << o.id << " " << to_string(o.rest);
      EXPECT_LT(r.rotation_deg[i], 3.0) << s.name << " " << o.id << " " << to_string(o.rest);
      moves.push_back(r.displacement[i]);
    }
  }
  std::sort(moves.begin(), moves.end());
  EXPECT_LT(moves[moves.size() / 2], 0.002);
  EXPECT_GT(stand, 0);
  EXPECT_GT(lie, 0);
  EXPECT_GT(lean, 0);
  fmt::print("settled {} objects (stand {}, lie {}, lean {}): median move {:.2e} m, max {:.2e} m\n", moves.size(), stand, lie,
             lean, moves[moves.size() / 2], moves.back());
}
