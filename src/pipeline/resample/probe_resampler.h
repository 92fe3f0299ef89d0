// Joins the model-side Resampler to the physics probe: the probe's OBB-guided requests (image, modal
// mask M_i, auxiliary crop mask M'_i) become Stage-1 condition inputs (crop box from M'_i, mask channel
// the modal mask, point map from the scene's depth), every object goes through ONE batched
// Resampler::resample call, and the decoded canonical mesh, rotation and scale go back to the probe
// (which sets the translation to the stretched OBB's centre).
#pragma once

#include <string>

#include <optional>

#include "data/preprocess.h"
#include "pipeline/physics/probe.h"
#include "pipeline/resample/resampler.h"

namespace simu::resample {

using physics::Camera;
using physics::ResampleFn;
using physics::Scene;

struct ProbeResamplerOptions {
  std::optional<data::PreprocessConfig> preprocess;  // unset = the model's (LiftOptions::preprocess)
  uint64_t seed = 0;                  // sampling noise seed
};

// The scene's depth or point map file (read_scene_pointmap: depth npy/PNG/EXR through the scene
// camera, or a point map npy) as a point map [3, H, W] in the PyTorch3D camera frame (NaN = invalid).
torch::Tensor pointmap_from_depth_file(const std::string& path, const Camera& camera);

// A ResampleFn for run_probe that uses `resampler` (which must outlive it) for the objects of `scene`,
// through the lift path (resample/lift.h lift_objects: the same preprocessing, batching and pose
// conversion as the `lift` program).
// Throws when the scene names an image or depth file that does not exist.
// Objects whose inputs cannot be prepared (missing image, empty mask...) come back not ok with the
// reason; the others are resampled together. The result reports the crop box taken from M'. With
// num_samples > 1 every usable sample becomes a candidate (ProbeResampleResult::candidates) and the
// probe keeps the most stable one (best-of-N); failed samples are named in the message.
ResampleFn make_probe_resample_fn(Resampler& resampler, const Scene& scene, ProbeResamplerOptions options = {});

}  // namespace simu::resample
