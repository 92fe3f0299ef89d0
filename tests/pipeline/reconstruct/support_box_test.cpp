// Tests the support box (support_box.h): the minimum-area rectangle of rotated point sets; a box table
// rendered from a pitched camera fitted back (top height, yaw, extents, corners); its height taken down
// to a given floor; flying pixels trimmed; a mask without an upward face rejected with its reason; and
// in a whole reconstruct run, a sidecar base with "fit": "box" composed as the fitted box (its top and
// bottom on the true table's, its corners inside the true box), not lifted.
#include <gtest/gtest.h>

#include <fstream>

#include "pipeline/physics/mesh.h"
#include "pipeline/reconstruct/run.h"
#include "pipeline/reconstruct/support_box.h"
#include "pipeline/reconstruct/synthetic_inputs.h"
#include "reconstruct_test_util.h"
#include "test_util.h"

using namespace simu::reconstruct;
using namespace simu::reconstruct::testing;

namespace {
// A 1.0 x 0.6 x 0.7 m box (0.6 tall), turned 20 degrees about up, 2.4 m ahead of a camera looking down 30 degrees.
struct BoxTable {
  Pinhole K = camera(320, 240, 280);
  Mat3 Rr = rot(Vec3(1, 0, 0), 30);
  Vec3 up = Rr * Vec3(0, -1, 0);
  Vec3 e = Vec3(1.0, 0.6, 0.7);
  Points C, W;
  Faces F;
  Mat3 R;
  Vec3 t;
  PointMap map;
  Mask mask;
  BoxTable() {
    box_mesh(e, C, F);
    R = Rr * rot(Vec3(0, 1, 0), 20);
    t = Rr * Vec3(0.1, 1.0, 2.4);
    W = place(C, Vec3::Ones(), R, t);
    const auto depth = render_depth(W, F, K);
    map = unproject(depth, K);
    mask = silhouette(depth, K);
  }
  TabletopInput input() const {
    TabletopInput in;
    in.id = "table";
    in.points = &map;
    in.mask = mask;
    in.K = K;
    in.up = up;
    return in;
  }
  double top() const { return up.dot(t) + e.y() / 2; }
};

// The largest distance from a fitted box's corners to the nearest corner of the true box.
double corner_error(const SupportBoxResult& r, const Points& truth) {
  const Points W = place(r.canonical, r.scale, r.R, r.t);
  double worst = 0;
  for (Eigen::Index i = 0; i < W.rows(); ++i) {
    double best = 1e300;
    for (Eigen::Index j = 0; j < truth.rows(); ++j) best = std::min(best, (W.row(i) - truth.row(j)).norm());
    worst = std::max(worst, best);
  }
  return worst;
}
}  // namespace

// Rotated rectangles (uniform interior points and a few on the corners): the angle found is a side's, mod 90.
TEST(SupportBox, MinimumAreaRectangleFindsTheSides) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-0.5, 0.5);
  for (double deg : {0.0, 17.0, 44.0, 71.0, 133.0}) {
    const double a = deg * M_PI / 180;
    const Eigen::Vector2d ax(std::cos(a), std::sin(a)), bx(-std::sin(a), std::cos(a));
    std::vector<Eigen::Vector2d> pts;
    for (int i = 0; i < 400; ++i) pts.push_back(1.6 * u(rng) * ax + 0.7 * u(rng) * bx);
    for (double s : {-0.5, 0.5})
      for (double v : {-0.5, 0.5}) pts.push_back(1.6 * s * ax + 0.7 * v * bx);
    const double got = min_area_rectangle_angle(pts) * 180 / M_PI;
    double diff = std::fmod(std::abs(got - deg), 90.0);
    diff = std::min(diff, 90.0 - diff);
    EXPECT_LT(diff, 1e-6) << "rectangle at " << deg << " deg, got " << got;
  }
}

// The rendered box fitted back: top to the plane fit's accuracy (5 mm, as tabletop_test), the sides within
// 1 degree, the extents and corners within 2.5 cm (~3 pixels at 2.4 m and f = 280: the silhouette's edge).
TEST(SupportBox, RenderedBoxTableIsFittedBack) {
  BoxTable b;
  const SupportBoxResult r = fit_support_box(b.input());
  ASSERT_TRUE(r.ok) << r.message;
  EXPECT_LT(angle_deg(r.top.normal, b.up), 0.5);
  EXPECT_NEAR(b.up.dot(r.t + 0.5 * r.extents.z() * r.R.col(2)), b.top(), 0.005);
  // Sides: the fitted side a is parallel to one of the true horizontal sides.
  const Vec3 tx = b.R.col(0), tz = b.R.col(2);
  EXPECT_GT(std::max(std::abs(r.R.col(0).dot(tx)), std::abs(r.R.col(0).dot(tz))), std::cos(M_PI / 180));
  const double long_side = std::max(r.extents.x(), r.extents.y()), short_side = std::min(r.extents.x(), r.extents.y());
  EXPECT_NEAR(long_side, 1.0, 0.025);
  EXPECT_NEAR(short_side, 0.7, 0.025);
  EXPECT_NEAR(r.extents.z(), 0.6, 0.025);  // no floor: down to the lowest visible point (the front face's bottom)
  EXPECT_LT(corner_error(r, b.W), 0.025);
  EXPECT_NEAR(r.R.determinant(), 1.0, 1e-9);
}

// With a floor 0.2 m below the box's bottom, the box reaches down to the floor.
TEST(SupportBox, HeightGoesDownToTheFloor) {
  BoxTable b;
  TabletopInput in = b.input();
  const Vec3 bottom = b.t - 0.3 * b.up;
  in.floor = PlaneFit{bottom - 0.2 * b.up, b.up, 0, 0};
  const SupportBoxResult r = fit_support_box(in);
  ASSERT_TRUE(r.ok) << r.message;
  EXPECT_NEAR(r.extents.z(), 0.8, 0.005 + 1e-3);  // the top's 5 mm, the plane tilt's (< 0.5 deg over 0.5 m) 4 mm
  EXPECT_NEAR(b.up.dot(r.t - 0.5 * r.extents.z() * r.R.col(2)), b.up.dot(bottom) - 0.2, 0.01);
}

// Flying pixels (0.5% of the mask, scattered 0.5 m beyond the top's edge at its height) do not move the sides.
TEST(SupportBox, FlyingPixelsAreTrimmed) {
  BoxTable b;
  const SupportBoxResult clean = fit_support_box(b.input());
  ASSERT_TRUE(clean.ok);
  PointMap noisy = b.map;
  std::mt19937 rng(5);
  int64_t n = 0, total = 0;
  for (auto v : b.mask.data) total += v;
  for (size_t i = 0; i < noisy.p.size() && n < total / 400; i += 97)
    if (b.mask.data[i]) noisy.p[i] = b.t + (0.6 + 0.3 * std::uniform_real_distribution<double>(0, 1)(rng)) * b.R.col(0), ++n;
  TabletopInput in = b.input();
  in.points = &noisy;
  const SupportBoxResult r = fit_support_box(in);
  ASSERT_TRUE(r.ok) << r.message;
  EXPECT_GT(n, 20);
  EXPECT_NEAR(std::max(r.extents.x(), r.extents.y()), std::max(clean.extents.x(), clean.extents.y()), 0.01);
}

// Only the front face in the mask: no support plane, rejected with the reason.
TEST(SupportBox, NoUpwardFaceIsRejected) {
  BoxTable b;
  TabletopInput in = b.input();
  const auto normals = point_map_normals(b.map);
  for (size_t i = 0; i < in.mask.data.size(); ++i)
    if (in.mask.data[i] && normals[i].allFinite() && normals[i].dot(b.up) > 0.5) in.mask.data[i] = 0;
  const SupportBoxResult r = fit_support_box(in);
  EXPECT_FALSE(r.ok);
  EXPECT_NE(r.message.find("insufficient plane support"), std::string::npos) << r.message;
}

// A reconstruct run whose table entry says "fit": "box": the base is the fitted box, on the true table.
TEST(SupportBox, ReconstructComposesTheFittedBase) {
  CameraSceneConfig cfg;
  cfg.generator.width = 240;
  cfg.generator.height = 180;
  cfg.generator.fx = 210;
  cfg.generator.min_objects = cfg.generator.max_objects = 3;
  const CameraScene s = generate_camera_scene(cfg, 11, "box");
  const auto dir = simu::testing::temp_dir("support_box_run");
  write_camera_scene_lift(s, dir + "/photo");
  ReconstructInputs in = camera_scene_inputs(s, dir + "/photo", true);
  const CameraObject* table = nullptr;
  for (const auto& o : s.objects)
    if (o.is_base) table = &o;
  ASSERT_NE(table, nullptr);
  for (auto& sp : in.specs)
    if (sp.id == table->id) sp.fit = "box", sp.mesh.clear(), sp.pose.clear();
  ReconstructOptions opt;
  opt.run_probe = false;
  const ReconstructResult r = reconstruct(in, opt, nullptr, dir + "/out");
  ASSERT_EQ(r.scene.bases.size(), 1u);
  const auto& base = r.scene.bases[0];
  bool fitted = false;
  for (const auto& o : r.objects)
    if (o.id == table->id)
      for (const auto& st : o.steps) fitted |= st.rfind("fitted box", 0) == 0;
  EXPECT_TRUE(fitted);
  // The true box in the camera frame and the fitted one's corners.
  const Points truth = place(table->canonical, table->gt_scale, table->gt_R, table->gt_t);
  const simu::physics::Mesh m = simu::physics::read_mesh(base.mesh_path);
  double top_true = -1e300, bottom_true = 1e300, top = -1e300, bottom = 1e300;
  for (Eigen::Index i = 0; i < truth.rows(); ++i) {
    top_true = std::max(top_true, s.up.dot(truth.row(i).transpose()));
    bottom_true = std::min(bottom_true, s.up.dot(truth.row(i).transpose()));
  }
  // The true box's frame: its centre and axes (gt_R columns), half extents from its vertices.
  const Vec3 c = truth.colwise().mean().transpose();
  Vec3 half = Vec3::Zero();
  for (Eigen::Index i = 0; i < truth.rows(); ++i)
    half = half.cwiseMax((table->gt_R.transpose() * (truth.row(i).transpose() - c)).cwiseAbs());
  for (Eigen::Index i = 0; i < m.V.rows(); ++i) {
    const Vec3 w = base.R * base.scale.cwiseProduct(m.V.row(i).transpose()) + base.t;
    top = std::max(top, s.up.dot(w)), bottom = std::min(bottom, s.up.dot(w));
    // Inside the true box, but for 2 cm (the depth noise of the synthetic photo and the silhouette's pixels).
    const Vec3 local = (table->gt_R.transpose() * (w - c)).cwiseAbs() - half;
    EXPECT_LT(local.maxCoeff(), 0.02) << "corner " << i;
  }
  // The top to the plane fit's 1 cm on the noisy synthetic depth; the bottom on the fitted floor (1 cm).
  EXPECT_NEAR(top, top_true, 0.01);
  EXPECT_NEAR(bottom, bottom_true, 0.015);
  EXPECT_GT(top - bottom, 0.5);
}
