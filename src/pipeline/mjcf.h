// MJCF writer for MuJoCo 2.2 and in-memory model loading.
//
// The paper's physics defaults: timestep 1/480 s, contacts with time constant 0.01 s and damping
// ratio 2.0 (solref), friction (sliding, torsional, rolling) = (1.0, 0.95, 0.01), condim 4,
// implicit integrator, multiccd enabled (a single mesh-mesh contact point lets a resting cube sink
// ~4 mm). Floor and walls are planes. Every geom has margin = gap, so contacts are reported
// (dist >= 0, no force) before penetration and the probe sees first contact.
// Meshes are written inline (vertex/face attributes): the file loads standalone.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "pipeline/collision.h"
#include "pipeline/scene.h"

struct mjModel_;
struct mjData_;

namespace simu::pipeline {

struct PhysicsConfig {
  double timestep = 1.0 / 480.0;
  double solref_timeconst = 0.01;
  double solref_dampratio = 2.0;
  Vec3 friction = Vec3(1.0, 0.95, 0.01);  // sliding, torsional, rolling
  int condim = 4;
  double margin = 0.004;  // m: contacts are reported this far before touching ...
  double gap = 0.004;     // ... and stay inactive (no force) until they touch
  bool multiccd = true;
  std::string integrator = "Euler";  // MuJoCo's default (semi-implicit); "implicit" is ~2x slower here
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
};

struct MjScene {
  Vec3 gravity = Vec3(0, 0, -9.81);   // vector (m/s^2)
  std::vector<Plane> planes;          // floor first, then walls; geom names "plane:<id>"
  std::vector<MjBody> bodies;         // geom names "<body>/<k>"
};

// The MJCF text of a scene.
std::string write_mjcf(const MjScene& scene, const PhysicsConfig& cfg);

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

}  // namespace simu::pipeline
