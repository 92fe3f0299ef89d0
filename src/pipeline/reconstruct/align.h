// Translation-scale alignment of one lifted object to its masked depth (supplementary "Pose Alignment
// Details", Eqs. align_loss, align_reg, align_select).
//
// Given the canonical mesh M (vertices c), its initial pose (R_init, s_init, t_init) and the observed
// points P (the object's mask back-projected through the depth, camera frame), the rotation stays
// fixed and only an isotropic factor of the scale and the translation are solved:
//
//   visibility   V_vis = the vertices of M visible in a z-buffer of M at the initial pose (computed once)
//   align_loss   L_align(s, t) = 1/|P| sum_{y in P} min_{v in V_vis} | y - (s R v + t) |
//   align_reg    L^(k) = L_align + lambda (log s - log s_init)^2,  Adam from s_0^(k) = rho_k s_init,
//                rho_k in {0.5, 0.75, 1.0, 1.25}; t_0 = t_init slid along its viewing ray so that the
//                visible vertices' mean depth matches the observed mean depth (ours: the paper does not
//                say how t starts; a start of another scale otherwise begins with its surface off the points)
//   align_select k* = argmax_k 1/2 Recall~^(k) + 1/2 (1 - L~_bi^(k))
//
// Recall^(k): fraction of the mask's pixels covered by the silhouette of the whole mesh at candidate k;
// L_bi^(k) = 1/2 (L_align + 1/|V'| sum_{v in V'} min_y |s R v + t - y|), V' = the visible vertices at
// the candidate that are not hidden behind the observed depth (other objects in front); the tildes
// divide by the largest value over the candidates (so both lie in [0, 1]). The paper gives neither
// lambda nor the normalisation; ours are in AlignConfig and docs/reconstruct.md.
//
// The nearest neighbours use the identity min_v |y - (sRv + t)| = s min_v |R^T (y - t)/s - v|: one
// nanoflann tree over V_vis in the canonical frame serves every iteration and every start.
#pragma once

#include "pipeline/reconstruct/types.h"

#include <string>
#include <vector>

namespace simu::reconstruct {

struct AlignConfig {
  std::vector<double> rho = {0.5, 0.75, 1.0, 1.25};  // multi-start factors of s_init
  double lambda = 1e-3;          // log-scale prior weight (loss in metres)
  int iterations = 250;          // Adam steps per start
  double lr_log_scale = 0.01;    // Adam step size of log s (decays linearly to 10%)
  double lr_translation = 0.01;  // of t, as a fraction of the observed cloud's bounding-box diagonal
  double beta1 = 0.9, beta2 = 0.999, eps = 1e-8;
  int64_t max_points = 3000;     // observed points used in the loss (evenly strided subsample)
  double max_edge = 1.0 / 80;    // canonical edges longer than this are split before visibility
                                 // (marching-cubes meshes at 64^3 are this dense already)
  double visibility_tol = 0.01;  // z-buffer tolerance, fraction of the placed mesh's diagonal
  double occlusion_margin = 0.02;  // m: a vertex behind the observed depth by more is hidden (L_bi)
  int64_t min_points = 20;       // fewer observed points: not aligned (flag)
  bool depth_init = true;        // each start's t_0 slid along the ray to the observed mean depth (ours)
  // Ours, after align_select: Adam steps on the bidirectional chamfer L_bi (the selection's own term,
  // on the visible vertices not hidden behind the observed depth) from the selected candidate. The
  // one-sided loss is flat along over-growth for boxes (a larger face still covers its points); the
  // selection only picks among the four ends of that valley. 0 (default) = the supplementary's method
  // alone. Experimental: on the proof scene 150 steps fix the boxes' over-growth but shrink rounded
  // shapes by 2-5% (silhouette-edge vertices pull inwards), so it is off.
  int polish_iterations = 0;
};

// The object to align. Scale: world = R_init (s_init * (shape .* c)) + t_init, `shape` the per-axis
// ratios of the pose's scale (s_pose = s_init * shape; isotropic poses have shape = 1).
struct AlignInput {
  std::string id;
  Points canonical;              // [n, 3] canonical vertices
  Faces faces;                   // [m, 3]
  Vec3 shape = Vec3::Ones();
  Mat3 R_init = Mat3::Identity();
  double s_init = 1;
  Vec3 t_init = Vec3::Zero();
  Points observed;               // [k, 3] masked depth points, camera frame
  Mask mask;                     // the object's visible mask (for the recall term)
  Pinhole K;
  const PointMap* depth = nullptr;  // optional full point map: occlusion test of L_bi's mesh side
};

struct AlignCandidate {
  double rho = 1, s = 1;
  Vec3 t = Vec3::Zero();
  double loss = 0;        // L^(k) at the end
  double chamfer = 0;     // L_align
  double recall = 0, bichamfer = 0, score = 0;
};

struct AlignResult {
  bool ok = false;
  std::string message;   // why not ok
  double s = 1;          // s* (isotropic factor; pose scale = s * shape)
  Vec3 t = Vec3::Zero(); // t*
  int best = -1;         // index into candidates
  double s_selected = 1; // the selected candidate before the polish
  Vec3 t_selected = Vec3::Zero();
  std::vector<AlignCandidate> candidates;
  int64_t visible_vertices = 0, points_used = 0;
};

// Runs the alignment. Per-object problems (too few points, no visible vertex) give ok = false with a
// message naming the object; the input pose is then returned unchanged.
AlignResult align_translation_scale(const AlignInput& in, const AlignConfig& config = {});

}  // namespace simu::reconstruct
