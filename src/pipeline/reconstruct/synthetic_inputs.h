// A synthetic camera scene (synthetic_camera.h) as the `reconstruct` front end's in-memory inputs
// (run.h ReconstructInputs): the shaded image, one mask per label value, the depth as a point map, K and
// the sidecar's entries; no image file is read or written, so builds without OpenCV run it too.
#pragma once

#include "pipeline/reconstruct/run.h"
#include "pipeline/reconstruct/synthetic_camera.h"

#include <string>

namespace simu::reconstruct {

// `dir` holds write_camera_scene_lift's files (objects.json, lift/*): bring-your-own meshes and poses
// resolve there. with_meshes = false drops every object's mesh + pose (all lifted by the port).
ReconstructInputs camera_scene_inputs(const CameraScene& s, const std::string& dir, bool with_meshes);

}  // namespace simu::reconstruct
