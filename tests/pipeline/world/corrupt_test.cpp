// Point-map corruption: with only the scale bias on, every point is the clean one times the recorded
// factor; the factor follows its clamp; holes remove about their ellipses' area; flying pixels only
// near depth edges; the warp is smooth and bounded; the same seed corrupts the same way.
#include "pipeline/world/corrupt.h"

#include "test_files.h"

#include <gtest/gtest.h>

#include <cmath>

using namespace simu::world;
using simu::testing::error_of;

namespace {
// A 64 x 48 point map: a plane at 2 m with a box at 1 m in the middle (a depth edge around it).
PointMap step_map() {
  PointMap m;
  m.width = 64, m.height = 48;
  m.xyz.resize(size_t(64) * 48 * 3);
  for (int r = 0; r < 48; ++r)
    for (int c = 0; c < 64; ++c) {
      const double z = (r >= 16 && r < 32 && c >= 20 && c < 44) ? 1.0 : 2.0;
      float* p = &m.xyz[(size_t(r) * 64 + c) * 3];
      p[0] = float((c - 32) / 60.0 * z), p[1] = float((r - 24) / 60.0 * z), p[2] = float(z);
    }
  return m;
}
CorruptionConfig only_scale() {
  CorruptionConfig c;
  c.warp_sigma = 0, c.flying_prob = 0, c.holes_min = c.holes_max = 0, c.noise_sigma = 0;
  return c;
}
}  // namespace

TEST(WorldCorrupt, ScaleBias) {
  const PointMap clean = step_map();
  double lo = 1e9, hi = 0;
  for (uint64_t seed = 0; seed < 50; ++seed) {
    CorruptionRecord rec;
    const PointMap out = corrupt_pointmap(clean, only_scale(), seed, &rec);
    lo = std::min(lo, rec.scale), hi = std::max(hi, rec.scale);
    EXPECT_GE(rec.scale, 0.75);
    EXPECT_LE(rec.scale, 1.33);
    for (size_t i = 0; i < clean.xyz.size(); ++i)  // one float rounding of the product: 2^-24 relative
      ASSERT_NEAR(out.xyz[i], clean.xyz[i] * rec.scale, 1.2e-7 * std::abs(clean.xyz[i] * rec.scale));
    EXPECT_EQ(rec.missing_pixels, 0);
    EXPECT_EQ(rec.valid_after, rec.valid_before);
  }
  // log sigma 0.1 over 50 draws: the factors spread (a spread below 5% would mean no bias applied).
  EXPECT_GT(hi - lo, 0.05);
  CorruptionConfig tight = only_scale();
  tight.log_scale_sigma = 5, tight.scale_min = 0.9, tight.scale_max = 1.1;
  CorruptionRecord rec;
  corrupt_pointmap(clean, tight, 3, &rec);
  EXPECT_TRUE(rec.scale == 0.9 || rec.scale == 1.1) << rec.scale;
}

// Holes: missing pixels at most the ellipses' area (plus their boundary pixels), at least one pixel per hole.
TEST(WorldCorrupt, MissingRegions) {
  CorruptionConfig c = only_scale();
  c.holes_min = c.holes_max = 2;
  c.hole_radius_min = c.hole_radius_max = 0.1;  // 4.8 px radius on 48 px
  for (uint64_t seed = 0; seed < 20; ++seed) {
    CorruptionRecord rec;
    const PointMap out = corrupt_pointmap(step_map(), c, seed, &rec);
    const double area = 3.14159265358979 * 4.8 * 4.8, perimeter = 2 * 3.14159265358979 * 4.8;
    // Pixel centres inside an ellipse: its area +- its perimeter (each boundary pixel counts at most once).
    EXPECT_LE(rec.missing_pixels, int64_t(2 * (area + perimeter)));
    EXPECT_GE(rec.missing_pixels, 1);
    int64_t nan = 0;
    for (size_t i = 0; i < size_t(64) * 48; ++i) nan += !out.valid(i);
    EXPECT_EQ(nan, rec.missing_pixels);
    EXPECT_EQ(rec.valid_after, rec.valid_before - rec.missing_pixels);
  }
}

// Flying pixels: only within flying_width of the depth step, with depths between its two sides.
TEST(WorldCorrupt, FlyingPixelsAtEdges) {
  CorruptionConfig c = only_scale();
  c.log_scale_sigma = 0, c.flying_prob = 1.0, c.flying_width = 1;
  CorruptionRecord rec;
  const PointMap clean = step_map();
  const PointMap out = corrupt_pointmap(clean, c, 7, &rec);
  EXPECT_GT(rec.flying_pixels, 0);
  int64_t moved = 0;
  for (int r = 0; r < 48; ++r)
    for (int col = 0; col < 64; ++col) {
      const size_t i = size_t(r) * 64 + col;
      const float z0 = clean.xyz[i * 3 + 2], z1 = out.xyz[i * 3 + 2];
      if (z0 == z1) continue;
      ++moved;
      const bool near_edge = r >= 15 && r <= 32 && col >= 19 && col <= 44;
      EXPECT_TRUE(near_edge) << r << "," << col;
      EXPECT_GE(z1, 1.0f - 1e-6f);
      EXPECT_LE(z1, 2.0f + 1e-6f);
    }
  EXPECT_EQ(moved, rec.flying_pixels);
}

// The warp: smooth (neighbouring pixels' factors differ little), bounded, deterministic.
TEST(WorldCorrupt, WarpSmoothAndSeeded) {
  CorruptionConfig c = only_scale();
  c.log_scale_sigma = 0, c.warp_sigma = 0.03, c.warp_cells = 3;
  const PointMap clean = step_map();
  const PointMap a = corrupt_pointmap(clean, c, 11), b = corrupt_pointmap(clean, c, 11), d = corrupt_pointmap(clean, c, 12);
  EXPECT_EQ(a.xyz, b.xyz);
  EXPECT_NE(a.xyz, d.xyz);
  double max_step = 0, max_dev = 0;
  for (int r = 0; r < 48; ++r)
    for (int col = 1; col < 64; ++col) {
      const size_t i = size_t(r) * 64 + col;
      const double f = a.xyz[i * 3 + 2] / clean.xyz[i * 3 + 2], g = a.xyz[(i - 1) * 3 + 2] / clean.xyz[(i - 1) * 3 + 2];
      max_step = std::max(max_step, std::abs(f - g));
      max_dev = std::max(max_dev, std::abs(f - 1));
    }
  // Catmull-Rom over 3 cells of 64 px: slope <= ~2 * (max grid jump) / 21 px; grid values ~N(0, 0.03)
  // stay below 6 sd = 0.18 with the grid's 36 draws, so a step <= 2 * 0.36 / 21 ~ 0.035 and |w| <= 1.25 * 0.18.
  EXPECT_LT(max_step, 0.035);
  EXPECT_LT(max_dev, 0.23);
  EXPECT_GT(max_dev, 1e-4);
}

TEST(WorldCorrupt, BadConfig) {
  CorruptionConfig c;
  c.scale_min = 2, c.scale_max = 1;
  EXPECT_NE(error_of([&] { corrupt_pointmap(step_map(), c, 0); }).find("scale_min"), std::string::npos);
  PointMap bad = step_map();
  bad.xyz.pop_back();
  EXPECT_NE(error_of([&] { corrupt_pointmap(bad, CorruptionConfig{}, 0); }).find("64x48"), std::string::npos);
}
