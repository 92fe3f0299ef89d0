// Rotation refinement of one lifted object after the translation-scale alignment (align.h): the idea of
// SAM 3D's layout post-optimisation (the decoded layout corrected against the point map after sampling),
// re-implemented as hypothesis-and-verify with trimmed ICP and a render-and-compare score.
//
// Given the aligned pose (R0, s0, t0) of the shaped canonical mesh M (world = s R (shape .* c) + t) and
// the object's masked point-map points Y (camera frame):
//
//   hypotheses   R_k = Rot(a, 2 pi k / yaw_steps) R0, k = 0..yaw_steps-1, turned about the object's centre
//                t0; a = the object's vertical axis: the axis of the predicted canonical frame (R0's column)
//                closest to `up` (gravity's opposite, camera frame). With `flips`, each also turned end over
//                end (180 degrees about the predicted horizontal axis R0 e_h, h the longer horizontal side).
//   ICP          per hypothesis, `iterations` steps of trimmed point-to-point ICP: each observed point to
//                its nearest sample of M's surface at the current pose, the `trim` closest pairs kept,
//                rotation, translation and scale solved in closed form (Umeyama), the scale clamped to
//                exp(+-max_log_scale) of s0 (fit_scale off: Kabsch, the aligned scale kept; yaw_only: the
//                turn about a alone, the tilt kept).
//   score        render-and-compare over the image (z-buffer of M at the pose, observed depth o, modal mask):
//                  mask pixel, drawn, depth known:  min(|z - o_z|, tau) / tau
//                  mask pixel, not drawn:           1 (the object seen, not explained)
//                  drawn outside the mask, o_z > z + tau: 1 (free space: the background is seen where
//                                                   the prediction would stand)
//                  drawn outside the mask otherwise: 0 (hidden behind a closer surface, or unknown)
//                summed and divided by the mask's pixel count; tau = depth_tol times the object's longest
//                side, clamped to [min_tol, max_tol] metres.
//   select       the lowest score among the hypotheses whose vertical axis ICP tipped by at most
//                max_tilt_deg; it replaces the aligned pose only when it is lower than the aligned pose's
//                own score by at least min_gain and by the fraction min_rel_gain (else the aligned pose is
//                kept, with a note). Defaults and the variants measured: docs/eval_lift.md.
//
// Deterministic (fixed-seed surface samples, fixed iteration counts) and re-entrant (no shared state).
#pragma once

#include "pipeline/reconstruct/align.h"

#include <string>
#include <vector>

namespace simu::reconstruct {

struct IcpConfig {
  int yaw_steps = 12;             // hypotheses about the vertical axis (k = 0 is the aligned rotation)
  bool flips = false;             // also each hypothesis turned end over end
  int iterations = 12;            // ICP steps per hypothesis
  double trim = 0.8;              // fraction of the closest pairs kept per step
  int64_t max_points = 600;       // observed points used by ICP (evenly strided subsample)
  int64_t surface_samples = 3000; // area-uniform samples of the mesh surface (ICP targets)
  bool yaw_only = false;          // ICP turns about the vertical axis only (else any rotation)
  double max_tilt_deg = 180;      // hypotheses whose vertical axis ICP tipped further are dropped
  bool fit_scale = true;          // Umeyama scale per step, clamped (else the aligned scale is kept)
  double max_log_scale = 0.1;     // |log(s / s0)| bound with fit_scale
  double depth_tol = 0.1;         // tau as a fraction of the placed object's longest side ...
  double min_tol = 0.005, max_tol = 0.03;  // ... clamped to these (metres)
  double min_gain = 0.05;         // score improvement needed to leave the aligned pose ...
  double min_rel_gain = 0;        // ... and as a fraction of the aligned pose's score
  int64_t min_points = 20;        // fewer observed points: nothing done (note)
};

struct IcpHypothesis {
  double yaw_deg = 0;   // the start's turn about the vertical axis
  bool flipped = false;
  Mat3 R = Mat3::Identity();
  double s = 1;
  Vec3 t = Vec3::Zero();
  double tilt_deg = 0;  // how far ICP turned the object's vertical axis
  bool dropped = false; // tilt_deg > IcpConfig::max_tilt_deg: not a candidate
  double residual = 0;  // trimmed mean distance of the observed points to the mesh at the end (m)
  double score = 0;     // render-and-compare score (lower is better)
};

struct IcpResult {
  bool changed = false;    // the pose below differs from the aligned one
  std::string message;     // why not changed
  Mat3 R = Mat3::Identity();
  double s = 1;            // isotropic factor (pose scale = s * shape)
  Vec3 t = Vec3::Zero();
  double aligned_score = 0;  // the aligned pose's own score
  int best = -1;             // index into hypotheses (-1: every one dropped)
  double turn_deg = 0;       // angle between the aligned and the returned rotation
  std::vector<IcpHypothesis> hypotheses;
};

// Refines `in`'s pose (R_init, s_init, t_init: the aligned pose) against in.observed, in.mask and
// in.depth (required for the free-space term; without it that term is 0). `up`: the scene's up
// direction in the camera frame (zero: the image's up, -y). Problems with the object (empty mesh, too
// few points) give changed = false with a message naming it and the aligned pose returned.
IcpResult refine_rotation_icp(const AlignInput& in, const Vec3& up, const IcpConfig& config = {});

// The render-and-compare score of the shaped mesh at pose (R, s, t) (camera frame); tau in metres.
double render_compare_score(const Points& shaped, const Faces& F, const Mat3& R, double s, const Vec3& t,
                            const AlignInput& in, double tau);

// The same score of in's mesh (canonical .* shape) at pose (R, s, t) with the tolerance the ICP uses:
// tau = config.depth_tol times the placed mesh's longest side, clamped to [min_tol, max_tol]. It ranks
// samples of one object against the point map (best of K, eval_lift / reconstruct). An empty mesh
// scores +infinity.
double pose_score(const AlignInput& in, const Mat3& R, double s, const Vec3& t, const IcpConfig& config = {});

}  // namespace simu::reconstruct
