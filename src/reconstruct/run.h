// The `reconstruct` front end: from a photo's masks and depth to the pre-simulation scene in our
// convention, then the physics probe (in-process resampling, final settle, MJCF, report, pictures).
//
//   inputs    image; masks (a label PNG or one PNG per object) with a JSON sidecar (docs/reconstruct.md):
//             per object id / label_value, label, role (object | floor | wall), dof (free | point | line),
//             pins, base (a fixed collider), and optionally a mesh + SAM 3D pose ("bring your own lift")
//             and a refined pose (e.g. FoundationPose, scene convention) replacing the rotation;
//             depth (.npy / 16-bit PNG mm / EXR) + K JSON, or a point map .npy (OpenCV camera);
//   steps     1 lift (the Stage-1 port, one batched call) for objects without their own mesh;
//             2 translation-scale alignment (align.h); 3 floor / walls (planes.h) and the floor snap;
//             4 tabletop refinement (tabletop.h) for table / desk labels; 5 compose the scene and run
//             the probe.
//   frame     the OpenCV camera frame is the world (camera pose identity), gravity = -up of step 3;
//             both are written into scene.json and reconstruct_report.json.
// Bad input is per object where it can be (mask size, no valid depth, an unknown sidecar entry, a
// mesh that does not load, a degenerate plane): the object is skipped or the step left out, and
// reconstruct_report.json lists what was skipped and why.
#pragma once

#include "resample/lift.h"
#include "physics/probe.h"
#include "reconstruct/align.h"
#include "reconstruct/planes.h"
#include "reconstruct/tabletop.h"

#include <nlohmann/json.hpp>

#include <map>
#include <optional>
#include <string>
#include <vector>

namespace simu::reconstruct {

struct ReconstructFiles {
  resample::LiftFiles lift;  // image, masks, depth / point map, K (resample/lift.h)
  std::string sidecar;       // objects JSON (optional: every mask then a free object)
};

struct ReconstructOptions {
  AlignConfig align;
  PlanesConfig planes;
  TabletopConfig tabletop;
  bool do_align = true, do_tabletop = true, do_floor_snap = true;
  resample::LiftOptions lift;
  physics::ProbeConfig probe;
  bool run_probe = true;
  bool overwrite = false;
  // Ground-truth world AABBs by object id (benchmarks on synthetic data: the probe's 3D IoU / ABO).
  std::map<std::string, physics::Box3> gt_boxes;
};

// One object of the sidecar, resolved against the masks.
struct ObjectSpec {
  std::string mask_id;          // which mask: "label_<k>" (label image) or a per-object mask's file stem
  std::string id, label;        // the object's name (sidecar "id", default mask_id) and class label
  std::string role = "object";  // object | floor | wall
  physics::PoseDof dof = physics::PoseDof::Free;
  bool base = false;
  std::string mesh, pose, refined_pose;  // absolute paths or empty
};

// What happened to one object.
struct ObjectReport {
  std::string id, label, role;
  bool used = false;          // in the composed scene
  std::vector<std::string> steps;   // e.g. "lifted", "byo_mesh", "aligned", "tabletop"
  std::vector<std::string> skipped; // "step: reason"
  double s_before = 0, s_after = 0;
  Vec3 t_before = Vec3::Zero(), t_after = Vec3::Zero();
  nlohmann::json to_json() const;
};

struct ReconstructResult {
  physics::Scene scene;       // the pre-simulation scene (world = OpenCV camera)
  PlanesResult planes;
  std::vector<ObjectReport> objects;
  std::vector<std::string> messages;
  nlohmann::json timings;      // seconds per step
  std::optional<physics::ProbeResult> probe;
};

// Parses the sidecar (throws simu::Error naming the file and the entry for malformed JSON).
std::vector<ObjectSpec> read_sidecar(const std::string& path, std::vector<std::string>* problems);

// The whole front end. `resampler` may be null when every object brings its own mesh (and then the
// probe writes the resampling hand-off instead of resampling). Writes into out_dir:
// input/scene.json (pre-simulation), input/meshes, input/masks, reconstruct_report.json and the
// probe's outputs under probe/ (scene.json, scene.xml, report.json, overlay.png).
ReconstructResult reconstruct(const ReconstructFiles& files, const ReconstructOptions& options,
                              resample::Resampler* resampler, const std::string& out_dir);

}  // namespace simu::reconstruct
