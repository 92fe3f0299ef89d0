// The probe's MuJoCo world (internal to the probe's files; users include physics/probe.h):
//  - probe_world.cpp: the per-object working state, reading and checking the inputs, building and
//    compiling a world (planes, bases, static and dynamic objects, pins), free-joint pose access,
//    pins, the sequential order;
//  - probe_settle.cpp: what is simulated in a world: contacts, penetration resolution, the gravity
//    diagnostics (fall until contact, settle on pins), the joint settle and the evaluation settle,
//    the settle of one best-of-N candidate.
// The algorithm that strings these together (diagnose, correct, compose, evaluate) is probe.cpp;
// reports and pictures are probe_report.cpp and pictures.cpp.
#pragma once

#include <mutex>
#include <string>
#include <vector>

#include "pipeline/physics/mjcf.h"
#include "pipeline/physics/probe.h"

namespace simu::physics::probe_detail {

// mj_loadXML keeps global compiler state: compile one model at a time.
std::mutex& compile_mutex();

// Per-object working state.
struct Obj {
  bool usable = false;    // has a mesh and collision hulls
  bool simulate = false;  // takes part in the physics (not disabled)
  Mesh canonical;
  CollisionShape shape;
  Vec3 t, s;
  Mat3 R;
  bool visual_ok = false;       // its mesh can be a visual geom of scene.xml
  std::vector<Vec3> pins_body;  // object-frame pins (anchored)
  int wall = -1;                // index into scene.walls (anchored)
};

// Adds a flag once and appends msg (when not empty) to the object's message.
void add_flag(Diagnostics& d, const std::string& flag, const std::string& msg);

// A file-name-safe form of an object id (letters, digits, '-' and '_'; others become '_').
std::string safe_name(const std::string& id);

// A compiled world for one simulation.
struct World {
  MjModelPtr model;
  MjDataPtr data;
  std::vector<int> obj_body;   // object index -> MuJoCo body id (-1 if absent or static)
  std::vector<bool> env_body;  // MuJoCo body id -> environment (world, planes, bases)
  std::vector<int> body_obj;   // MuJoCo body id -> object index (-1 for environment)
};

// What every step of the probe works on: the scene, the config, the objects' working state and the
// bases with their collision hulls.
struct Ctx {
  const Scene& scene;
  const ProbeConfig& cfg;
  std::vector<Obj>& objs;
  std::vector<BaseBody> bases;
  std::vector<std::vector<Mesh>> base_hulls;  // scaled, base frame
};

// --- probe_world.cpp ------------------------------------------------------------------------

// Reads and checks the inputs (step 1 of the probe and of evaluate_physics): bases read and
// decomposed (a bad base is skipped with a warning), objects read, decomposed and checked; problems
// flag the object (diags), the rest goes on.
void load_inputs(Ctx& c, std::vector<Diagnostics>& diags);

// Builds and compiles a world: planes, bases, static objects, dynamic objects (pins optional).
// detect: a diagnostic model (contacts reported detect_margin before touching, no force there).
// visuals: the final file's visual geoms (OBJ files under meshes/); such a model is not compiled here
// (its mesh files do not exist yet): the world returned is compiled from the same text without them.
World build_world(const Ctx& c, const std::vector<int>& statics, const std::vector<int>& dynamics, bool pins,
                  std::string* xml_out = nullptr, const std::vector<int>& visual_only = {}, int buffer_factor = 1,
                  bool detect = false, bool visuals = false);

// Free-joint pose access (set_pose also zeroes the body's velocity).
void set_pose(World& w, int body, const Vec3& t, const Mat3& R);
void get_pose(const World& w, int body, Vec3* t, Mat3* R);
// Largest absolute component of the body's 6-D velocity.
double body_speed(const World& w, int body);
// Puts object i's body at the object's working pose at rest and runs mj_forward (contacts of that pose).
void start_at_pose(const Ctx& c, World& w, int i);

// Object-side pins at the object's current pose, paired with its wall (anchored objects).
void place_pins(Ctx& c, int i, Diagnostics& d);

// Sequential order: ascending lowest world-AABB corner along gravity.
std::vector<int> sequential_order(const Ctx& c, const std::vector<int>& idx);

// --- probe_settle.cpp -----------------------------------------------------------------------

// Penetration resolution of one dynamic object (paper: environment group first, push by max depth +
// 7 mm along the depth-weighted mean normal, <= 200 iterations, > 0.3 m or surviving contact fails).
// For anchored objects, pushes keep the object on its wall (the wall-normal component is removed
// unless the wall itself is penetrated).
bool resolve_penetration(const Ctx& c, World& w, int i, Vec3* dt, int* iters, double* max_depth, std::string* why);

// Free-object gravity diagnostic: fall until the first frame with a contact (margin makes it
// visible before touching), then close the remaining gap along gravity.
bool fall_until_contact(const Ctx& c, World& w, int i, Vec3* dt, double* time, std::string* why);

// Anchored-object gravity diagnostic: simulate on the pins until settled.
bool settle_on_pins(const Ctx& c, World& w, int i, Vec3* dt, Mat3* dR, double* time, std::string* why);

// Outcome of one joint settle over `objects` (Scene::objects indices).
struct SettleRun {
  std::vector<SettleRecord> rec;  // per entry of `objects`
  std::vector<Vec3> t;            // poses after the settle
  std::vector<Mat3> R;
  bool reset = false;             // MuJoCo reset the data (bad qacc): poses are the initial ones
  bool full = false;              // contact buffers still full at the largest size
  double simulated = 0;           // s
  double scene_peak = 0;          // J: max over time of the summed kinetic energy
  int buffer_factor = 1;          // contact/constraint buffer multiplier that sufficed
};

// Joint settle: free objects 6-DoF, anchored ones on their pins, everything under gravity for
// `duration` s; stops early once, over one settle_window, no body moved more than rest_distance.
// Full contact/constraint buffers restart it with larger ones. Records per object: displacement,
// deepest contact at the start and at the end, peak kinetic energy, category.
SettleRun joint_settle(const Ctx& c, const std::vector<int>& objects, double duration, double rest_distance);

// The metrics settle over `live` objects: a PhysicsEvaluation over every scene object (the others
// are physics_disabled records at their current pose).
PhysicsEvaluation evaluate_settle(const Ctx& c, const std::vector<int>& live, double duration);

// Best-of-N: the stability figure of one candidate shape for object i. The candidate is placed at
// `centre` with `statics` as static colliders, its penetration resolved, then it settles alone for
// candidate_settle_time (stopping once at rest over settle_window). displacement = |final - centre|
// (the push out of penetration included). The object's working state is restored afterwards.
Diagnostics::Candidate settle_candidate(const Ctx& c, const std::vector<int>& statics, int i,
                                        const ProbeShapeCandidate& cand, const CollisionShape& shape, const Vec3& centre);

// --- probe_report.cpp -----------------------------------------------------------------------

// Writes every output of a probe run into out_dir through a staging folder beside it, moved into
// place at the end (a failed run leaves the previous output as it was): meshes, scene.json,
// scene.xml, the resample hand-off, report.json, overlay.png and the pictures.
void write_outputs(ProbeResult& res, const std::vector<Obj>& objs, const std::string& out_dir, const ProbeConfig& cfg);

}  // namespace simu::physics::probe_detail
