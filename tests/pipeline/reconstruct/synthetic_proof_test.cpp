// The proof on synthetic camera data (synthetic_camera.h): a table scene with two walls,
// objects on the table (some occluded) and hanging objects, rendered to RGB / masks / depth / K, each
// object "lifted" as its ground-truth mesh with SAM 3D-like errors (scale +-10..25%, 1..5% of its
// distance along the ray, up to 2 degrees of rotation). Asserts:
//  - the translation-scale alignment brings every object seen enough (visible mask >= 40% of its
//    silhouette alone and >= 150 pixels), boxes included, to within 3% of its true scale and 1 cm of
//    its true centre on two scenes whose lifted poses carry the scale and ray errors (the alignment
//    keeps the rotation fixed, so these scenes inject none); with up to 2 degrees of rotation error as
//    well, within 6% and 1 cm (a rotation error biases the one-sided loss's minimum, docs/reconstruct.md);
//  - floor and walls from their masks within 1 degree of the truth, up within 1 degree;
//  - the table's top lands on the true top plane (1 degree, 1 cm) after hard_snap + table_refine;
//  - the SAM 3D pose conversion round-trips (independent: both conventions place the same vertices).
#include <gtest/gtest.h>

#include "pipeline/reconstruct/align.h"
#include "pipeline/reconstruct/planes.h"
#include "pipeline/reconstruct/synthetic_camera.h"
#include "pipeline/reconstruct/tabletop.h"
#include "tolerance.h"

#include <fmt/format.h>

#include <cstdlib>

using namespace simu::reconstruct;

namespace {
CameraScene make_scene(uint64_t seed, double rotation_deg) {
  CameraSceneConfig cfg;
  cfg.generator.min_objects = 6;
  cfg.generator.max_objects = 6;
  cfg.generator.max_hanging = 2;
  cfg.rotation_err_max_deg = rotation_deg;
  return generate_camera_scene(cfg, seed, "proof");
}
const CameraScene& scene() {
  static const CameraScene s = make_scene(5, 2);
  return s;
}
bool seen_enough(const CameraObject& o) {
  return !o.is_base && o.mask.count() >= 150 && double(o.mask.count()) >= 0.4 * double(o.amodal_pixels);
}
// Aligns every object seen enough; returns how many, expecting |scale error| < max_scale, t error < max_t.
int check_alignment(const CameraScene& s, double max_scale, double max_t) {
  int tested = 0;
  for (const auto& o : s.objects) {
    if (!seen_enough(o)) continue;
    AlignInput in;
    in.id = o.id;
    in.canonical = o.canonical;
    in.faces = o.faces;
    in.shape = o.lift_scale / o.lift_scale.maxCoeff();
    in.s_init = o.lift_scale.maxCoeff();
    in.R_init = o.lift_R;
    in.t_init = o.lift_t;
    in.mask = o.mask;
    in.K = s.K;
    in.observed = masked_points(s.points, o.mask, o.id);
    in.depth = &s.points;
    const AlignResult r = align_translation_scale(in);
    EXPECT_TRUE(r.ok) << r.message;
    if (!r.ok) continue;
    const double scale_err = r.s / o.gt_scale.maxCoeff() - 1;
    const double t_err = (r.t - o.gt_t).norm();
    std::cout << fmt::format("  {:<16} injected scale x{:.3f} ray {:+.3f} m rot {:.1f} deg -> scale err {:+.2f}% t err {:.1f} mm "
                             "(start rho {})\n",
                             o.id, o.scale_error, o.ray_error, o.rotation_error, 100 * scale_err, 1000 * t_err,
                             r.candidates[size_t(r.best)].rho);
    EXPECT_LT(std::abs(scale_err), max_scale) << o.id;
    EXPECT_LT(t_err, max_t) << o.id;
    ++tested;
  }
  return tested;
}
}  // namespace

// Scale and ray errors only (the rotation is what the alignment keeps): the 3% / 1 cm, boxes too.
TEST(ReconstructProof, AlignmentRecoversScaleAndTranslation) {
  int tested = 0;
  // The alignment's resolution (align_test): 3% of scale and 1 cm at the rendered depth's pixel pitch.
  for (uint64_t seed : {5, 6}) tested += check_alignment(make_scene(seed, 0), 0.03, 0.01);
  EXPECT_GE(tested, 10);
}

// With up to 2 degrees of rotation error too: measured worst 5.2% / 4.7 mm over 8 scenes, asserted at 6% / 1 cm.
// With the injected rotation errors the chamfer optimum of scale is shallower: 6% (the faces seen at the
// wrong angle change the apparent extent by up to 1 - cos(rotation error) of it, plus the 3% above).
TEST(ReconstructProof, AlignmentUnderRotationError) { EXPECT_GE(check_alignment(scene(), 0.06, 0.01), 4); }

TEST(ReconstructProof, PlanesWithinOneDegree) {
  const CameraScene& s = scene();
  const Points floor = masked_points(s.points, s.mask_of_label(1), "floor");
  std::vector<WallInput> walls = {{"back_wall", masked_points(s.points, s.mask_of_label(2), "back_wall")},
                                  {"left_wall", masked_points(s.points, s.mask_of_label(3), "left_wall")}};
  const PlanesResult r = fit_planes(floor, walls, Points(), Vec3::Zero());
  ASSERT_TRUE(r.floor);
  ASSERT_EQ(r.walls.size(), 2u);
  EXPECT_EQ(r.up_source, "walls");
  // Plane fits over thousands of rendered points with the scene's depth noise: normals within a small
  // fraction of a degree, offsets within mm; 1 degree and 2 cm are the acceptance (as planes_test).
  EXPECT_LT(angle_deg(r.up, s.up), 1.0);
  EXPECT_LT(angle_deg(r.floor->plane.normal, s.floor.plane.normal), 1.0);
  EXPECT_LT(std::abs(s.floor.plane.distance(r.floor->plane.point)), 0.02);
  for (const auto& w : r.walls) {
    const NamedPlane& truth = w.id == "back_wall" ? s.back_wall : s.left_wall;
    EXPECT_LT(angle_deg(w.plane.normal, truth.plane.normal), 1.0) << w.id;
    EXPECT_LT(std::abs(truth.plane.distance(w.plane.point)), 0.02) << w.id;
  }
}

TEST(ReconstructProof, TableTopOnTheTruePlane) {
  const CameraScene& s = scene();
  const CameraObject& t = s.objects.at(0);
  ASSERT_TRUE(t.is_base);
  TabletopInput in;
  in.id = t.id;
  in.canonical = t.canonical;
  in.faces = t.faces;
  in.scale = t.lift_scale;
  in.R = t.lift_R;
  in.t = t.lift_t;
  in.points = &s.points;
  in.mask = t.mask;
  in.K = s.K;
  in.up = s.up;
  in.floor = s.floor.plane;
  const TabletopResult r = refine_tabletop(in);
  ASSERT_TRUE(r.ok) << r.message;
  // True top height along up.
  const Points Wgt = place(t.canonical, t.gt_scale, t.gt_R, t.gt_t);
  const Points W = place(t.canonical, r.scale, r.R, r.t);
  double top_gt = -1e9, top = -1e9;
  for (Eigen::Index i = 0; i < W.rows(); ++i) {
    top_gt = std::max(top_gt, s.up.dot(Wgt.row(i).transpose()));
    top = std::max(top, s.up.dot(W.row(i).transpose()));
  }
  // The support plane's fit (as above) and the top within a centimetre: the table's own depth noise
  // and the refined pose's residual tilt across its half-width.
  EXPECT_LT(angle_deg(r.support.normal, s.up), 1.0);
  EXPECT_NEAR(top, top_gt, 0.01);
  // The canonical up axis (-y) of the table now points up.
  EXPECT_LT(angle_deg(r.R * Vec3(0, -1, 0), s.up), 1.0);
}

TEST(ReconstructProof, Sam3dPoseRoundTrip) {
  // Mesh vertices v (not canonical), a scene pose of their canonical mesh; SAM 3D's pose must place v
  // where the scene pose places c, and the inverse must give the scene pose back.
  Points V(3, 3);
  V << 0.1, 0.2, 0.3, -0.2, 0.4, 0.0, 0.3, -0.1, 0.2;
  const Vec3 lo = V.colwise().minCoeff(), hi = V.colwise().maxCoeff();
  const Vec3 centre = 0.5 * (lo + hi);
  const double factor = 1.0 / (hi - lo).maxCoeff();
  const Mat3 R = Eigen::AngleAxisd(0.7, Vec3(1, 2, 3).normalized()).toRotationMatrix();
  const Vec3 s(0.3, 0.3, 0.3), t(0.1, -0.2, 2.0);
  // A SAM 3D pose of v equivalent to (R, s, t) on c: scale_v = s * factor, and the centre folded into t.
  const Sam3dPose p0 = sam3d_pose_from_scene(R, s * factor, t - R * (s * factor).cwiseProduct(centre));
  const ScenePoseOut back = scene_pose_from_sam3d_mesh(p0, centre, factor);
  EXPECT_LT((back.R - R).norm(), simu::testing::kFp64Solve);
  EXPECT_LT((back.scale - s).norm(), simu::testing::kFp64Solve);
  EXPECT_LT((back.t - t).norm(), simu::testing::kFp64Solve);
  // Row-vector SAM 3D placement in PyTorch3D, flipped to OpenCV, equals the scene placement.
  const Eigen::Quaterniond q(p0.rotation_wxyz[0], p0.rotation_wxyz[1], p0.rotation_wxyz[2], p0.rotation_wxyz[3]);
  for (int i = 0; i < 3; ++i) {
    const Eigen::RowVector3d v = V.row(i);
    const Eigen::RowVector3d p3d = v.cwiseProduct(p0.scale.transpose()) * q.toRotationMatrix() + p0.translation.transpose();
    const Vec3 p_cv(-p3d.x(), -p3d.y(), p3d.z());
    const Vec3 c = (v.transpose() - centre) * factor;
    EXPECT_LT((p_cv - (R * s.cwiseProduct(c) + t)).norm(), simu::testing::kFp64Solve);
  }
}
