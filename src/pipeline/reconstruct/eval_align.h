// The SimuScene alignment (align.h) as eval_lift's pose refinement: eval_lift --align simuscene scores
// each lifted object after the translation-scale alignment the reconstruct pipeline runs on it, so the
// table measures the pose users get from `reconstruct` as well as the raw lift.
//
//   resample::EvalLiftOptions opt;
//   opt.refine = reconstruct::alignment_refiner({});
//   opt.refine_name = "simuscene";
#pragma once

#include "pipeline/reconstruct/align.h"
#include "pipeline/reconstruct/icp_refine.h"
#include "pipeline/resample/eval_lift.h"

namespace simu::reconstruct {

// A PoseRefiner that moves the prediction into the camera frame (OpenCV, the point map's), runs
// align_translation_scale with `config` (the rotation kept; the observed points = the point map's valid
// points under the modal mask; the full point map for the occlusion test) and writes the aligned
// isotropic scale factor and translation back in the world frame. Not aligned (the pose kept, the
// reason returned): too few points, no visible vertex, a point map or mask of another size.
resample::PoseRefiner alignment_refiner(const AlignConfig& config);

// eval_lift --align icp: the alignment above, then refine_rotation_icp (icp_refine.h) from the aligned
// pose, with up = -RefineInput::gravity (the image's up when unknown). Returns "" when the ICP's pose
// was taken (rotation, scale and translation changed); else the note says why not, with the aligned
// pose kept when the alignment ran, the lifted pose when it did not.
resample::PoseRefiner icp_refiner(const AlignConfig& align, const IcpConfig& icp);

// eval_lift's choice among several samples of one object (EvalLiftOptions::select): pose_score
// (icp_refine.h: render-and-compare against the point map and the modal mask, the ICP's tolerance) of
// the prediction at its pose, in the camera frame. +infinity when it cannot be scored (a point map or
// mask of another size, an empty mesh).
resample::PoseScorer render_compare_scorer(const IcpConfig& icp);

}  // namespace simu::reconstruct
