// Tests eval_lift's alignment refiner (eval_align.h): a box seen by a camera that is turned and moved in
// the world, its prediction given in the world frame with a wrong scale and a depth error; the refiner
// must bring the world pose back (so the camera <-> world conversions both ways are right), and refuse,
// leaving the pose alone, a mask of another size.
#include <gtest/gtest.h>

#include "pipeline/reconstruct/eval_align.h"
#include "pipeline/reconstruct/zbuffer.h"
#include "common/source_dir.h"
#include "test_util.h"
#include "reconstruct_test_util.h"

using namespace simu::reconstruct;
using namespace simu::reconstruct::testing;

namespace {

// The scene camera: K of the test util, turned 25 degrees about a tilted axis and moved.
simu::physics::Camera world_camera(const Pinhole& K) {
  simu::physics::Camera c;
  c.fx = K.fx, c.fy = K.fy, c.cx = K.cx, c.cy = K.cy, c.width = K.width, c.height = K.height;
  c.R_world_cam = rot(Vec3(0.3, 1, 0.2).normalized(), 25);
  c.t_world_cam = Vec3(0.4, -1.2, 0.9);
  return c;
}

}  // namespace

// Scale x1.2 and 8 cm too far along the ray, in the world frame, come back to 3% and 1 cm.
TEST(EvalAlign, RefinerRecoversTheWorldPose) {
  const Pinhole K = camera();
  const auto cam = world_camera(K);
  // Truth in the camera frame, then in the world.
  simu::physics::PlacedShape truth;
  Points C;
  Faces F;
  box_mesh(Vec3(1.0, 0.6, 0.8), C, F);
  truth.canonical.V = C;
  truth.canonical.F = F;
  const Mat3 R_cam = rot(Vec3(0, 1, 0), 30) * rot(Vec3(1, 0, 0), -20);
  const Vec3 t_cam(0.05, 0.02, 1.6);
  const double s = 0.3;
  truth.scale = Vec3::Constant(s);
  truth.R = cam.R_world_cam * R_cam;
  truth.t = cam.R_world_cam * t_cam + cam.t_world_cam;
  // Its depth seen by the camera -> the shape world's point map and modal mask.
  Points Vc = (C * s) * R_cam.transpose();
  Vc.rowwise() += t_cam.transpose();
  const auto depth = render_depth(Vc, F, K);
  const PointMap pm = unproject(depth, K);
  const Mask sil = silhouette(depth, K);
  simu::world::PointMap wpm;
  wpm.width = K.width, wpm.height = K.height;
  wpm.xyz.assign(size_t(K.width) * K.height * 3, std::numeric_limits<float>::quiet_NaN());
  simu::physics::BinaryMask modal(K.width, K.height);
  for (size_t i = 0; i < pm.p.size(); ++i) {
    modal.data[i] = sil.data[i];
    if (PointMap::valid(pm.p[i]))
      for (int a = 0; a < 3; ++a) wpm.xyz[3 * i + a] = float(pm.p[i][a]);
  }
  ASSERT_GT(modal.count(), 1000);
  // The prediction: right rotation, scale x1.2, 8 cm further along the camera ray (world frame).
  simu::physics::PlacedShape pred = truth;
  pred.scale = truth.scale * 1.2;
  pred.t = cam.R_world_cam * (t_cam * (1 + 0.08 / t_cam.norm())) + cam.t_world_cam;
  simu::resample::RefineInput in;
  in.camera = &cam;
  in.pointmap = &wpm;
  in.modal = &modal;
  in.id = "box";
  const auto refine = alignment_refiner({});
  const std::string note = refine(pred, in);
  ASSERT_EQ(note, "");
  // The fit's resolution (align_test.cpp: the chamfer optimum is flat within a pixel pitch over the
  // object): 3% of scale and 1 cm of translation. Rotation and the scale's shape are not touched.
  EXPECT_NEAR(pred.scale.x() / s, 1.0, 0.03);
  EXPECT_NEAR(pred.scale.y() / pred.scale.x(), 1.0, 1e-12);
  EXPECT_LT((pred.t - truth.t).norm(), 0.01) << "world t " << pred.t.transpose() << " truth " << truth.t.transpose();
  EXPECT_TRUE(pred.R.isApprox(truth.R, 1e-12));
  // The same prediction with an identity camera pose lands elsewhere: the conversion is exercised.
  EXPECT_GT((cam.R_world_cam * t_cam - t_cam).norm(), 0.3);

  // A mask of another size: refused with the object named, the pose unchanged.
  simu::physics::PlacedShape pred2 = truth;
  pred2.t += Vec3(0, 0, 0.1);
  simu::physics::BinaryMask small(K.width / 2, K.height);
  in.modal = &small;
  const std::string why = refine(pred2, in);
  EXPECT_NE(why.find("box"), std::string::npos) << why;
  EXPECT_EQ(pred2.t, truth.t + Vec3(0, 0, 0.1));
}

// eval_lift with the refiner, the ground truth as the prediction (the committed meshes in world scenes,
// clean point maps): the alignment starts at the true pose, and the true shape fits its own depth best
// there, so every object stays where it is. A wrong frame or another object's mask in the eval path
// moves it by its own size (IoU near 0). The bound: align_test.cpp's fit resolution (1 cm, 3% of scale
// on a 30 cm box) on these 2-60 cm objects at the metric's <= 1 cm voxels: IoU >= 0.6, F@2cm >= 0.9.
TEST(EvalAlign, TruePoseSurvivesTheAlignmentInEvalLift) {
  simu::resample::EvalLiftOptions opt;
  opt.objects_dir = simu::source_dir() + "/tests/testdata/meshes";
  opt.gt_as_prediction = true;
  opt.pictures = false;
  opt.metrics.samples = 2000;
  opt.refine = alignment_refiner({});
  opt.refine_name = "simuscene";
  const auto r = simu::resample::run_eval_lift(opt, {}, simu::testing::temp_dir("eval_align_gt"));
  ASSERT_EQ(r.objects.size(), 5u);
  for (const auto& row : r.rows) {
    const auto& o = r.objects[row.object];
    ASSERT_TRUE(row.ok) << row.error;
    EXPECT_TRUE(row.refined) << o.id << ": " << row.refine_note;
    EXPECT_GE(row.metrics.iou, 0.6) << o.id << " size " << o.gt.size();
    EXPECT_GE(row.metrics.fscore[1].f, 0.9) << o.id;
    EXPECT_LT((row.lifted_t - o.gt.t).norm(), 1e-12) << o.id;  // the refiner started at the truth
  }
}
