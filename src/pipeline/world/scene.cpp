// World scenes: room and table, camera and light, objects at rest, occluders for target visibility.
#include "pipeline/world/scene.h"

#include "common/error.h"
#include "pipeline/physics/camera.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/world/families.h"
#include "pipeline/world/placement.h"
#include "pipeline/world/settle.h"

#include <algorithm>
#include <cmath>
#include <fmt/format.h>

namespace simu::world {

using detail::Footprint;
using detail::Oriented;
using detail::Table;

const char* to_string(Rest r) {
  switch (r) {
    case Rest::Stand: return "stand";
    case Rest::Lie: return "lie";
    case Rest::Lean: return "lean";
  }
  return "stand";
}

SceneConfig SceneConfig::from(simu::config::Reader& r) {
  SceneConfig c;
  r.field("width", c.width);
  r.field("height", c.height);
  r.field("fov_min_deg", c.fov_min_deg);
  r.field("fov_max_deg", c.fov_max_deg);
  r.field("min_objects", c.min_objects);
  r.field("max_objects", c.max_objects);
  r.field("families", c.families);
  r.field("w_stand", c.w_stand);
  r.field("w_lie", c.w_lie);
  r.field("w_lean", c.w_lean);
  r.field("floor_fraction", c.floor_fraction);
  r.field("max_size_m", c.max_size_m);
  r.field("cam_distance_min", c.cam_distance_min);
  r.field("cam_distance_max", c.cam_distance_max);
  r.field("cam_elevation_min_deg", c.cam_elevation_min_deg);
  r.field("cam_elevation_max_deg", c.cam_elevation_max_deg);
  r.field("cam_yaw_max_deg", c.cam_yaw_max_deg);
  r.field("light_min", c.light_min);
  r.field("light_max", c.light_max);
  r.field("ambient", c.ambient);
  r.field("targets", c.targets);
  r.field("visible_min", c.visible_min);
  r.field("visible_max", c.visible_max);
  r.field("occlusion_attempts", c.occlusion_attempts);
  r.field("min_visible", c.min_visible);
  r.field("min_pixels", c.min_pixels);
  r.field("settle", c.settle);
  r.field("settle_seconds", c.settle_seconds);
  r.field("placement_attempts", c.placement_attempts);
  r.finish();
  return c;
}

namespace {

constexpr double kPi = 3.14159265358979323846;

void validate(const SceneConfig& c) {
  auto bad = [](const std::string& key, const std::string& why) {
    throw Error(fmt::format("scene config: {} {}", key, why), "fix the value in the world config or on the command line");
  };
  if (c.width < 16 || c.height < 16 || c.width > 8192 || c.height > 8192) bad("width/height", "must be in [16, 8192]");
  if (!(c.fov_min_deg > 5 && c.fov_max_deg >= c.fov_min_deg && c.fov_max_deg < 150)) bad("fov_min_deg/fov_max_deg", "must satisfy 5 < min <= max < 150");
  if (c.min_objects < 0 || c.max_objects < c.min_objects || c.max_objects > 64) bad("min_objects/max_objects", "must satisfy 0 <= min <= max <= 64");
  if (c.w_stand < 0 || c.w_lie < 0 || c.w_lean < 0 || c.w_stand + c.w_lie + c.w_lean <= 0) bad("w_stand/w_lie/w_lean", "must be >= 0 with a positive sum");
  if (!(c.floor_fraction >= 0 && c.floor_fraction <= 1)) bad("floor_fraction", "must be in [0, 1]");
  if (!(c.cam_distance_min > 0.2 && c.cam_distance_max >= c.cam_distance_min)) bad("cam_distance_min/max", "must satisfy 0.2 < min <= max");
  if (!(c.cam_elevation_min_deg >= 5 && c.cam_elevation_max_deg >= c.cam_elevation_min_deg && c.cam_elevation_max_deg <= 80))
    bad("cam_elevation_min_deg/max", "must satisfy 5 <= min <= max <= 80");
  if (!(c.visible_min >= 0 && c.visible_max <= 1 && c.visible_min < c.visible_max)) bad("visible_min/visible_max", "must satisfy 0 <= min < max <= 1");
  if (c.targets < 0 || c.targets > c.max_objects) bad("targets", "must be in [0, max_objects]");
  if (c.occlusion_attempts < 1 || c.placement_attempts < 1) bad("occlusion_attempts/placement_attempts", "must be >= 1");
  if (!(c.light_min >= 0 && c.light_max >= c.light_min && c.ambient >= 0)) bad("light_min/light_max/ambient", "must be >= 0 with min <= max");
}

// The families a scene draws from, checked against the split.
std::vector<std::string> scene_families(const SceneConfig& c, Split split) {
  if (c.families.empty()) return split_families(split);
  for (const auto& f : c.families) {
    family_spec(f);  // throws for an unknown name
    if (f == held_out_family() && split != Split::Test)
      throw Error(fmt::format("scene config: families names the held-out family '{}' in a {} scene", f, to_string(split)),
                  "the held-out family appears in test scenes only");
  }
  return c.families;
}

// Room (floor, wall), the table, the camera and the light of one attempt.
Table make_room(WorldScene& s, const SceneConfig& cfg, Rng& rng) {
  Table t;
  const double width = rng.uniform(1.0, 1.6), xc = rng.uniform(-0.3, 0.3);
  t.x0 = xc - 0.5 * width, t.x1 = xc + 0.5 * width;
  t.depth = rng.uniform(0.55, 0.85);
  t.height = rng.uniform(0.68, 0.78);
  s.floor_y = 0, s.wall_z = 0, s.table_top_y = -t.height;
  s.environment.clear();
  s.environment.push_back(physics::quad_mesh(Vec3(-6, 0, -8), Vec3(6, 0, -8), Vec3(6, 0, 0), Vec3(-6, 0, 0)));
  s.environment.push_back(physics::quad_mesh(Vec3(-6, -4, 0), Vec3(6, -4, 0), Vec3(6, 0, 0), Vec3(-6, 0, 0)));
  // Table: a top 4 cm thick and four legs 5 cm square, inset 5 cm.
  const double top = 0.04, leg = 0.05, inset = 0.05;
  std::vector<physics::Mesh> parts = {box_part(Vec3(width, top, t.depth), Vec3(xc, -t.height + 0.5 * top, -0.5 * t.depth))};
  for (const double x : {t.x0 + inset + 0.5 * leg, t.x1 - inset - 0.5 * leg})
    for (const double z : {-t.depth + inset + 0.5 * leg, -inset - 0.5 * leg})
      parts.push_back(box_part(Vec3(leg, t.height - top, leg), Vec3(x, -0.5 * (t.height - top), z)));
  s.environment.push_back(merge(parts));
  // Colours: floor (greys / woods), wall (light), table (woods / whites).
  const double fl = rng.uniform(0.25, 0.6), wl = rng.uniform(0.6, 0.9), tl = rng.uniform(0.3, 0.8);
  const double fw = rng.uniform(0.0, 0.25), ww = rng.uniform(-0.05, 0.08), tw = rng.uniform(0.0, 0.3);
  s.environment_albedo = {Vec3(fl * (1 + fw), fl, fl * (1 - fw)), Vec3(wl * (1 + ww), wl, wl * (1 - ww)),
                          Vec3(tl * (1 + tw), tl, tl * (1 - tw))};
  // Camera looking at a point over the table or the floor beside it, from the room side.
  const double lx = rng.uniform(t.x0 - 0.2, t.x1 + 0.2), ly = -t.height * rng.uniform(0.55, 1.0), lz = -t.depth * rng.uniform(0.3, 0.8);
  const double dist = rng.uniform(cfg.cam_distance_min, cfg.cam_distance_max);
  const double elev = rng.uniform(cfg.cam_elevation_min_deg, cfg.cam_elevation_max_deg) * kPi / 180;
  const double yaw = rng.uniform(-cfg.cam_yaw_max_deg, cfg.cam_yaw_max_deg) * kPi / 180;
  const double fov = rng.uniform(cfg.fov_min_deg, cfg.fov_max_deg) * kPi / 180;
  const Vec3 look(lx, ly, lz);
  const Vec3 back(std::cos(elev) * std::sin(yaw), -std::sin(elev), -std::cos(elev) * std::cos(yaw));  // look -> camera
  const Vec3 fwd = -back, right = Vec3(0, 1, 0).cross(fwd).normalized(), down = fwd.cross(right);
  physics::Camera& cam = s.camera;
  cam.width = cfg.width, cam.height = cfg.height;
  cam.fx = cam.fy = 0.5 * cfg.width / std::tan(0.5 * fov);
  cam.cx = 0.5 * cfg.width, cam.cy = 0.5 * cfg.height;
  cam.R_world_cam.col(0) = right, cam.R_world_cam.col(1) = down, cam.R_world_cam.col(2) = fwd;
  cam.t_world_cam = look + dist * back;
  // Light travelling down and towards the wall, from a random side.
  s.light_dir = Vec3(rng.uniform(-0.7, 0.7), 1.0, rng.uniform(0.2, 0.9)).normalized();
  s.light = rng.uniform(cfg.light_min, cfg.light_max);
  s.ambient = cfg.ambient;
  return t;
}

// Places one instance: a rest orientation, then a support (floor with probability p_floor, the other
// as the fallback). Returns false when it fits nowhere.
bool place_instance(WorldScene& s, ShapeInstance inst, const SceneConfig& cfg, const Table& table,
                    std::vector<Footprint>& taken, Rng& rng) {
  const RestAnalysis a = analyse_rest(inst.mesh, inst.closed);
  const auto o = detail::orient(inst, a, cfg, rng);
  if (!o) return false;
  const double p_floor = inst.size_m > 0.35 ? std::max(cfg.floor_fraction, 0.7) : cfg.floor_fraction;
  const bool first = rng.chance(p_floor);
  for (const bool floor : {first, !first}) {
    if (auto placed = detail::place_on_support(*o, floor, table, s.camera, taken, rng, cfg.placement_attempts)) {
      taken.push_back(placed->second);
      detail::add_object(s, std::move(inst), *o, placed->first, floor);
      return true;
    }
  }
  return false;
}

// One attempt at a scene: room, objects, occluders; rendered. Returns the number of targets in range.
int attempt_scene(WorldScene& s, const SceneConfig& cfg, Split split, const std::vector<std::string>& fams,
                  const std::vector<ShapeInstance>& extra, Rng& rng) {
  s.objects.clear();
  s.removed.clear();
  const Table table = make_room(s, cfg, rng);
  std::vector<Footprint> taken;
  for (const auto& inst : extra) {
    if (!place_instance(s, inst, cfg, table, taken, rng))
      throw Error(fmt::format("scene {}: the instance '{}' ({:.3f} m) fits nowhere in the view", s.name, inst.name, inst.size_m),
                  "give it a smaller size (make_external_shape size_m) or a larger image / field of view");
  }
  const int n = cfg.min_objects + rng.below(cfg.max_objects - cfg.min_objects + 1);
  // Each slot draws up to 3 instances until one fits (large ones often do not in a close view).
  for (int i = int(extra.size()); i < n; ++i)
    for (int k = 0; k < 3; ++k)
      if (place_instance(s, detail::draw_instance(fams, split, cfg, rng), cfg, table, taken, rng)) break;
  // Occluders for the targets: objects in random order, one occluder each, until enough are hidden.
  std::vector<int> targets;
  if (cfg.targets > 0) {
    std::vector<int> order(s.objects.size());
    for (size_t i = 0; i < order.size(); ++i) order[i] = int(i);
    for (size_t i = order.size(); i > 1; --i) std::swap(order[i - 1], order[size_t(rng.below(int(i)))]);
    for (int i : order) {
      if (int(targets.size()) >= cfg.targets) break;
      const double goal = rng.uniform(cfg.visible_min, cfg.visible_max);
      if (detail::place_occluder(s, i, goal, fams, split, cfg, table, taken, rng)) targets.push_back(i);
    }
  }
  if (cfg.settle) settle_scene(s, cfg.settle_seconds, true);
  render_scene(s);
  int met = 0;
  for (int i : targets) {
    WorldObject& o = s.objects[size_t(i)];
    o.target = o.visible_fraction >= cfg.visible_min && o.visible_fraction <= cfg.visible_max;
    met += o.target;
  }
  return met;
}

}  // namespace

physics::Mesh object_world_mesh(const WorldObject& o) { return transformed(o.shape.mesh, o.R * Mat3(o.scale.asDiagonal()), o.t); }

WorldScene make_scene(const SceneConfig& cfg, uint64_t seed, Split split, const std::vector<ShapeInstance>& extra) {
  validate(cfg);
  if (scene_split_of(seed) != split)
    throw Error(fmt::format("make_scene: seed {} belongs to the {} split, not {}", seed, to_string(scene_split_of(seed)), to_string(split)),
                fmt::format("take scene seeds from world::next_scene_seed({}, from)", to_string(split)));
  const std::vector<std::string> fams = scene_families(cfg, split);
  WorldScene best;
  int best_met = -1;
  for (int attempt = 0; attempt < (cfg.targets > 0 ? cfg.occlusion_attempts : 1); ++attempt) {
    WorldScene s;
    s.seed = seed;
    s.split = split;
    s.name = fmt::format("{}_{}", to_string(split), seed);
    s.min_visible = cfg.min_visible, s.min_pixels = cfg.min_pixels;
    Rng rng(hash_key("scene", seed) ^ splitmix64(uint64_t(attempt)));
    const int met = attempt_scene(s, cfg, split, fams, extra, rng);
    if (met > best_met) best = std::move(s), best_met = met;
    if (best_met >= cfg.targets) break;
  }
  return best;
}

WorldScene render_without(const WorldScene& s, const std::vector<int>& removed) {
  WorldScene e = s;
  for (int i : removed) {
    SIMU_CHECK(i >= 0 && i < int(s.objects.size()), "render_without: object index {} outside [0, {}) of scene {}", i,
               s.objects.size(), s.name);
    e.removed.push_back(i);
  }
  std::sort(e.removed.begin(), e.removed.end());
  e.removed.erase(std::unique(e.removed.begin(), e.removed.end()), e.removed.end());
  render_scene(e);
  return e;
}

}  // namespace simu::world
