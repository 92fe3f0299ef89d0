// Occluders placed in front of target objects to reach a visible fraction (SceneConfig::targets).
#include "pipeline/physics/camera.h"
#include "pipeline/world/parts.h"
#include "pipeline/world/placement.h"

#include <fmt/format.h>

#include <cmath>

namespace simu::world::detail {

ShapeInstance draw_instance(const std::vector<std::string>& fams, Split split, const SceneConfig& cfg, Rng& rng) {
  ShapeInstance inst;
  for (int k = 0; k < 8; ++k) {
    const std::string& f = fams[size_t(rng.below(int(fams.size())))];
    inst = make_shape(f, next_instance_seed(f, split, rng.next()));
    if (inst.size_m <= cfg.max_size_m) break;
  }
  return inst;
}

void add_object(WorldScene& s, ShapeInstance inst, const Oriented& o, const Vec3& t, bool floor) {
  WorldObject w;
  w.id = fmt::format("obj{:02d}_{}", s.objects.size(), inst.family == "external" ? inst.name : inst.family);
  w.shape = std::move(inst);
  w.rest = o.rest;
  w.on_floor = floor;
  w.R = o.R;
  w.scale = w.shape.scale();
  w.t = t;
  s.objects.push_back(std::move(w));
}

namespace {

// The target's amodal mask and the fraction of it an occluder silhouette leaves uncovered, with the
// silhouette shifted by whole pixels (a sideways move of the occluder moves its image about rigidly:
// one silhouette render serves the whole bisection; the final pose is checked exactly).
struct Coverage {
  const physics::BinaryMask& target;
  int64_t target_pixels = 0;
  std::vector<int> rows, cols;  // the occluder's silhouette pixels at lateral 0

  Coverage(const physics::BinaryMask& t, int64_t tp, const physics::BinaryMask& occ) : target(t), target_pixels(tp) {
    for (int r = 0; r < occ.height; ++r)
      for (int c = 0; c < occ.width; ++c)
        if (occ.at(r, c)) rows.push_back(r), cols.push_back(c);
  }
  double visible(int du, int dv) const {
    int64_t covered = 0;
    for (size_t k = 0; k < rows.size(); ++k) {
      const int r = rows[k] + dv, c = cols[k] + du;
      if (r >= 0 && r < target.height && c >= 0 && c < target.width) covered += target.at(r, c);
    }
    return 1.0 - double(covered) / double(target_pixels);
  }
};

// The exact visible fraction of the target (amodal mask) with an occluder silhouette over it.
double visible_exact(const physics::BinaryMask& target, int64_t tp, const physics::BinaryMask& occ) {
  int64_t left = 0;
  for (size_t i = 0; i < target.data.size(); ++i) left += target.data[i] && !occ.data[i];
  return double(left) / double(tp);
}

}  // namespace

bool place_occluder(WorldScene& s, int ti, double goal, const std::vector<std::string>& fams, Split split,
                    const SceneConfig& cfg, const Table& table, std::vector<Footprint>& taken, Rng& rng) {
  const WorldObject& target = s.objects[size_t(ti)];
  const physics::BinaryMask amodal = physics::render_silhouette(s.camera, object_world_mesh(target));
  const int64_t tp = amodal.count();
  if (tp < cfg.min_pixels) return false;
  const double target_size = target.shape.size_m;
  const Footprint tf = taken[size_t(ti)];
  const Vec3 cam = physics::camera_center(s.camera);
  Eigen::Vector2d towards(cam.x() - tf.centre.x(), cam.z() - tf.centre.y());
  towards.normalize();
  const Eigen::Vector2d side(-towards.y(), towards.x());
  for (int tries = 0; tries < 12; ++tries) {
    ShapeInstance inst = draw_instance(fams, split, cfg, rng);
    if (tries < 8 && inst.size_m < 0.8 * target_size) continue;  // prefer occluders as large as the target
    const RestAnalysis a = analyse_rest(inst.mesh, inst.closed);
    auto o = orient_as(inst, a, Rest::Stand, rng);
    if (!o) o = orient_as(inst, a, Rest::Lie, rng);
    if (!o) continue;
    const double ahead = tf.radius + o->radius + rng.uniform(0.02, 0.12);
    auto pose_at = [&](double lateral) {
      const Eigen::Vector2d c = tf.centre + ahead * towards + lateral * side;
      return position_at(*o, c.x(), c.y(), tf.floor, table);
    };
    const Vec3 t0 = pose_at(0.0);
    const Coverage cover(amodal, tp, physics::render_silhouette(s.camera, transformed(o->offsets, Mat3::Identity(), t0)));
    const physics::Projection p0 = physics::project(s.camera, t0);
    auto vis = [&](double lateral) {
      const physics::Projection p = physics::project(s.camera, pose_at(lateral));
      return cover.visible(int(std::lround(p.u - p0.u)), int(std::lround(p.v - p0.v)));
    };
    if (vis(0.0) > goal) continue;  // too small to hide enough of the target
    const double sign = rng.chance(0.5) ? 1.0 : -1.0;
    for (const double sg : {sign, -sign}) {
      double lo = 0, hi = 2.0 * (tf.radius + o->radius);
      if (vis(sg * hi) < goal) continue;
      for (int it = 0; it < 12; ++it) {
        const double mid = 0.5 * (lo + hi);
        (vis(sg * mid) < goal ? lo : hi) = mid;
      }
      const Vec3 t = pose_at(sg * 0.5 * (lo + hi));
      if (!footprint_ok(*o, t, tf.floor, table, s.camera, taken, false)) continue;
      const double exact = visible_exact(amodal, tp, physics::render_silhouette(s.camera, transformed(o->offsets, Mat3::Identity(), t)));
      if (exact < cfg.visible_min || exact > cfg.visible_max) continue;
      Footprint f;
      f.floor = tf.floor;
      f.centre = Eigen::Vector2d(t.x() + o->centre.x(), t.z() + o->centre.y());
      f.radius = o->radius;
      taken.push_back(f);
      add_object(s, std::move(inst), *o, t, tf.floor);
      return true;
    }
  }
  return false;
}

}  // namespace simu::world::detail
