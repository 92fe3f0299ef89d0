// MJCF writer and in-memory model loading (MuJoCo 2.2, the version we link).
//
// The paper's physics defaults (supplementary "Physics-mode parameters"): timestep 1/480 s, contacts
// with time constant 0.01 s and damping ratio 2.0 (solref), friction (sliding, torsional, rolling) =
// (1.0, 0.95, 0.01), condim 4, implicit integrator; multiccd enabled (a single mesh-mesh contact
// point lets a resting cube sink ~4 mm). Floor and walls are planes.
//
// The file handed to users (scene.xml) has margin = gap = 0: MuJoCo 2.2 sums the two geoms' gaps and
// subtracts them from the summed margins, current MuJoCo (3.x, 4.x) does not combine them the same
// way, so any non-zero margin/gap pair makes resting objects behave differently between versions
// (MuJoCo 4.0 lifted every resting object 8 mm with margin = gap = 0.004). The probe's own diagnostic
// models use detect_margin (margin = gap, no force) so the first contact of a fall is seen before it
// penetrates; those models are compiled by MuJoCo 2.2 only and never written out.
//
// Each body's collision hulls are written inline (vertex/face) in group 3 (hidden in MuJoCo's viewer
// by default); its reconstructed mesh, when given, is a visual geom (group 2, no contacts, no mass)
// read from an OBJ file beside the MJCF, which both MuJoCo 2.2 and current MuJoCo read.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "pipeline/physics/collision.h"
#include "pipeline/physics/scene.h"

struct mjModel_;
struct mjData_;

namespace simu::physics {

struct PhysicsConfig {
  double timestep = 1.0 / 480.0;
  double solref_timeconst = 0.01;
  double solref_dampratio = 2.0;
  Vec3 friction = Vec3(1.0, 0.95, 0.01);  // sliding, torsional, rolling
  int condim = 4;
  double margin = 0.0;          // m: written in every model's geom defaults (0: same in every MuJoCo version)
  double gap = 0.0;             // m
  double detect_margin = 0.004; // m: margin = gap in the probe's diagnostic models only (write_mjcf's `detect`)
  bool multiccd = true;
  std::string integrator = "implicit";  // paper; "Euler" = MuJoCo's semi-implicit default
  int nconmax = 2000;   // upper bounds; the probe sizes each model to its dynamic bodies
  int njmax = 5000;     // (mjData holds an njmax x njmax matrix: 5000 -> 200 MB)
  // Equality (pin) constraint softness: stiff but critically damped.
  double eq_timeconst = 0.01;
  double eq_dampratio = 1.0;
};

// A rigid body to write: world pose of the body frame, hulls in the body frame.
struct MjBody {
  std::string name;
  Vec3 pos = Vec3::Zero();
  Mat3 R = Mat3::Identity();
  std::vector<Mesh> hulls;  // closed convex meshes, body frame (already scaled)
  bool dynamic = false;     // free joint; else a static collider
  MassProps mass;           // body frame (dynamic bodies)
  std::vector<Vec3> pins;   // body-frame points held at their current world position (connect)
  std::string rgba = "0.7 0.7 0.7 1";
  // Visual geom: the reconstructed mesh as an OBJ file (path relative to the MJCF's folder) scaled
  // per axis into the body frame. Empty: no visual geom (the hulls are drawn instead).
  std::string visual_file;
  Vec3 visual_scale = Vec3::Ones();
  bool collide = true;      // false: no collision hulls are written (a visual-only body)
};

struct MjScene {
  Vec3 gravity = Vec3(0, 0, -9.81);   // vector (m/s^2)
  std::vector<Plane> planes;          // floor first, then walls; geom names "plane:<id>"
  std::vector<MjBody> bodies;         // geom names "<body>/<k>"
};

// The MJCF text of a scene. detect: a probe-internal diagnostic model (margin = gap = detect_margin).
std::string write_mjcf(const MjScene& scene, const PhysicsConfig& cfg, bool detect = false);

// Routes MuJoCo's warnings and errors to simu::log instead of stderr and MUJOCO_LOG.TXT in the
// working directory (called by every loader; idempotent).
void install_mujoco_log_handlers();

// Owning handles of a compiled model and its data.
struct MjModelDeleter {
  void operator()(mjModel_* m) const;
};
struct MjDataDeleter {
  void operator()(mjData_* d) const;
};
using MjModelPtr = std::unique_ptr<mjModel_, MjModelDeleter>;
using MjDataPtr = std::unique_ptr<mjData_, MjDataDeleter>;

// Compiles MJCF text in memory (virtual file system). Throws simu::Error with MuJoCo's message.
MjModelPtr load_mjcf_string(const std::string& xml, const std::string& name = "model.xml");
// Compiles an MJCF file from disk.
MjModelPtr load_mjcf_file(const std::string& path);
MjDataPtr make_data(const mjModel_* m);

// Bitmask of MuJoCo warnings raised since the last call (counts reset). mjWARN_BADQACC means the
// data was reset to qpos0: the step must be treated as failed.
int take_warnings(mjData_* d);
std::string describe_warnings(int mask);

}  // namespace simu::physics
