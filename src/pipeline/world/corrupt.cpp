// Monocular-estimator-like corruption of a point map.
#include "pipeline/world/corrupt.h"

#include "common/error.h"
#include "pipeline/world/rng.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace simu::world {

bool PointMap::valid(size_t i) const {
  return std::isfinite(xyz[i * 3]) && std::isfinite(xyz[i * 3 + 1]) && std::isfinite(xyz[i * 3 + 2]) && xyz[i * 3 + 2] > 0;
}

CorruptionConfig CorruptionConfig::from(simu::config::Reader& r) {
  CorruptionConfig c;
  r.field("log_scale_sigma", c.log_scale_sigma);
  r.field("scale_min", c.scale_min);
  r.field("scale_max", c.scale_max);
  r.field("warp_sigma", c.warp_sigma);
  r.field("warp_cells", c.warp_cells);
  r.field("edge_jump", c.edge_jump);
  r.field("flying_width", c.flying_width);
  r.field("flying_prob", c.flying_prob);
  r.field("holes_min", c.holes_min);
  r.field("holes_max", c.holes_max);
  r.field("hole_radius_min", c.hole_radius_min);
  r.field("hole_radius_max", c.hole_radius_max);
  r.field("noise_sigma", c.noise_sigma);
  r.finish();
  return c;
}

namespace {

void validate(const CorruptionConfig& c) {
  auto bad = [](const char* key, const char* why) {
    throw Error(fmt::format("corruption config: {} {}", key, why), "fix the corruption settings");
  };
  if (!(c.log_scale_sigma >= 0)) bad("log_scale_sigma", "must be >= 0");
  if (!(c.scale_min > 0 && c.scale_max >= c.scale_min)) bad("scale_min/scale_max", "must satisfy 0 < min <= max");
  if (!(c.warp_sigma >= 0 && c.warp_sigma < 0.5)) bad("warp_sigma", "must be in [0, 0.5)");
  if (c.warp_cells < 1 || c.warp_cells > 64) bad("warp_cells", "must be in [1, 64]");
  if (!(c.edge_jump > 0)) bad("edge_jump", "must be > 0");
  if (c.flying_width < 0 || c.flying_width > 8) bad("flying_width", "must be in [0, 8]");
  if (!(c.flying_prob >= 0 && c.flying_prob <= 1)) bad("flying_prob", "must be in [0, 1]");
  if (c.holes_min < 0 || c.holes_max < c.holes_min || c.holes_max > 100) bad("holes_min/holes_max", "must satisfy 0 <= min <= max <= 100");
  if (!(c.hole_radius_min >= 0 && c.hole_radius_max >= c.hole_radius_min && c.hole_radius_max <= 1))
    bad("hole_radius_min/max", "must satisfy 0 <= min <= max <= 1");
  if (!(c.noise_sigma >= 0 && c.noise_sigma < 0.2)) bad("noise_sigma", "must be in [0, 0.2)");
}

// Catmull-Rom weights of the four samples around fraction t.
void cubic_weights(double t, double w[4]) {
  const double t2 = t * t, t3 = t2 * t;
  w[0] = 0.5 * (-t3 + 2 * t2 - t);
  w[1] = 0.5 * (3 * t3 - 5 * t2 + 2);
  w[2] = 0.5 * (-3 * t3 + 4 * t2 + t);
  w[3] = 0.5 * (t3 - t2);
}

// Multiplies pixel i's point by f (it stays on its ray).
void scale_point(std::vector<float>& xyz, size_t i, double f) {
  for (int k = 0; k < 3; ++k) xyz[i * 3 + k] = float(xyz[i * 3 + k] * f);
}

}  // namespace

PointMap corrupt_pointmap(const PointMap& clean, const CorruptionConfig& cfg, uint64_t seed, CorruptionRecord* record) {
  validate(cfg);
  const int W = clean.width, H = clean.height;
  SIMU_CHECK(W > 0 && H > 0 && clean.xyz.size() == size_t(W) * H * 3, "corrupt_pointmap: point map {}x{} holds {} floats, expected {}",
             W, H, clean.xyz.size(), size_t(W) * H * 3);
  Rng rng(hash_key("corrupt", seed));
  PointMap out = clean;
  const size_t N = size_t(W) * H;
  CorruptionRecord rec;
  for (size_t i = 0; i < N; ++i) rec.valid_before += clean.valid(i);
  // 1. Low-frequency warp: bicubic interpolation of a (cells + 3)^2 grid (one sample beyond each side).
  const int G = cfg.warp_cells + 3;
  std::vector<double> grid(size_t(G) * G);
  for (auto& g : grid) g = cfg.warp_sigma * rng.normal();
  for (int r = 0; r < H; ++r) {
    const double gy = (r + 0.5) / H * cfg.warp_cells;
    const int iy = std::min(int(gy), cfg.warp_cells - 1);
    double wy[4];
    cubic_weights(gy - iy, wy);
    for (int c = 0; c < W; ++c) {
      const size_t i = size_t(r) * W + c;
      if (!clean.valid(i)) continue;
      const double gx = (c + 0.5) / W * cfg.warp_cells;
      const int ix = std::min(int(gx), cfg.warp_cells - 1);
      double wx[4];
      cubic_weights(gx - ix, wx);
      double w = 0;
      for (int a = 0; a < 4; ++a)
        for (int b = 0; b < 4; ++b) w += wy[a] * wx[b] * grid[size_t(iy + a) * G + (ix + b)];
      scale_point(out.xyz, i, 1.0 + w);
    }
  }
  // 2. Flying pixels near depth edges: a point between the nearest and farthest depth around it.
  if (cfg.flying_width > 0 && cfg.flying_prob > 0) {
    const std::vector<float> warped = out.xyz;
    auto z_of = [&](size_t i) { return double(warped[i * 3 + 2]); };
    const int F = cfg.flying_width;
    for (int r = 0; r < H; ++r)
      for (int c = 0; c < W; ++c) {
        const size_t i = size_t(r) * W + c;
        if (!out.valid(i)) continue;
        double zmin = z_of(i), zmax = zmin;
        for (int dr = -F; dr <= F; ++dr)
          for (int dc = -F; dc <= F; ++dc) {
            const int rr = r + dr, cc = c + dc;
            if (rr < 0 || rr >= H || cc < 0 || cc >= W) continue;
            const size_t j = size_t(rr) * W + cc;
            if (!clean.valid(j)) continue;
            zmin = std::min(zmin, z_of(j)), zmax = std::max(zmax, z_of(j));
          }
        if ((zmax - zmin) / zmin <= cfg.edge_jump) continue;
        // The draw happens for every edge pixel (a fixed number of draws per edge pixel).
        const double u = rng.unit(), mix = rng.unit();
        if (u >= cfg.flying_prob) continue;
        scale_point(out.xyz, i, (zmin + mix * (zmax - zmin)) / z_of(i));
        ++rec.flying_pixels;
      }
  }
  // 3. Missing regions: rotated ellipses.
  const int holes = cfg.holes_min + rng.below(cfg.holes_max - cfg.holes_min + 1);
  const double side = std::min(W, H);
  for (int h = 0; h < holes; ++h) {
    const double cx = rng.uniform(0, W), cy = rng.uniform(0, H);
    const double ra = rng.uniform(cfg.hole_radius_min, cfg.hole_radius_max) * side;
    const double rb = rng.uniform(cfg.hole_radius_min, cfg.hole_radius_max) * side;
    const double th = rng.uniform(0, 3.14159265358979323846), ct = std::cos(th), st = std::sin(th);
    const int r0 = std::max(0, int(cy - std::max(ra, rb)) - 1), r1 = std::min(H - 1, int(cy + std::max(ra, rb)) + 1);
    const int c0 = std::max(0, int(cx - std::max(ra, rb)) - 1), c1 = std::min(W - 1, int(cx + std::max(ra, rb)) + 1);
    for (int r = r0; r <= r1; ++r)
      for (int c = c0; c <= c1; ++c) {
        const double dx = c - cx, dy = r - cy, a = (ct * dx + st * dy) / std::max(ra, 1e-9), b = (-st * dx + ct * dy) / std::max(rb, 1e-9);
        if (a * a + b * b > 1) continue;
        const size_t i = size_t(r) * W + c;
        if (out.valid(i)) ++rec.missing_pixels;
        for (int k = 0; k < 3; ++k) out.xyz[i * 3 + k] = std::numeric_limits<float>::quiet_NaN();
      }
  }
  // 4. Global scale bias, 5. per-pixel depth noise.
  rec.scale = std::clamp(std::exp(cfg.log_scale_sigma * rng.normal()), cfg.scale_min, cfg.scale_max);
  for (size_t i = 0; i < N; ++i) {
    const double noise = cfg.noise_sigma > 0 ? cfg.noise_sigma * rng.normal() : 0.0;
    if (!out.valid(i)) continue;
    scale_point(out.xyz, i, rec.scale * (1.0 + noise));
  }
  for (size_t i = 0; i < N; ++i) rec.valid_after += out.valid(i);
  if (record) *record = rec;
  return out;
}

}  // namespace simu::world
