// The `reconstruct` front end: from a photo's masks and depth to the pre-simulation scene in our
// convention, then the physics probe (in-process resampling, final settle, MJCF, report, pictures).
//
//   inputs    image; masks (a label PNG or one PNG per object) with a JSON sidecar (docs/reconstruct.md):
//             per object id / label_value, label, role (object | floor | wall), dof (free | point | line),
//             pins, base (a fixed collider), and optionally a mesh + SAM 3D pose ("bring your own lift")
//             and a refined pose (e.g. FoundationPose, scene convention) replacing the rotation;
//             depth (.npy / 16-bit PNG mm / EXR) + K JSON, or a point map .npy (OpenCV camera);
//   steps     1 lift (the Stage-1 port, one batched call) for objects without their own mesh;
//             2 translation-scale alignment (align.h); an object lifted with several samples
//             (lift.samples, else the model's num_samples) has each sample aligned and keeps the one
//             the depth and mask agree with most (icp_refine.h's pose_score, lowest); 3 floor / walls (planes.h, first pass, up from
//             walls, else floor, else the lifted meshes' up axes); 4 tabletop refinement (tabletop.h)
//             for table / desk labels; 5 plane re-extraction with the fitted meshes (their up axes,
//             the fallback floor without the objects' points) and the floor snap to the lowest vertex
//             of their union; a wall for every hanging object (its sidecar "wall", else the nearest
//             fitted wall behind it, else a plane fitted to the depth around its mask); 6 compose
//             the scene and run the probe.
//   frame     the OpenCV camera frame is the world (camera pose identity), gravity = -up of step 3;
//             both are written into scene.json and reconstruct_report.json.
// Bad input is per object where it can be (mask size, no valid depth, an unknown sidecar entry, a
// mesh that does not load, a degenerate plane): the object is skipped or the step left out, and
// reconstruct_report.json lists what was skipped and why.
#pragma once

#include "pipeline/resample/lift.h"
#include "pipeline/physics/probe.h"
#include "pipeline/reconstruct/align.h"
#include "pipeline/reconstruct/planes.h"
#include "pipeline/reconstruct/support_box.h"
#include "pipeline/reconstruct/tabletop.h"

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
  SupportBoxConfig support_box;  // bases with "fit": "box"
  bool do_align = true, do_tabletop = true, do_floor_snap = true;
  // Not in the paper (which keeps SAM 3D's scale for a resampled shape): each resampled candidate's
  // scale fitted to its object's depth by step 2's alignment, started at the target OBB's centre; the
  // probe still places it at that centre. For models whose own scale is poor (the miniature).
  bool align_resampled = false;
  // The first lift: lift.samples shapes per object (kFirstLiftSamples by default; 0 = the model's
  // num_samples); with several, step 2 keeps the best (see above).
  resample::LiftOptions lift = resample::first_lift_options();
  physics::ProbeConfig probe;
  bool run_probe = true;
  bool overwrite = false;
  // Ground-truth world AABBs by object id (benchmarks on synthetic data: the probe's 3D IoU / ABO).
  std::map<std::string, physics::Box3> gt_boxes;
  // The canonical up axis of meshes lifted by the port ("+z": SAM 3D's canonical frame is z-up), for
  // the mesh-derived up; "" = unknown (lifted objects then give no up). Bring-your-own meshes give
  // theirs in the sidecar ("up_axis").
  std::string lift_up_axis = "+z";
  // Hanging objects: a fitted wall farther than this from the object's mesh is not its wall (m); the
  // ring of pixels around the mask that a wall is fitted to when none is (pixels).
  double hang_wall_max_gap = 0.10;
  int hang_wall_ring_px = 12;
};

// One object of the sidecar, resolved against the masks.
struct ObjectSpec {
  std::string mask_id;          // which mask: "label_<k>" (label image) or a per-object mask's file stem
  std::string id, label;        // the object's name (sidecar "id", default mask_id) and class label
  std::string role = "object";  // object | floor | wall
  physics::PoseDof dof = physics::PoseDof::Free;
  bool base = false;
  std::string fit = "lift";     // lift (the model, or a brought mesh) | box (bases: support_box.h)
  std::string mesh, pose, refined_pose;  // absolute paths or empty
  std::string up_axis;          // canonical up axis of a brought mesh ("+x" .. "-z"; "" unknown)
  std::string wall;             // hanging objects: id of the wall entry it hangs on ("" = found)
};

// A photo already in memory: what resample::load_lift_inputs reads from files (rgb, point map, K, one
// mask per object id) and the sidecar's entries (empty: every mask a free object). The benchmark and
// builds without image I/O (no OpenCV) hand a synthetic photo over this way.
struct ReconstructInputs {
  resample::LiftInputs lift;
  std::vector<ObjectSpec> specs;
  std::string sidecar_name;  // names the sidecar in messages ("" = none)
  std::string image_path;    // written into the scene (the probe's overlay); may be empty
  std::vector<std::string> messages;  // problems found while reading (passed to the report)
};

// What happened to one object.
struct ObjectReport {
  std::string id, label, role;
  bool used = false;          // in the composed scene
  std::vector<std::string> steps;   // e.g. "lifted", "byo_mesh", "aligned", "tabletop"
  std::vector<std::string> skipped; // "step: reason"
  double s_before = 0, s_after = 0;
  Vec3 t_before = Vec3::Zero(), t_after = Vec3::Zero();
  std::string wall;           // hanging objects: the wall it is anchored to
  nlohmann::json to_json() const;
};

struct ReconstructResult {
  physics::Scene scene;       // the pre-simulation scene (world = OpenCV camera)
  PlanesResult planes;        // after the re-extraction and the floor snap
  PlanesResult planes_first;  // the first pass (depth and masks only)
  Vec3 mesh_up = Vec3::Zero();  // the fitted meshes' up (zero: none known)
  double floor_snap = 0;      // m along up
  std::vector<ObjectReport> objects;
  std::vector<std::string> messages;
  nlohmann::json timings;      // seconds per step
  std::optional<physics::ProbeResult> probe;
};

// Parses the sidecar (throws simu::Error naming the file and the entry for malformed JSON).
std::vector<ObjectSpec> read_sidecar(const std::string& path, std::vector<std::string>* problems);

// Reads the photo's files and the sidecar (whole-run errors name the file; per-mask problems stay
// with their object).
ReconstructInputs load_reconstruct_inputs(const ReconstructFiles& files);

// A unit canonical axis from "+x", "-x", "+y", "-y", "+z", "-z" (throws naming `what` otherwise).
Vec3 parse_axis(const std::string& axis, const std::string& what);

// The whole front end. `resampler` may be null when every object brings its own mesh (and then the
// probe writes the resampling hand-off instead of resampling). Writes into out_dir:
// input/scene.json (pre-simulation), input/meshes, input/masks, reconstruct_report.json and the
// probe's outputs under probe/ (scene.json, scene.xml, report.json, overlay.png).
ReconstructResult reconstruct(const ReconstructFiles& files, const ReconstructOptions& options,
                              resample::Resampler* resampler, const std::string& out_dir);
// The same from inputs in memory (masks are written into out_dir/input/masks only with OpenCV).
ReconstructResult reconstruct(const ReconstructInputs& inputs, const ReconstructOptions& options,
                              resample::Resampler* resampler, const std::string& out_dir);

}  // namespace simu::reconstruct
