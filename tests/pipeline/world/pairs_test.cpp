// Preference pairs from world scenes (pipeline/world/pairs.h): corrupted masks keep to their kind
// (erode and cut stay inside the mask, a shift moves its centroid), differ from the mask and are seeded;
// planned completion pairs are 20-60% visible behind objects and at least 90% visible once their
// occluders are removed, preservation pairs are unoccluded and off the border.
#include "pipeline/world/pairs.h"

#include "test_files.h"

#include <gtest/gtest.h>

#include <cmath>
#include <set>

using namespace simu::world;
using simu::physics::BinaryMask;
using simu::testing::error_of;

namespace {
// A filled disc of radius r at (cx, cy) in a w x h mask.
BinaryMask disc(int w, int h, double cx, double cy, double r) {
  BinaryMask m(w, h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      if ((x - cx) * (x - cx) + (y - cy) * (y - cy) <= r * r) m.at(y, x) = 1;
  return m;
}
// Mean pixel position.
std::pair<double, double> centroid(const BinaryMask& m) {
  double sx = 0, sy = 0, n = 0;
  for (int y = 0; y < m.height; ++y)
    for (int x = 0; x < m.width; ++x)
      if (m.at(y, x)) sx += x, sy += y, ++n;
  return {sx / n, sy / n};
}
bool inside(const BinaryMask& a, const BinaryMask& b) {
  for (size_t i = 0; i < a.data.size(); ++i)
    if (a.data[i] && !b.data[i]) return false;
  return true;
}
}  // namespace

TEST(WorldPairs, CorruptMaskKinds) {
  const BinaryMask m = disc(80, 60, 40, 30, 15);
  const int64_t area = m.count();
  std::set<std::string> seen;
  for (uint64_t seed = 0; seed < 40; ++seed) {
    std::string how;
    const BinaryMask c = corrupt_mask(m, seed, &how);
    seen.insert(how);
    ASSERT_GT(c.count(), 0) << how;
    EXPECT_NE(c.data, m.data) << how;
    if (how == "erode" || how == "cut") EXPECT_TRUE(inside(c, m)) << how << " seed " << seed;
    // A cut keeps 50-75% of the area; one pixel row of the line either way.
    if (how == "cut") {
      const double kept = double(c.count()) / double(area);
      EXPECT_GE(kept, 0.5 - 0.05) << seed;
      EXPECT_LE(kept, 0.75 + 0.05) << seed;
    }
    // Erosion by r = round(0.08 sqrt(area)) pixels shrinks a disc of radius 15 to about radius 15 - r.
    if (how == "erode") {
      const int r = std::max(1, int(std::lround(0.08 * std::sqrt(double(area)))));
      EXPECT_NEAR(std::sqrt(double(c.count()) / M_PI), 15.0 - r, 1.0) << seed;
    }
    // A shift by 15-30% of the 31-pixel box moves the centroid 4.6-9.3 pixels (rounding: +-1).
    if (how == "shift") {
      const auto [x0, y0] = centroid(m);
      const auto [x1, y1] = centroid(c);
      const double d = std::hypot(x1 - x0, y1 - y0);
      EXPECT_GE(d, 0.15 * 31 - 1.0) << seed;
      EXPECT_LE(d, 0.30 * 31 + 1.0) << seed;
    }
    // Seeded: the same seed, the same mask.
    EXPECT_EQ(corrupt_mask(m, seed).data, c.data);
  }
  EXPECT_EQ(seen, (std::set<std::string>{"cut", "erode", "shift"}));
  EXPECT_NE(error_of([] { corrupt_mask(BinaryMask(8, 8), 0); }).find("empty"), std::string::npos);
}

TEST(WorldPairs, PlannedPairsFollowTheRules) {
  SceneConfig cfg;
  cfg.targets = 1;
  PairPlanConfig pc;
  int completion = 0, preservation = 0;
  for (uint64_t from = 0; completion < 3 || preservation < 3; ++from) {
    ASSERT_LT(from, 40u) << "40 train scenes gave " << completion << " completion / " << preservation << " preservation pairs";
    const uint64_t seed = next_scene_seed(Split::Train, from * 1000);
    const WorldScene s = make_scene(cfg, seed, Split::Train);
    for (const auto& p : plan_pairs(s, pc, seed)) {
      const WorldObject& o = s.objects[size_t(p.object)];
      EXPECT_GE(o.modal_pixels, pc.min_pixels);
      if (p.completion) {
        ++completion;
        EXPECT_GE(o.visible_fraction, pc.completion_min);
        EXPECT_LE(o.visible_fraction, pc.completion_max);
        EXPECT_FALSE(o.occluders.empty());
        // The edited scene: the occluders gone, the object (nearly) whole, the full mask covers the modal one.
        EXPECT_EQ(p.edited.removed, o.occluders);
        EXPECT_GE(p.edited.objects[size_t(p.object)].visible_fraction, pc.full_min);
        EXPECT_TRUE(inside(o.modal, p.full_mask));
        EXPECT_GT(p.full_mask.count(), o.modal.count());
      } else {
        ++preservation;
        EXPECT_TRUE(o.occluders.empty());
        EXPECT_GE(o.visible_fraction, pc.preserve_min);
        EXPECT_GT(p.corrupted.count(), 0);
        EXPECT_NE(p.corrupted.data, o.modal.data);
      }
    }
  }
}
