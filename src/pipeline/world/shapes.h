// The shape world's objects (issue 35 section 1): procedural families with random proportions, metric
// sizes (2 cm to 60 cm longest side) and albedo, their canonical meshes in SAM 3D's convention, and the
// train / val / test splits of object instances (plus one held-out family, never in train or val).
//
//   const auto inst = simu::world::make_shape("mug", 1234);   // deterministic from (family, seed)
//   inst.mesh;     // canonical: AABB-centred, longest side 1; canonical -y is the top when it stands
//   inst.size_m;   // longest metric side: world = R (size_m * c) + t
//   inst.split;    // Train / Val / Test by a hash of the instance id; held-out family -> Test
//
// Canonical frame: like physics/synthetic.h, canonical y is the object's up/down axis with -y up (the
// world frame has y down = gravity), so a standing object has R = a yaw about y. Lathe families
// (bottle, bowl, cylinder, cone, ...) revolve about canonical y.
#pragma once

#include "pipeline/physics/scene.h"

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace simu::world {

using physics::Mat3;
using physics::Mesh;
using physics::Vec3;

// ---- Families -------------------------------------------------------------------------------------

// Every family name, in a fixed order (the order of the shapes table and the contact sheet): box,
// cylinder, sphere, cone, capsule, torus, bowl, bottle, mug, cup, vase, wedge, l_bracket, book_stack,
// stool, table, chair (docs/world.md has their pictures).
const std::vector<std::string>& families();
// The family never used in train or val (its instances are all Test; scenes of other splits never
// contain it): "mug" (a composite of body and handle whose handle no other family has).
const std::string& held_out_family();
// Whether name is one of families().
bool is_family(const std::string& name);

// ---- Splits ---------------------------------------------------------------------------------------

enum class Split { Train = 0, Val = 1, Test = 2 };
// The families a scene of a split draws from by default: every family but the held-out one (for
// Test too: the held-out family is asked for by name, SceneConfig::families).
std::vector<std::string> split_families(Split split);
const char* to_string(Split s);  // "train", "val", "test"
// Parses "train", "val", "test"; throws simu::Error naming `what` otherwise.
Split parse_split(const std::string& s, const std::string& what = "split");

// The instance id of (family, instance seed): a 64-bit hash of both (the split key of an instance).
uint64_t instance_id(const std::string& family, uint64_t instance_seed);
// The split of an instance id by its hash: 80% Train, 10% Val, 10% Test. (The held-out family
// overrides this: see instance_split.)
Split split_of(uint64_t instance_id);
// The split of (family, seed): Test for the held-out family, else split_of(instance_id(...)).
Split instance_split(const std::string& family, uint64_t instance_seed);
// The first instance seed >= from whose instance_split is `split` (expected 1.25 tries for Train,
// 10 for Val / Test). Throws simu::Error for the held-out family with Train or Val.
uint64_t next_instance_seed(const std::string& family, Split split, uint64_t from);

// The split of a scene seed by its hash (80 / 10 / 10, independent of the instance hash), and the
// first scene seed >= from of a split: make_scene accepts only seeds of its split.
Split scene_split_of(uint64_t scene_seed);
uint64_t next_scene_seed(Split split, uint64_t from);

// ---- Instances ------------------------------------------------------------------------------------

// One object instance: its canonical mesh and what the world knows about it.
struct ShapeInstance {
  std::string family;         // a families() name, or "external" (make_external_shape)
  std::string name;           // "<family>_<instance id as 16 hex digits>" (external: the file stem)
  uint64_t seed = 0;          // instance seed (make_shape's argument)
  uint64_t id = 0;            // instance_id(family, seed) (external: a hash of the mesh)
  Split split = Split::Train;
  bool held_out = false;      // the held-out family (or an external mesh)
  Mesh mesh;                  // canonical: AABB-centred, longest side 1 (fp64 rounding), -y up
  double size_m = 0;          // longest metric side (m), in [0.02, 0.6] for the families
  Vec3 albedo = Vec3::Constant(0.5);  // linear RGB in [0, 1]
  bool closed = false;        // every edge shared by exactly two faces with opposite directions
  // Scene convention per-axis scale: Vec3::Constant(size_m) (canonical longest side 1).
  Vec3 scale() const { return Vec3::Constant(size_m); }
};

// Makes instance `instance_seed` of a family: proportions, size, albedo and mesh are deterministic
// functions of (family, seed) (bit-identical wherever libm's sin / cos / exp / log agree). Throws simu::Error naming the family
// when it is unknown (the hint lists families()).
ShapeInstance make_shape(const std::string& family, uint64_t instance_seed);

// An external mesh (eval_lift --objects DIR) as an instance: the mesh is normalised to the canonical
// convention (AABB-centred, longest side 1) with its axes kept (no up axis is assumed: the scene
// generator puts it in a stable rest pose of its convex hull). Its metric size: size_m when > 0, else the
// file's longest side read in metres, centimetres or millimetres, whichever lands in [0.02, 0.6]
// first (a file in none of them is clamped into that range: a normalised mesh of side 1 gets 0.6 m). Split Test, held_out true.
ShapeInstance make_external_shape(const Mesh& mesh, const std::string& name, double size_m = 0);
// Reads a mesh file through physics::read_mesh (OBJ/PLY/STL/GLB) and calls make_external_shape with
// the file's stem as its name. Throws simu::Error naming the file.
ShapeInstance load_external_shape(const std::string& path, double size_m = 0);

}  // namespace simu::world
