// Point-map corruption the way a monocular estimator (MoGe) errs, for training on realistic inputs and
// evaluating clean vs corrupted depth side by side. Applied in this order, all seeded:
//   1. smooth low-frequency warp: depth along each pixel's ray times (1 + w(u, v)), w a bicubic
//      interpolation of a (warp_cells + 1)^2 grid of N(0, warp_sigma) values (points stay on their rays);
//   2. flying pixels: pixels within flying_width of a depth edge (relative jump > edge_jump) become,
//      with probability flying_prob, a point between the near and far side (uniform mix along the ray);
//   3. missing regions: elliptical holes (count in [holes_min, holes_max], radii a fraction
//      hole_radius_min..max of the image's shorter side) set to NaN, plus the invalid pixels kept;
//   4. global scale bias: every point times s = exp(N(0, log_scale_sigma)) clamped to [scale_min,
//      scale_max] (MoGe's scale is relative; a metric-scale estimator still errs by ~10%);
//   5. per-pixel depth noise: depth times (1 + N(0, noise_sigma)).
#pragma once

#include "common/config.h"

#include <cstdint>
#include <vector>

namespace simu::world {

// A point map [H, W, 3] float32, row-major, OpenCV camera (x right, y down, z forward); NaN (or inf)
// components mark invalid pixels.
struct PointMap {
  int width = 0, height = 0;
  std::vector<float> xyz;  // [H, W, 3]
  bool valid(size_t pixel) const;
};

struct CorruptionConfig {
  double log_scale_sigma = 0.1;              // global scale bias (log space)
  double scale_min = 0.75, scale_max = 1.33;
  double warp_sigma = 0.03;                  // relative depth warp amplitude
  int warp_cells = 3;                        // warp grid cells across the image (low frequency)
  double edge_jump = 0.05;                   // relative depth jump that makes an edge
  int flying_width = 1;                      // pixels either side of an edge
  double flying_prob = 0.5;
  int holes_min = 0, holes_max = 3;          // missing elliptical regions
  double hole_radius_min = 0.02, hole_radius_max = 0.08;  // fraction of min(H, W)
  double noise_sigma = 0.003;                // per-pixel relative depth noise
  static CorruptionConfig from(simu::config::Reader& r);
};

// What corrupt_pointmap did (for tests and gt.json).
struct CorruptionRecord {
  double scale = 1;               // the global scale factor applied
  int64_t flying_pixels = 0;      // pixels moved between edge sides
  int64_t missing_pixels = 0;     // valid pixels set invalid by the holes
  int64_t valid_before = 0, valid_after = 0;
};

// The corrupted copy of a clean point map (deterministic from seed). Throws simu::Error on a size
// mismatch or a bad config (negative sigma, scale_min > scale_max, holes_min > holes_max, ...).
PointMap corrupt_pointmap(const PointMap& clean, const CorruptionConfig& config, uint64_t seed,
                          CorruptionRecord* record = nullptr);

}  // namespace simu::world
