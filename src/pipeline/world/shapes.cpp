// Families, splits and instances of the shape world.
#include "pipeline/world/shapes.h"

#include "common/error.h"
#include "pipeline/physics/collision.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/synthetic.h"
#include "pipeline/world/families.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fmt/format.h>

namespace simu::world {

namespace {
// Salts keeping the instance, scene and property hashes independent.
constexpr uint64_t kSplitSalt = 0x5157A11D5EEDULL, kSceneSalt = 0x5CE7E5EEDULL;

// 80 / 10 / 10 from the top bits of a hash.
Split split_of_hash(uint64_t h) {
  const uint64_t bucket = (h >> 32) % 10;
  return bucket < 8 ? Split::Train : bucket == 8 ? Split::Val : Split::Test;
}

// HSV (all in [0, 1]) -> RGB.
Vec3 hsv_to_rgb(double h, double s, double v) {
  const double c = v * s, hp = std::fmod(h * 6.0, 6.0), x = c * (1 - std::abs(std::fmod(hp, 2.0) - 1));
  Vec3 rgb = Vec3::Zero();
  if (hp < 1) rgb = Vec3(c, x, 0);
  else if (hp < 2) rgb = Vec3(x, c, 0);
  else if (hp < 3) rgb = Vec3(0, c, x);
  else if (hp < 4) rgb = Vec3(0, x, c);
  else if (hp < 5) rgb = Vec3(x, 0, c);
  else rgb = Vec3(c, 0, x);
  return rgb + Vec3::Constant(v - c);
}
}  // namespace

const std::vector<std::string>& families() {
  static const std::vector<std::string> names = [] {
    std::vector<std::string> n;
    for (const auto& s : family_specs()) n.push_back(s.name);
    return n;
  }();
  return names;
}

const std::string& held_out_family() {
  static const std::string name = "mug";
  return name;
}

bool is_family(const std::string& name) {
  const auto& f = families();
  return std::find(f.begin(), f.end(), name) != f.end();
}

std::vector<std::string> split_families(Split) {
  std::vector<std::string> out;
  for (const auto& f : families())
    if (f != held_out_family()) out.push_back(f);
  return out;
}

const char* to_string(Split s) {
  switch (s) {
    case Split::Train: return "train";
    case Split::Val: return "val";
    case Split::Test: return "test";
  }
  return "train";
}

Split parse_split(const std::string& s, const std::string& what) {
  if (s == "train") return Split::Train;
  if (s == "val") return Split::Val;
  if (s == "test") return Split::Test;
  throw Error(fmt::format("{}: unknown split '{}'", what, s), "use train, val or test");
}

uint64_t instance_id(const std::string& family, uint64_t seed) { return hash_key(family, seed); }

Split split_of(uint64_t id) { return split_of_hash(splitmix64(id ^ kSplitSalt)); }

Split instance_split(const std::string& family, uint64_t seed) {
  return family == held_out_family() ? Split::Test : split_of(instance_id(family, seed));
}

uint64_t next_instance_seed(const std::string& family, Split split, uint64_t from) {
  if (family == held_out_family() && split != Split::Test)
    throw Error(fmt::format("shape world: the held-out family '{}' has no {} instances", family, to_string(split)),
                "ask for it in the test split only");
  for (uint64_t s = from;; ++s)
    if (instance_split(family, s) == split) return s;
}

Split scene_split_of(uint64_t scene_seed) { return split_of_hash(splitmix64(scene_seed ^ kSceneSalt)); }

uint64_t next_scene_seed(Split split, uint64_t from) {
  for (uint64_t s = from;; ++s)
    if (scene_split_of(s) == split) return s;
}

ShapeInstance make_shape(const std::string& family, uint64_t seed) {
  const FamilySpec& spec = family_spec(family);
  ShapeInstance inst;
  inst.family = family;
  inst.seed = seed;
  inst.id = instance_id(family, seed);
  inst.name = fmt::format("{}_{:016x}", family, inst.id);
  inst.split = instance_split(family, seed);
  inst.held_out = family == held_out_family();
  // Draws: proportions (the builder's own), then size, then colour.
  Rng rng(inst.id);
  inst.mesh = spec.build(rng);
  physics::normalise_canonical(inst.mesh);
  inst.size_m = rng.log_uniform(spec.size_min, spec.size_max);
  const double h = rng.unit(), s = rng.uniform(0.15, 0.9), v = rng.uniform(0.3, 0.95);
  inst.albedo = hsv_to_rgb(h, s, v);
  inst.closed = physics::is_closed_oriented(inst.mesh);
  return inst;
}

ShapeInstance make_external_shape(const Mesh& mesh, const std::string& name, double size_m) {
  const std::string problem = physics::mesh_problem(mesh);
  if (!problem.empty()) throw Error(fmt::format("external mesh '{}': {}", name, problem));
  ShapeInstance inst;
  inst.family = "external";
  inst.name = name;
  inst.mesh = physics::clean_mesh(mesh);
  const double longest = physics::normalise_canonical(inst.mesh);
  inst.id = physics::mesh_hash(inst.mesh);
  inst.seed = inst.id;
  inst.split = Split::Test;
  inst.held_out = true;
  if (size_m > 0) {
    inst.size_m = size_m;
  } else {
    // The file's units: metres, centimetres or millimetres, whichever gives a plausible size.
    inst.size_m = std::clamp(longest, 0.02, 0.6);
    for (const double unit : {1.0, 0.01, 0.001})
      if (longest * unit >= 0.02 && longest * unit <= 0.6) {
        inst.size_m = longest * unit;
        break;
      }
  }
  inst.albedo = Vec3(0.7, 0.55, 0.4);
  inst.closed = physics::is_closed_oriented(inst.mesh);
  return inst;
}

ShapeInstance load_external_shape(const std::string& path, double size_m) {
  try {
    return make_external_shape(physics::read_mesh(path), std::filesystem::path(path).stem().string(), size_m);
  } catch (const Error& e) {
    throw Error(fmt::format("{} (file {})", e.what(), path), e.hint());
  }
}

}  // namespace simu::world
