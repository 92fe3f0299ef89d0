#include "models/pose.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <cmath>

#include "common/error.h"

namespace simu::models {

torch::Tensor rotation_6d_mean() {
  return torch::tensor({-0.06366084883674913, 0.008438224692279752, 0.00017084786438302483, 0.0007126610473540038,
                        -0.0030916726538816417, 0.5166093753457688},
                       torch::kFloat64)
      .to(torch::kFloat32);
}

torch::Tensor rotation_6d_std() {
  return torch::tensor({0.6656971967514863, 0.6787012271867754, 0.30345010594844524, 0.4394504420678794,
                        0.39817973931717104, 0.6176286868761914},
                       torch::kFloat64)
      .to(torch::kFloat32);
}

namespace {
// L2 normalisation along the last dim as torch.nn.functional.normalize (eps 1e-12).
torch::Tensor normalize(const torch::Tensor& v) {
  return v / v.norm(2, -1, /*keepdim=*/true).clamp_min(1e-12);
}
// [B, 1, C] or [B, C] -> [B, C] float32; checks the channel count.
torch::Tensor flat(const torch::Tensor& t, int64_t channels, const std::string& name) {
  SIMU_CHECK(t.dim() >= 1 && t.size(-1) == channels, "decode_pose: latent '{}' must end in {} channels, got {}", name,
             channels, t.sizes());
  return t.reshape({-1, channels}).to(torch::kFloat32);
}
}  // namespace

torch::Tensor rotation_6d_normalized_to_matrix(const torch::Tensor& rot6d_normalized) {
  SIMU_CHECK(rot6d_normalized.size(-1) == 6, "rotation_6d: expected [..., 6], got {}", rot6d_normalized.sizes());
  const auto x = rot6d_normalized.to(torch::kFloat32);
  // De-normalise with the official statistics.
  const auto rot6d = x * rotation_6d_std().to(x.device()) + rotation_6d_mean().to(x.device());
  const auto a1 = rot6d.narrow(-1, 0, 3), a2 = rot6d.narrow(-1, 3, 3);
  // Gram-Schmidt, then the cross product for the third axis.
  const auto b1 = normalize(a1);
  const auto b2 = normalize(a2 - (b1 * a2).sum(-1, true) * b1);
  const auto b3 = torch::cross(b1, b2, -1);
  return torch::stack({b1, b2, b3}, -1);  // [..., 3, 3], columns b1 b2 b3
}

torch::Tensor matrix_to_rotation_6d_normalized(const torch::Tensor& rotation) {
  const auto r = rotation.to(torch::kFloat32);
  // Columns 0 and 1, de-normalised form -> normalised.
  const auto rot6d = torch::cat({r.select(-1, 0), r.select(-1, 1)}, -1);
  return (rot6d - rotation_6d_mean().to(r.device())) / rotation_6d_std().to(r.device());
}

torch::Tensor matrix_to_quaternion(const torch::Tensor& m) {
  SIMU_CHECK(m.dim() >= 2 && m.size(-1) == 3 && m.size(-2) == 3, "matrix_to_quaternion: expected [..., 3, 3], got {}",
             m.sizes());
  // Entry (i, j) of every matrix: [...].
  const auto e = [&](int64_t i, int64_t j) { return m.select(-2, i).select(-1, j); };
  const auto m00 = e(0, 0), m01 = e(0, 1), m02 = e(0, 2);
  const auto m10 = e(1, 0), m11 = e(1, 1), m12 = e(1, 2);
  const auto m20 = e(2, 0), m21 = e(2, 1), m22 = e(2, 2);
  // |q| components from the diagonal (PyTorch3D's _sqrt_positive_part).
  const auto q_abs = torch::sqrt(torch::clamp_min(
      torch::stack({1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22}, -1), 0));
  // Four candidate quaternions, each exact when its leading component is the largest.
  const auto c0 = torch::stack({q_abs.select(-1, 0).pow(2), m21 - m12, m02 - m20, m10 - m01}, -1);
  const auto c1 = torch::stack({m21 - m12, q_abs.select(-1, 1).pow(2), m10 + m01, m02 + m20}, -1);
  const auto c2 = torch::stack({m02 - m20, m10 + m01, q_abs.select(-1, 2).pow(2), m12 + m21}, -1);
  const auto c3 = torch::stack({m10 - m01, m20 + m02, m21 + m12, q_abs.select(-1, 3).pow(2)}, -1);
  auto candidates = torch::stack({c0, c1, c2, c3}, -2);  // [..., 4, 4]
  candidates = candidates / (2.0 * q_abs.unsqueeze(-1).clamp_min(0.1));
  // Pick the best-conditioned candidate, then standardise to w >= 0.
  const auto best = q_abs.argmax(-1, true);  // [..., 1]
  std::vector<int64_t> idx_shape(best.sizes().begin(), best.sizes().end());
  idx_shape.push_back(4);
  auto q = candidates.gather(-2, best.unsqueeze(-1).expand(idx_shape)).squeeze(-2);
  return torch::where(q.select(-1, 0).unsqueeze(-1) < 0, -q, q);
}

DecodedPose decode_pose(const std::map<std::string, torch::Tensor>& latents, const PoseDecodeOptions& options) {
  const auto& conv = options.convention;
  SIMU_CHECK(conv == "ScaleShiftInvariant" || conv == "ScaleShiftInvariantWTranslationScale" || conv == "ApparentSize" ||
                 conv == "default",
             "decode_pose: unknown pose convention '{}' (expected ScaleShiftInvariant, "
             "ScaleShiftInvariantWTranslationScale, ApparentSize or default)",
             conv);
  const bool needs_ts = conv == "ScaleShiftInvariantWTranslationScale" || conv == "ApparentSize";
  // Every latent the convention needs must be present.
  std::vector<std::string> needed = {"6drotation_normalized", "scale", "translation"};
  if (needs_ts) needed.push_back("translation_scale");
  std::vector<std::string> missing;
  for (const auto& n : needed)
    if (!latents.count(n)) missing.push_back(n);
  SIMU_CHECK(missing.empty(), "decode_pose: convention {} needs pose latents [{}], missing [{}]", conv,
             fmt::join(needed, ", "), fmt::join(missing, ", "));

  DecodedPose out;
  // Step 1: rotation.
  const auto rot6d = flat(latents.at("6drotation_normalized"), 6, "6drotation_normalized");  // [B, 6]
  out.rotation_official = rotation_6d_normalized_to_matrix(rot6d);                         // [B, 3, 3]
  out.rotation = out.rotation_official.transpose(-1, -2).contiguous();
  out.quaternion = matrix_to_quaternion(out.rotation_official);
  // Step 2: log-space scale and translation scale.
  const auto scale = torch::exp(flat(latents.at("scale"), 3, "scale"));     // [B, 3]
  const auto translation = flat(latents.at("translation"), 3, "translation");  // [B, 3]
  const auto dev = translation.device();
  const auto s_scene = static_cast<float>(options.scene_scale);
  const auto shift = torch::tensor({options.scene_shift[0], options.scene_shift[1], options.scene_shift[2]},
                                   torch::kFloat64)
                         .to(torch::kFloat32)
                         .to(dev)
                         .unsqueeze(0);  // [1, 3]
  // Step 3: convention -> instance pose.
  if (conv == "ScaleShiftInvariant" || conv == "default") {
    const float s = conv == "default" ? 1.f : s_scene;
    out.scale_per_axis = scale * s;
    out.translation = conv == "default" ? translation.clone() : translation * s + shift;
  } else if (conv == "ScaleShiftInvariantWTranslationScale") {
    const auto ts = torch::exp(flat(latents.at("translation_scale"), 1, "translation_scale"));  // [B, 1]
    const auto unit = translation / translation.norm(2, -1, true);
    out.scale_per_axis = scale * s_scene;
    out.translation = unit * ts * s_scene + shift;
  } else {  // ApparentSize: s_tilde = scale, t_unit = translation, |t_rel| = translation_scale
    const auto ts = torch::exp(flat(latents.at("translation_scale"), 1, "translation_scale"));  // [B, 1]
    out.scale_per_axis = scale * ts * s_scene;
    out.translation = translation * ts * s_scene;
  }
  // The official output scale: mean over the axes, repeated.
  out.scale = out.scale_per_axis.mean(-1, true).expand({-1, 3}).contiguous();
  return out;
}

torch::Tensor apply_pose(const DecodedPose& pose, int64_t b, const torch::Tensor& points) {
  SIMU_CHECK(points.dim() == 2 && points.size(1) == 3, "apply_pose: expected points [N, 3], got {}", points.sizes());
  const auto p = points.to(torch::kFloat32).to(pose.rotation.device());
  // Row-vector form as the official Transform3d: (p * s) @ R + t.
  return (p * pose.scale[b]).matmul(pose.rotation_official[b]) + pose.translation[b];
}


std::map<std::string, torch::Tensor> encode_pose(const InstancePose& pose, const PoseDecodeOptions& options) {
  const auto& conv = options.convention;
  SIMU_CHECK(conv == "ScaleShiftInvariant" || conv == "ScaleShiftInvariantWTranslationScale" || conv == "ApparentSize" ||
                 conv == "default",
             "encode_pose: unknown pose convention '{}' (expected ScaleShiftInvariant, "
             "ScaleShiftInvariantWTranslationScale, ApparentSize or default)",
             conv);
  SIMU_CHECK(pose.rotation.defined() && pose.rotation.dim() == 3 && pose.rotation.size(1) == 3 && pose.rotation.size(2) == 3,
             "encode_pose: rotation must be [B, 3, 3], got {}", pose.rotation.defined() ? pose.rotation.sizes() : c10::IntArrayRef{});
  const int64_t B = pose.rotation.size(0);
  SIMU_CHECK(pose.translation.defined() && pose.translation.sizes() == (c10::IntArrayRef{B, 3}),
             "encode_pose: translation must be [{}, 3], got {}", B,
             pose.translation.defined() ? pose.translation.sizes() : c10::IntArrayRef{});
  SIMU_CHECK(pose.scale.defined() && pose.scale.dim() == 2 && pose.scale.size(0) == B &&
                 (pose.scale.size(1) == 3 || pose.scale.size(1) == 1),
             "encode_pose: scale must be [{}, 3] or [{}, 1], got {}", B, B,
             pose.scale.defined() ? pose.scale.sizes() : c10::IntArrayRef{});
  SIMU_CHECK(options.scene_scale > 0 && std::isfinite(options.scene_scale),
             "encode_pose: scene_scale must be positive, got {}", options.scene_scale);
  // Float64 throughout: the latents then carry one float32 rounding each.
  const auto f64 = torch::TensorOptions().dtype(torch::kFloat64).device(pose.rotation.device());
  const auto R = pose.rotation.to(torch::kFloat64);                            // [B, 3, 3]
  const auto t = pose.translation.to(torch::kFloat64);                         // [B, 3]
  const auto s = pose.scale.to(torch::kFloat64).expand({B, 3}).contiguous();  // [B, 3]
  // Inputs the decoder can give back: proper rotations, positive finite scales.
  const auto ortho = (R.transpose(1, 2).matmul(R) - torch::eye(3, f64)).abs().amax({1, 2});  // [B]
  const auto det = torch::linalg_det(R);                                                        // [B]
  for (int64_t b = 0; b < B; ++b) {
    const double o = ortho[b].item<double>(), d = det[b].item<double>();
    SIMU_CHECK(o <= 1e-4 && d > 0, "encode_pose: rotation {} is not a proper rotation (max |R^T R - I| {:.3g}, det {:.6g})",
               b, o, d);
    const double smin = s[b].min().item<double>();
    SIMU_CHECK(smin > 0 && std::isfinite(s[b].sum().item<double>()), "encode_pose: scale {} must be positive, got {}", b,
               smin);
  }
  const double s_scene = options.scene_scale;
  const auto shift = torch::tensor({options.scene_shift[0], options.scene_shift[1], options.scene_shift[2]}, f64)
                         .unsqueeze(0);  // [1, 3]
  torch::Tensor scale, translation, translation_scale;  // [B, 3], [B, 3], [B, 1] in float64
  if (conv == "default") {
    scale = torch::log(s);
    translation = t;
    translation_scale = torch::zeros({B, 1}, f64);
  } else if (conv == "ScaleShiftInvariant") {
    scale = torch::log(s / s_scene);
    translation = (t - shift) / s_scene;
    translation_scale = torch::zeros({B, 1}, f64);
  } else if (conv == "ScaleShiftInvariantWTranslationScale") {
    const auto d = (t - shift) / s_scene;
    const auto n = d.norm(2, -1, true).clamp_min(1e-7);  // [B, 1]
    scale = torch::log(s / s_scene);
    translation = d / n;
    translation_scale = torch::log(n);
  } else {  // ApparentSize: s_tilde = s_rel / |t_rel|, t_unit = t_rel / |t_rel|
    const auto t_rel = t / s_scene;
    const auto n = t_rel.norm(2, -1, true).clamp_min(1e-8);  // [B, 1]
    scale = torch::log(s / s_scene / n);
    translation = t_rel / n;
    translation_scale = torch::log(n);
  }
  // The rotation: the official R is rotation^T; its first two columns, standardised.
  const auto Ro = R.transpose(1, 2);
  const auto rot6d = torch::cat({Ro.select(-1, 0), Ro.select(-1, 1)}, -1);  // [B, 6]
  const auto mean = rotation_6d_mean().to(f64.device()).to(torch::kFloat64), std = rotation_6d_std().to(f64.device()).to(torch::kFloat64);
  return {{"6drotation_normalized", ((rot6d - mean) / std).to(torch::kFloat32)},
          {"scale", scale.to(torch::kFloat32)},
          {"translation", translation.to(torch::kFloat32)},
          {"translation_scale", translation_scale.to(torch::kFloat32)}};
}

}  // namespace simu::models
