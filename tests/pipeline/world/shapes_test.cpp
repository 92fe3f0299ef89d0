// Shape world instances and splits: every family's canonical mesh follows SAM 3D's convention (AABB
// centred, longest side 1) and is closed and outward-wound, instances are deterministic from their
// seed, sizes lie in 2..60 cm, splits follow the 80/10/10 hash and keep the held-out family out of
// train and val, external meshes are normalised and their units guessed.
#include "pipeline/world/shapes.h"

#include "pipeline/physics/collision.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/world/families.h"

#include "test_files.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <set>

using namespace simu::world;
using simu::testing::error_of;

// At least 10 families, the held-out one among them.
TEST(WorldShapes, Families) {
  EXPECT_GE(families().size(), 10u);
  EXPECT_TRUE(is_family(held_out_family()));
  EXPECT_FALSE(is_family("teapot"));
  for (Split sp : {Split::Train, Split::Val, Split::Test}) {
    const auto f = split_families(sp);
    EXPECT_EQ(f.size(), families().size() - 1);
    EXPECT_EQ(std::count(f.begin(), f.end(), held_out_family()), 0);
  }
  EXPECT_NE(error_of([] { make_shape("teapot", 1); }).find("unknown family 'teapot'"), std::string::npos);
}

// Canonical convention, closedness, outward winding, sizes and colours, 8 instances per family.
TEST(WorldShapes, CanonicalClosedAndSized) {
  for (const auto& f : families()) {
    const FamilySpec& spec = family_spec(f);
    for (uint64_t seed = 0; seed < 8; ++seed) {
      const ShapeInstance s = make_shape(f, seed);
      SCOPED_TRACE(s.name);
      const Vec3 lo = s.mesh.V.colwise().minCoeff().transpose(), hi = s.mesh.V.colwise().maxCoeff().transpose();
      // (v - centre) / longest: each coordinate carries at most a few ulps of 0.5 (2^-53 ~ 1.1e-16 each):
      // 4e-16 bounds the sum of the two bounds' rounding and the division's.
      EXPECT_LE((lo + hi).cwiseAbs().maxCoeff(), 4e-16);
      EXPECT_NEAR((hi - lo).maxCoeff(), 1.0, 4e-16);
      EXPECT_TRUE(s.closed);
      EXPECT_TRUE(simu::physics::is_closed_oriented(s.mesh));
      EXPECT_GT(simu::physics::signed_volume(s.mesh), 0.0);
      EXPECT_GE(s.size_m, spec.size_min);
      EXPECT_LE(s.size_m, spec.size_max);
      EXPECT_GE(s.size_m, 0.02);
      EXPECT_LE(s.size_m, 0.6);
      EXPECT_GE(s.albedo.minCoeff(), 0.0);
      EXPECT_LE(s.albedo.maxCoeff(), 1.0);
      EXPECT_EQ(s.family, f);
      EXPECT_EQ(s.id, instance_id(f, seed));
      EXPECT_EQ(s.split, instance_split(f, seed));
    }
  }
}

// Same seed: bit-identical instance; another seed: other proportions.
TEST(WorldShapes, Deterministic) {
  for (const auto& f : families()) {
    const ShapeInstance a = make_shape(f, 42), b = make_shape(f, 42), c = make_shape(f, 43);
    ASSERT_EQ(a.mesh.V.rows(), b.mesh.V.rows());
    EXPECT_TRUE(a.mesh.V == b.mesh.V) << f;
    EXPECT_TRUE(a.mesh.F == b.mesh.F) << f;
    EXPECT_EQ(a.size_m, b.size_m);
    EXPECT_TRUE(a.albedo == b.albedo);
    EXPECT_NE(a.size_m, c.size_m) << f;
  }
}

// The instance hash splits 80 / 10 / 10; the held-out family is test only.
TEST(WorldShapes, Splits) {
  const int n = 20000;
  int count[3] = {0, 0, 0};
  for (uint64_t s = 0; s < uint64_t(n); ++s) ++count[int(instance_split("box", s))];
  // Binomial counts: sd sqrt(n p (1 - p)) = 57 (p 0.8) and 42 (p 0.1); 5 sd ~ 290 / 210.
  EXPECT_NEAR(count[0], 0.8 * n, 290);
  EXPECT_NEAR(count[1], 0.1 * n, 210);
  EXPECT_NEAR(count[2], 0.1 * n, 210);
  for (uint64_t s = 0; s < 200; ++s) EXPECT_EQ(instance_split(held_out_family(), s), Split::Test);
  EXPECT_TRUE(make_shape(held_out_family(), 3).held_out);
  EXPECT_NE(error_of([] { next_instance_seed(held_out_family(), Split::Train, 0); }).find("held-out"), std::string::npos);
  for (Split sp : {Split::Train, Split::Val, Split::Test}) {
    const uint64_t s = next_instance_seed("cone", sp, 1000);
    EXPECT_GE(s, 1000u);
    EXPECT_EQ(instance_split("cone", s), sp);
    for (uint64_t k = 1000; k < s; ++k) EXPECT_NE(instance_split("cone", k), sp);
    const uint64_t q = next_scene_seed(sp, 77);
    EXPECT_EQ(scene_split_of(q), sp);
  }
  // Scene seeds split independently of instance seeds (the two hashes use different salts).
  int same = 0;
  for (uint64_t s = 0; s < 2000; ++s) same += scene_split_of(s) == split_of(s);
  EXPECT_LT(same, 1900);
  EXPECT_EQ(parse_split("val"), Split::Val);
  EXPECT_NE(error_of([] { parse_split("dev", "--split"); }).find("--split: unknown split 'dev'"), std::string::npos);
}

// An external mesh in millimetres: canonical, its size read in metres.
TEST(WorldShapes, ExternalUnits) {
  const simu::physics::Mesh mm = simu::physics::box_mesh(Vec3(50, 25, 10));  // 100 x 50 x 20 mm
  const ShapeInstance s = make_external_shape(mm, "brick");
  EXPECT_NEAR(s.size_m, 0.1, 1e-12);
  EXPECT_EQ(s.split, Split::Test);
  EXPECT_TRUE(s.held_out);
  EXPECT_TRUE(s.closed);
  EXPECT_NEAR((s.mesh.V.colwise().maxCoeff() - s.mesh.V.colwise().minCoeff()).maxCoeff(), 1.0, 1e-15);
  EXPECT_EQ(make_external_shape(mm, "brick", 0.3).size_m, 0.3);
  // 80 km read in m, cm or mm is no plausible size: clamped to 60 cm.
  EXPECT_EQ(make_external_shape(simu::physics::box_mesh(Vec3(4e4, 1, 1)), "huge").size_m, 0.6);
}
