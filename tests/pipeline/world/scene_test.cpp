// World scenes: deterministic from (config, seed, split); objects of the split only; masks and visible
// fractions consistent with the label image (visible = modal / amodal pixels, occluders really cover
// the amodal mask); the point map is the depth unprojected through the intrinsics; resting objects
// touch their support (and leaning ones the wall); the edited render removes exactly the chosen
// object; the occlusion knob yields targets in the requested range; extra (external) instances placed.
#include "pipeline/world/scene.h"

#include "pipeline/physics/camera.h"
#include "pipeline/world/parts.h"

#include "test_files.h"

#include <gtest/gtest.h>

#include <cmath>

using namespace simu::world;
using simu::testing::error_of;

namespace {
WorldScene scene(Split sp, uint64_t from, const SceneConfig& cfg = {}) { return make_scene(cfg, next_scene_seed(sp, from), sp); }
}  // namespace

// Same seed, same scene (pixels and poses); another seed, another scene.
TEST(WorldScene, Deterministic) {
  const WorldScene a = scene(Split::Train, 10), b = scene(Split::Train, 10), c = scene(Split::Train, a.seed + 1);
  EXPECT_EQ(a.rgb, b.rgb);
  EXPECT_EQ(a.labels, b.labels);
  ASSERT_EQ(a.objects.size(), b.objects.size());
  for (size_t i = 0; i < a.objects.size(); ++i) {
    EXPECT_TRUE(a.objects[i].R == b.objects[i].R);
    EXPECT_TRUE(a.objects[i].t == b.objects[i].t);
    EXPECT_EQ(a.objects[i].shape.id, b.objects[i].shape.id);
  }
  EXPECT_NE(a.rgb, c.rgb);
  // A seed of another split is refused with the way out.
  const uint64_t test_seed = next_scene_seed(Split::Test, 0);
  const std::string e = error_of([&] { make_scene(SceneConfig{}, test_seed, Split::Train); });
  EXPECT_NE(e.find("belongs to the test split"), std::string::npos) << e;
}

// Objects come from the scene's split; the held-out family only in test scenes that ask for it.
TEST(WorldScene, SplitsAndHeldOut) {
  for (Split sp : {Split::Train, Split::Val, Split::Test})
    for (uint64_t k = 0; k < 3; ++k) {
      const WorldScene s = scene(sp, 100 * k);
      EXPECT_GE(s.objects.size(), 1u);
      for (const auto& o : s.objects) {
        EXPECT_EQ(o.shape.split, sp) << o.id;
        EXPECT_NE(o.shape.family, held_out_family()) << o.id;
      }
    }
  SceneConfig held;
  held.families = {held_out_family()};
  const WorldScene t = scene(Split::Test, 5, held);
  for (const auto& o : t.objects) EXPECT_EQ(o.shape.family, held_out_family());
  const std::string e = error_of([&] { scene(Split::Train, 5, held); });
  EXPECT_NE(e.find("held-out family"), std::string::npos) << e;
}

// Masks, visible fractions, occluders and the point map agree with the label image and the camera.
TEST(WorldScene, MasksAndPointMap) {
  for (uint64_t k = 0; k < 4; ++k) {
    const WorldScene s = scene(Split::Train, 1000 + 37 * k);
    const int W = s.camera.width, H = s.camera.height;
    ASSERT_EQ(s.rgb.size(), size_t(W) * H * 3);
    for (size_t i = 0; i < s.objects.size(); ++i) {
      const WorldObject& o = s.objects[i];
      int64_t modal = 0, amodal = 0;
      for (size_t p = 0; p < size_t(W) * H; ++p) {
        EXPECT_EQ(o.modal.data[p], s.labels[p] == o.label ? 1 : 0);
        ASSERT_TRUE(!o.modal.data[p] || o.amodal.data[p]);  // visible pixels are in the silhouette
        modal += o.modal.data[p], amodal += o.amodal.data[p];
      }
      EXPECT_EQ(modal, o.modal_pixels);
      EXPECT_EQ(amodal, o.amodal_pixels);
      EXPECT_GT(amodal, 0) << o.id;
      EXPECT_DOUBLE_EQ(o.visible_fraction, double(modal) / double(amodal));
      // Each occluder's label covers part of the amodal mask; no other object's does.
      std::vector<int> covering;
      for (size_t j = 0; j < s.objects.size(); ++j) {
        bool covers = false;
        for (size_t p = 0; p < size_t(W) * H && !covers; ++p) covers = o.amodal.data[p] && s.labels[p] == s.objects[j].label && j != i;
        if (covers) covering.push_back(int(j));
      }
      EXPECT_EQ(covering, o.occluders) << o.id;
      // Camera-frame pose = world pose seen from the camera.
      const Vec3 c = o.R_cam * o.scale.cwiseProduct(Vec3(0.3, -0.2, 0.1)) + o.t_cam;
      const Vec3 w = o.R * o.scale.cwiseProduct(Vec3(0.3, -0.2, 0.1)) + o.t;
      EXPECT_LT((simu::physics::camera_to_world(s.camera, c) - w).norm(), 1e-12);
    }
    // Point map: the depth along the pixel's ray through the intrinsics, stored as float (one rounding
    // of the double value: relative 2^-24 ~ 6e-8, so 1.2e-7 relative plus 1e-12 m near zero).
    int64_t bad = 0;
    for (int r = 0; r < H; ++r)
      for (int c = 0; c < W; ++c) {
        const size_t p = size_t(r) * W + c;
        const float* q = &s.pointmap.xyz[p * 3];
        if (!std::isfinite(s.depth[p])) {
          bad += !(std::isnan(q[0]) && std::isnan(q[1]) && std::isnan(q[2]));
          continue;
        }
        const double z = s.depth[p], x = (c - s.camera.cx) / s.camera.fx * z, y = (r - s.camera.cy) / s.camera.fy * z;
        bad += q[2] != s.depth[p] || std::abs(q[0] - x) > 1.2e-7 * std::abs(x) + 1e-12 || std::abs(q[1] - y) > 1.2e-7 * std::abs(y) + 1e-12;
      }
    EXPECT_EQ(bad, 0);
  }
}

// Resting objects touch their support plane; leaning ones also the wall; none below the floor.
TEST(WorldScene, RestContacts) {
  SceneConfig cfg;
  cfg.families = {"box", "cone"};  // one family that can lean, one that cannot
  cfg.w_lean = 30.0;                // boxes lean wherever they can
  int leaning = 0;
  for (uint64_t k = 0; k < 6; ++k) {
    const WorldScene s = scene(Split::Train, 500 + 11 * k, cfg);
    for (const auto& o : s.objects) {
      const Mesh w = object_world_mesh(o);
      const double support = o.on_floor ? s.floor_y : s.table_top_y;
      // Placement puts the lowest vertex exactly on the support (one rounding of the sum: 1e-12 m).
      EXPECT_NEAR(w.V.col(1).maxCoeff(), support, 1e-12) << o.id;
      EXPECT_LE(w.V.col(2).maxCoeff(), s.wall_z + 1e-12) << o.id;
      if (o.rest == Rest::Lean) {
        ++leaning;
        EXPECT_NEAR(w.V.col(2).maxCoeff(), s.wall_z - 0.0005, 1e-9) << o.id;  // 0.5 mm from the wall
      }
    }
  }
  EXPECT_GT(leaning, 0);
}

// The edited image: the removed object's pixels go to what was behind it; every other pixel keeps its
// label and can only get brighter (the removed object's shadow is gone, nothing else changes).
TEST(WorldScene, RenderWithout) {
  const WorldScene s = scene(Split::Train, 300);
  ASSERT_GE(s.objects.size(), 2u);
  const WorldScene e = render_without(s, {0});
  const WorldObject& gone = e.objects[0];
  EXPECT_EQ(gone.modal_pixels, 0);
  EXPECT_FALSE(gone.usable);
  EXPECT_EQ(e.removed, std::vector<int>{0});
  int64_t changed = 0, relabelled = 0, darker = 0, brighter = 0;
  for (size_t p = 0; p < s.labels.size(); ++p) {
    if (s.labels[p] == s.objects[0].label) {
      changed += e.labels[p] != s.objects[0].label;
      continue;
    }
    relabelled += e.labels[p] != s.labels[p];
    for (int ch = 0; ch < 3; ++ch) darker += e.rgb[p * 3 + ch] < s.rgb[p * 3 + ch], brighter += e.rgb[p * 3 + ch] > s.rgb[p * 3 + ch];
  }
  EXPECT_EQ(changed, s.objects[0].modal_pixels);
  EXPECT_EQ(relabelled, 0);
  EXPECT_EQ(darker, 0);
  EXPECT_GE(brighter, 0);
  for (size_t i = 1; i < s.objects.size(); ++i) EXPECT_GE(e.objects[i].visible_fraction, s.objects[i].visible_fraction);
  EXPECT_NE(error_of([&] { render_without(s, {99}); }).find("index 99"), std::string::npos);
}

// Occlusion control: targets with a visible fraction in [0.2, 0.6], each with an occluder.
TEST(WorldScene, OcclusionTargets) {
  SceneConfig cfg;
  cfg.targets = 2;
  int met_scenes = 0;
  const int n = 6;
  for (uint64_t k = 0; k < n; ++k) {
    const WorldScene s = scene(Split::Train, 2000 + 13 * k, cfg);
    int targets = 0;
    for (const auto& o : s.objects) {
      if (!o.target) continue;
      ++targets;
      EXPECT_GE(o.visible_fraction, cfg.visible_min);
      EXPECT_LE(o.visible_fraction, cfg.visible_max);
      EXPECT_TRUE(!o.occluders.empty() || o.occluded_by_table) << o.id;
    }
    met_scenes += targets >= cfg.targets;
  }
  EXPECT_GE(met_scenes, n - 1);
}

// An extra instance (an external mesh) is placed first, at rest, in view.
TEST(WorldScene, ExtraInstance) {
  const ShapeInstance brick = make_external_shape(box_part(Vec3(120, 60, 30)), "brick");
  const WorldScene s = make_scene(SceneConfig{}, next_scene_seed(Split::Test, 0), Split::Test, {brick});
  ASSERT_GE(s.objects.size(), 1u);
  EXPECT_EQ(s.objects[0].shape.name, "brick");
  EXPECT_NEAR(s.objects[0].shape.size_m, 0.12, 1e-12);
  EXPECT_GT(s.objects[0].amodal_pixels, 0);
}
