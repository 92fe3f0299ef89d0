// Tests the rotation refinement after the alignment (icp_refine.h) on scenes built from first principles:
// an L-shaped object (two boxes) rendered by the z-buffer at a known pose in front of a wall, seen from a
// camera looking down on it; the mask and the point map are the render's. A start turned by 97 degrees
// about the vertical (and tilted by 4) must come back within 3 degrees; the true pose must not be made
// worse; too few points leave the pose alone with the object named; and eval_lift's icp refiner keeps the
// ground truth where it is.
#include <gtest/gtest.h>

#include "pipeline/reconstruct/eval_align.h"
#include "pipeline/reconstruct/icp_refine.h"
#include "pipeline/reconstruct/zbuffer.h"
#include "common/source_dir.h"
#include "test_util.h"
#include "reconstruct_test_util.h"

#include <cmath>

using namespace simu::reconstruct;
using namespace simu::reconstruct::testing;

namespace {

// Two boxes that touch: a foot 30 x 6 x 12 cm and an upright 6 x 20 x 12 cm at its -x end (y down is
// the object's down), so no turn about the vertical maps the shape onto itself.
void l_shape(Points& V, Faces& F) {
  Points A, B;
  Faces FA, FB;
  box_mesh(Vec3(0.30, 0.06, 0.12), A, FA);
  box_mesh(Vec3(0.06, 0.20, 0.12), B, FB);
  A.rowwise() += Vec3(0, 0.07, 0).transpose();
  B.rowwise() += Vec3(-0.12, -0.06, 0).transpose();
  V.resize(A.rows() + B.rows(), 3);
  V << A, B;
  F.resize(FA.rows() + FB.rows(), 3);
  F << FA, (FB.array() + int(A.rows())).matrix();
}

double angle_deg(const Mat3& A, const Mat3& B) {
  return std::acos(std::clamp(((A.transpose() * B).trace() - 1) / 2, -1.0, 1.0)) * 180 / 3.14159265358979323846;
}

// The scene: the camera pitched 30 degrees down (up in its frame = Rx(30) (0, -1, 0)), the L turned 40
// degrees about its vertical 1 m away, a wall at 2.5 m behind it.
struct Scene {
  Pinhole K = camera();
  Points V;
  Faces F;
  Mat3 R;
  Vec3 t = Vec3(0.02, 0.03, 1.0);
  Vec3 up;
  PointMap depth;
  Mask mask;
  Points observed;
  Scene() {
    l_shape(V, F);
    R = rot(Vec3(1, 0, 0), 30) * rot(Vec3(0, 1, 0), 40);
    up = rot(Vec3(1, 0, 0), 30) * Vec3(0, -1, 0);
    Points Vc = V * R.transpose();
    Vc.rowwise() += t.transpose();
    std::vector<float> z = render_depth(Vc, F, K);
    mask = silhouette(z, K);
    for (float& d : z)
      if (!std::isfinite(d)) d = 2.5f;
    depth = unproject(z, K);
    observed = masked_points(depth, mask, "L");
  }
  AlignInput input(const Mat3& R0) const {
    AlignInput in;
    in.id = "L";
    in.canonical = V;
    in.faces = F;
    in.R_init = R0;
    in.s_init = 1;
    in.t_init = t;
    in.observed = observed;
    in.mask = mask;
    in.K = K;
    in.depth = &depth;
    return in;
  }
};

}  // namespace

// Started 97 degrees off about the vertical and 4 degrees tilted: back within 3 degrees, scale and
// position kept to 3% and 1 cm.
TEST(IcpRefine, RecoversATurnAboutTheVertical) {
  const Scene sc;
  ASSERT_GT(sc.mask.count(), 1500);
  const Mat3 R0 = rot(sc.up, 97) * rot(Vec3(0, 0, 1), 4) * sc.R;
  ASSERT_GT(angle_deg(R0, sc.R), 90);
  const IcpResult r = refine_rotation_icp(sc.input(R0), sc.up);
  ASSERT_TRUE(r.changed) << r.message;
  EXPECT_LT(angle_deg(r.R, sc.R), 3.0) << "best hypothesis yaw " << r.hypotheses[size_t(r.best)].yaw_deg;
  EXPECT_NEAR(r.s, 1.0, 0.03);
  EXPECT_LT((r.t - sc.t).norm(), 0.01);
  EXPECT_LT(r.hypotheses[size_t(r.best)].score, r.aligned_score);
  EXPECT_NEAR(r.turn_deg, angle_deg(R0, r.R), 1e-9);
  // ICP from the start alone (one hypothesis) does not get there: the turns are what finds it.
  IcpConfig one;
  one.yaw_steps = 1;
  const IcpResult r1 = refine_rotation_icp(sc.input(R0), sc.up, one);
  EXPECT_GT(angle_deg(r1.R, sc.R), 20.0);
}

// The true pose is not made worse: the result stays within 1 degree, 1% and 5 mm; the same input gives
// the same result (deterministic).
TEST(IcpRefine, KeepsTheTruePose) {
  const Scene sc;
  const IcpResult r = refine_rotation_icp(sc.input(sc.R), sc.up);
  EXPECT_LT(angle_deg(r.R, sc.R), 1.0) << r.message;
  EXPECT_NEAR(r.s, 1.0, 0.01);
  EXPECT_LT((r.t - sc.t).norm(), 0.005);
  const IcpResult again = refine_rotation_icp(sc.input(sc.R), sc.up);
  EXPECT_EQ(again.R, r.R);
  EXPECT_EQ(again.t, r.t);
  EXPECT_EQ(again.changed, r.changed);
  // The render-and-compare score of the truth is about 0 (its own depth and mask).
  EXPECT_LT(render_compare_score(sc.V, sc.F, sc.R, 1.0, sc.t, sc.input(sc.R), 0.015), 0.02);
}

// Too few points: nothing done, the object named, the pose returned as given.
TEST(IcpRefine, TooFewPointsLeavesThePose) {
  const Scene sc;
  AlignInput in = sc.input(rot(sc.up, 90) * sc.R);
  in.observed = in.observed.topRows(5);
  const IcpResult r = refine_rotation_icp(in, sc.up);
  EXPECT_FALSE(r.changed);
  EXPECT_NE(r.message.find("object L"), std::string::npos) << r.message;
  EXPECT_EQ(r.R, in.R_init);
  EXPECT_EQ(r.t, in.t_init);
}

// pose_score (best of K samples): the render-and-compare score with the ICP's tolerance (10% of the
// placed longest side, clamped to [5, 30] mm: 30 mm for the 30 cm L), about 0 for the truth, higher for
// shapes the image does not show (the L shrunk to 70%, turned 90 degrees about the vertical, or its
// bounding box), +infinity for an empty mesh.
TEST(IcpRefine, PoseScoreRanksTheShapeTheImageShowsFirst) {
  const Scene sc;
  const AlignInput in = sc.input(sc.R);
  const double truth = pose_score(in, sc.R, 1.0, sc.t);
  EXPECT_EQ(truth, render_compare_score(sc.V, sc.F, sc.R, 1.0, sc.t, in, 0.03));
  EXPECT_LT(truth, 0.02);
  // At a tenth of the size the tolerance is clamped to 5 mm.
  EXPECT_EQ(pose_score(in, sc.R, 0.1, sc.t), render_compare_score(sc.V, sc.F, sc.R, 0.1, sc.t, in, 0.005));
  EXPECT_GT(pose_score(in, sc.R, 0.7, sc.t), truth + 0.2);
  EXPECT_GT(pose_score(in, rot(sc.up, 90) * sc.R, 1.0, sc.t), truth + 0.05);
  AlignInput box = in;
  Points B;
  Faces FB;
  box_mesh(Vec3(0.30, 0.26, 0.12), B, FB);  // the L's bounding box: x in [-0.15, 0.15], y in [-0.16, 0.10]
  B.rowwise() += Vec3(0, -0.03, 0).transpose();
  box.canonical = B;
  box.faces = FB;
  EXPECT_GT(pose_score(box, sc.R, 1.0, sc.t), truth + 0.1);
  AlignInput empty = in;
  empty.canonical.resize(0, 3);
  EXPECT_TRUE(std::isinf(pose_score(empty, sc.R, 1.0, sc.t)));
}

// eval_lift with the icp refiner, the ground truth as the prediction (the committed meshes in world
// scenes, clean point maps): the truth fits its own depth best, so every object stays where it is
// (eval_align_test.cpp's bounds: IoU >= 0.6, F@2cm >= 0.9).
TEST(IcpRefine, TruePoseSurvivesTheRefinerInEvalLift) {
  simu::resample::EvalLiftOptions opt;
  opt.objects_dir = simu::source_dir() + "/tests/testdata/meshes";
  opt.gt_as_prediction = true;
  opt.pictures = false;
  opt.metrics.samples = 2000;
  opt.refine = icp_refiner({}, {});
  opt.refine_name = "icp";
  const auto r = simu::resample::run_eval_lift(opt, {}, simu::testing::temp_dir("icp_refine_gt"));
  ASSERT_EQ(r.objects.size(), 5u);
  for (const auto& row : r.rows) {
    const auto& o = r.objects[row.object];
    ASSERT_TRUE(row.ok) << row.error;
    EXPECT_GE(row.metrics.iou, 0.6) << o.id << " size " << o.gt.size() << " " << row.refine_note;
    EXPECT_GE(row.metrics.fscore[1].f, 0.9) << o.id;
    EXPECT_LT(row.metrics.rot_err_deg, 5.0) << o.id << " " << row.refine_note;
  }
}
