// Pose decoding of SAM 3D Objects Stage 1 (the generator's pose latents -> rotation, translation, scale)
// and its exact inverse, the pose encoding (a pose -> the latents a Stage-1 model is trained to produce).
//
// Decoding: the generator's pose latents -> rotation, translation, scale,
// as the official `pose_decoder(convention)` (sam3d_objects/pipeline/inference_utils.py) with
// `PoseTargetConverter` (sam3d_objects/data/dataset/tdfy/pose_target.py) computes them.
//
// Steps (official):
//  1. `6drotation_normalized` [.., 6] is de-normalised with ROTATION_6D_STD / ROTATION_6D_MEAN, split into
//     a1 = [0:3], a2 = [3:6]; Gram-Schmidt: b1 = a1/|a1|, b2 = normalize(a2 - (b1.a2) b1), b3 = b1 x b2;
//     R = stack([b1, b2, b3], dim=-1) (b1, b2, b3 are the COLUMNS of R).
//  2. scale = exp(`scale`), translation_scale = exp(`translation_scale`); translation is used as is.
//  3. The pose-target convention maps these to the instance pose (object -> camera) given the scene
//     (point-map) scale s_scene and shift; the decoder then averages the scale over the three axes.
//
// Frame convention. The official transform is PyTorch3D's row-vector one:
//   p_cam_row = (p_obj_row * scale) @ R + translation
// so for column vectors p_cam = R^T (scale * p_obj) + translation. DecodedPose::rotation is that R^T
// (column-vector convention), DecodedPose::rotation_official is R itself (what the official quaternion encodes).
#pragma once

#include <torch/torch.h>

#include <array>
#include <map>
#include <string>

namespace simu::models {

// Official ROTATION_6D_MEAN / ROTATION_6D_STD (inference_utils.py), float32 [6].
torch::Tensor rotation_6d_mean();
torch::Tensor rotation_6d_std();

// Step 1 alone: normalised 6-D rotation [..., 6] -> the official matrix R [..., 3, 3] (columns b1, b2, b3).
torch::Tensor rotation_6d_normalized_to_matrix(const torch::Tensor& rot6d_normalized);
// Inverse of step 1 for a rotation matrix R (official convention): [R[:, 0], R[:, 1]] normalised with
// the mean/std. (No official encoder ships with the repository; this is the exact inverse of the decode.)
torch::Tensor matrix_to_rotation_6d_normalized(const torch::Tensor& rotation);
// PyTorch3D matrix_to_quaternion (w, x, y, z), standardised to w >= 0. [..., 3, 3] -> [..., 4].
torch::Tensor matrix_to_quaternion(const torch::Tensor& rotation);

struct PoseDecodeOptions {
  // Official conventions: "ScaleShiftInvariant" (translation = t * s_scene + shift, scale = exp(s) * s_scene),
  // "ScaleShiftInvariantWTranslationScale" (translation = unit(t) * exp(ts) * s_scene + shift),
  // "ApparentSize" (translation = t * exp(ts) * s_scene, scale = exp(s) * exp(ts) * s_scene), and
  // "default": the generic decode (steps 1-2) with no scene conversion, i.e. ScaleShiftInvariant at
  // s_scene = 1, shift = 0. (The official "default" pose decoder returns nothing and leaves the latents
  // raw; the project uses this name for the plain decode.)
  std::string convention = "ScaleShiftInvariant";
  double scene_scale = 1.0;                     // isotropic point-map scale (official pointmap_scale)
  std::array<double, 3> scene_shift{0, 0, 0};   // point-map shift (official pointmap_shift)
};

struct DecodedPose {
  torch::Tensor rotation;           // [B, 3, 3] column-vector object->camera: p = rotation @ (scale * p_obj) + t
  torch::Tensor rotation_official;  // [B, 3, 3] official R (= rotation^T), PyTorch3D row-vector convention
  torch::Tensor quaternion;         // [B, 4] (w, x, y, z) of rotation_official, as the official output
  torch::Tensor translation;        // [B, 3]
  torch::Tensor scale;              // [B, 3] the axis mean repeated 3 times, as the official output
  torch::Tensor scale_per_axis;     // [B, 3] before the mean
};

// pose latents by official name ("6drotation_normalized" [B, 1, 6] or [B, 6], "scale" [B,(1,)3],
// "translation" [B,(1,)3], "translation_scale" [B,(1,)1] when the convention needs it) -> DecodedPose
// in float32 on the latents' device. Missing latents -> error naming them.
DecodedPose decode_pose(const std::map<std::string, torch::Tensor>& latents, const PoseDecodeOptions& options = {});

// Applies pose b to object-frame points [N, 3] -> camera-frame points [N, 3].
torch::Tensor apply_pose(const DecodedPose& pose, int64_t b, const torch::Tensor& points);

// A pose to encode, in DecodedPose's column-vector convention: p = rotation @ (scale * p_obj) + translation,
// in the frame of the point map the preprocessing normalised (its scale/shift go in PoseDecodeOptions).
struct InstancePose {
  torch::Tensor rotation;     // [B, 3, 3] proper rotations (R^T R = I, det +1)
  torch::Tensor translation;  // [B, 3]
  torch::Tensor scale;        // [B, 3] per axis, positive ([B, 1]: the same on every axis)
};

// The pose encoding: the exact inverse of decode_pose for the same options, as the official
// `PoseTargetConvention.from_instance_pose` of each convention builds its targets, followed by the
// inverse of the decoder's latent maps (log for scale and translation_scale, the normalised 6-D
// rotation: the first two columns of the official R = rotation^T, standardised by ROTATION_6D_MEAN/STD).
// Per convention, with d = (translation - shift) / s_scene:
//   ScaleShiftInvariant: scale = log(s / s_scene), translation = d, translation_scale = log 1 = 0
//     (the official targets' x_translation_scale is ones; the decoder ignores it);
//   ScaleShiftInvariantWTranslationScale: translation = d / |d|, translation_scale = log |d|,
//     scale = log(s / s_scene) (|d| clamped at 1e-7, as the official);
//   ApparentSize (no shift, as its decoder): t_rel = translation / s_scene, translation = t_rel / |t_rel|,
//     translation_scale = log |t_rel|, scale = log(s / s_scene / |t_rel|) (|t_rel| clamped at 1e-8);
//   default: scale = log(s), translation as is, translation_scale = 0.
// Returns float32 latents by official name, one token each: "6drotation_normalized" [B, 6], "scale"
// [B, 3], "translation" [B, 3], "translation_scale" [B, 1], on the pose's device. decode_pose of them
// gives the pose back (scale as scale_per_axis) up to float32 rounding. Errors name the batch entry
// whose rotation is not a proper rotation (tolerance 1e-4) or whose scale is not positive.
std::map<std::string, torch::Tensor> encode_pose(const InstancePose& pose, const PoseDecodeOptions& options = {});

}  // namespace simu::models
