// Preference pairs from world scenes: which objects qualify, and corrupted masks (pairs.h).
#include "pipeline/world/pairs.h"

#include "common/error.h"
#include "pipeline/world/rng.h"

#include <algorithm>
#include <cmath>

namespace simu::world {

namespace {

using physics::BinaryMask;

// Pixels within r (4-neighbour steps) of the background or the image edge removed.
BinaryMask erode(const BinaryMask& m, int r) {
  BinaryMask cur = m;
  for (int it = 0; it < r; ++it) {
    BinaryMask next = cur;
    for (int y = 0; y < m.height; ++y)
      for (int x = 0; x < m.width; ++x) {
        if (!cur.at(y, x)) continue;
        const bool edge = y == 0 || x == 0 || y == m.height - 1 || x == m.width - 1 || !cur.at(y - 1, x) ||
                          !cur.at(y + 1, x) || !cur.at(y, x - 1) || !cur.at(y, x + 1);
        if (edge) next.at(y, x) = 0;
      }
    cur = std::move(next);
  }
  return cur;
}

// The pixels whose projection on (cos a, sin a) is at least the q-quantile of the mask's projections.
BinaryMask cut(const BinaryMask& m, double angle, double q) {
  const double cx = std::cos(angle), cy = std::sin(angle);
  std::vector<double> proj;
  for (int y = 0; y < m.height; ++y)
    for (int x = 0; x < m.width; ++x)
      if (m.at(y, x)) proj.push_back(cx * x + cy * y);
  std::vector<double> sorted = proj;
  const size_t k = std::min(sorted.size() - 1, static_cast<size_t>(q * static_cast<double>(sorted.size())));
  std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(k), sorted.end());
  const double thr = sorted[k];
  BinaryMask out(m.width, m.height);
  for (int y = 0; y < m.height; ++y)
    for (int x = 0; x < m.width; ++x)
      if (m.at(y, x) && cx * x + cy * y >= thr) out.at(y, x) = 1;
  return out;
}

BinaryMask shift(const BinaryMask& m, int dx, int dy) {
  BinaryMask out(m.width, m.height);
  for (int y = 0; y < m.height; ++y)
    for (int x = 0; x < m.width; ++x) {
      const int sy = y - dy, sx = x - dx;
      if (sy >= 0 && sx >= 0 && sy < m.height && sx < m.width && m.at(sy, sx)) out.at(y, x) = 1;
    }
  return out;
}

bool touches_border(const BinaryMask& m, int border) {
  for (int y = 0; y < m.height; ++y)
    for (int x = 0; x < m.width; ++x)
      if (m.at(y, x) && (y < border || x < border || y >= m.height - border || x >= m.width - border)) return true;
  return false;
}

}  // namespace

BinaryMask corrupt_mask(const BinaryMask& mask, uint64_t seed, std::string* how) {
  const int64_t area = mask.count();
  SIMU_CHECK(area > 0, "corrupt_mask: the mask is empty");
  Rng rng(splitmix64(seed ^ 0x6d61736b636f7272ULL));
  const int kind = rng.below(3);
  const double angle = rng.uniform(0, 6.283185307179586);
  const double keep = rng.uniform(0.5, 0.75);
  const double frac = rng.uniform(0.15, 0.30);
  const auto differs = [&](const BinaryMask& b) { return b.count() > 0 && b.data != mask.data; };
  BinaryMask out;
  std::string name;
  if (kind == 0) {
    out = erode(mask, std::max(1, static_cast<int>(std::lround(0.08 * std::sqrt(static_cast<double>(area))))));
    name = "erode";
  } else if (kind == 2) {
    int x0 = mask.width, x1 = -1, y0 = mask.height, y1 = -1;
    for (int y = 0; y < mask.height; ++y)
      for (int x = 0; x < mask.width; ++x)
        if (mask.at(y, x)) x0 = std::min(x0, x), x1 = std::max(x1, x), y0 = std::min(y0, y), y1 = std::max(y1, y);
    const double bw = x1 - x0 + 1, bh = y1 - y0 + 1;
    out = shift(mask, static_cast<int>(std::lround(frac * bw * std::cos(angle))),
                static_cast<int>(std::lround(frac * bh * std::sin(angle))));
    name = "shift";
  }
  if (!differs(out)) {
    // A line cut keeps 1 - q of the area.
    out = cut(mask, angle, 1.0 - keep);
    name = "cut";
  }
  SIMU_CHECK(differs(out), "corrupt_mask: a mask of {} pixels cannot be corrupted", area);
  if (how) *how = name;
  return out;
}

std::vector<PlannedPair> plan_pairs(const WorldScene& s, const PairPlanConfig& c, uint64_t seed) {
  std::vector<PlannedPair> out;
  for (size_t i = 0; i < s.objects.size(); ++i) {
    const WorldObject& o = s.objects[i];
    if (o.modal_pixels < c.min_pixels) continue;
    const bool hidden_by_objects = !o.occluders.empty() && !o.occluded_by_table;
    if (hidden_by_objects && o.visible_fraction >= c.completion_min && o.visible_fraction <= c.completion_max) {
      // Completion: the occluders removed must reveal (nearly) the whole silhouette.
      PlannedPair p;
      p.object = static_cast<int>(i);
      p.completion = true;
      p.edited = render_without(s, o.occluders);
      const WorldObject& e = p.edited.objects[i];
      if (e.visible_fraction < c.full_min || e.modal_pixels < c.min_pixels) continue;
      p.full_mask = e.modal;
      out.push_back(std::move(p));
    } else if (o.occluders.empty() && !o.occluded_by_table && o.visible_fraction >= c.preserve_min &&
               !touches_border(o.modal, c.border)) {
      PlannedPair p;
      p.object = static_cast<int>(i);
      p.corrupted = corrupt_mask(o.modal, seed ^ splitmix64(i + 1), &p.corruption);
      out.push_back(std::move(p));
    }
  }
  return out;
}

}  // namespace simu::world
