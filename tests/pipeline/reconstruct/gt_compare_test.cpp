// Tests the ground-truth comparison (reconstruct/gt_compare.h): a gt.json written here (a camera turned
// and moved in the GT world, one cube), scenes in the camera frame as reconstruct writes them. The GT
// carried through the frames scores IoU 1; a copy shifted along the world x axis scores the IoU of two
// offset boxes; a missing object and the probe's outcome reach the rows and the table.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <fstream>

#include "common/fs.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/metrics.h"
#include "pipeline/reconstruct/gt_compare.h"
#include "test_files.h"

using namespace simu::reconstruct;
using simu::physics::Mat3;
using simu::physics::Vec3;
using nlohmann::json;

namespace {

// A cube of side kSide whose faces lie mid-voxel on the IoU lattice (spacing h = min(1 cm, kSide / 50)
// = 4 mm; centre at x = y = z = h / 2, so each face is 25 h from it, half a voxel off the lattice).
constexpr double kSide = 0.2;
constexpr double kH = kSide / 50;

// The GT camera's pose in the GT world: turned about a skew axis and moved.
Mat3 cam_R() { return Eigen::AngleAxisd(0.7, Vec3(1, 2, -0.5).normalized()).toRotationMatrix(); }
Vec3 cam_t() { return Vec3(0.3, -1.2, 0.8); }

// Writes gt.json with one cube object (world pose: identity rotation, centre c) and its canonical mesh.
std::string write_gt(const std::string& dir, const Vec3& c) {
  simu::physics::write_mesh(simu::physics::box_mesh(Vec3::Constant(0.5)), dir + "/cube.obj");
  auto mj = [](const Mat3& R) {
    return json{{R(0, 0), R(0, 1), R(0, 2)}, {R(1, 0), R(1, 1), R(1, 2)}, {R(2, 0), R(2, 1), R(2, 2)}};
  };
  const Mat3 R = cam_R();
  const Vec3 t = cam_t();
  json j = {{"camera", {{"fx", 200}, {"fy", 200}, {"cx", 160}, {"cy", 120}, {"width", 320}, {"height", 240},
                        {"R_world_cam", mj(R)}, {"t_world_cam", {t.x(), t.y(), t.z()}}}},
            {"objects", json::array({{{"id", "obj00_box"}, {"family", "box"}, {"visible_fraction", 0.5},
                                      {"R", mj(Mat3::Identity())}, {"scale", {kSide, kSide, kSide}},
                                      {"t", {c.x(), c.y(), c.z()}}, {"mesh", "cube.obj"}}})}};
  simu::fs::atomic_write(dir + "/gt.json", j.dump(1));
  return dir + "/gt.json";
}

// A reconstruct-style scene (world = the camera) holding the cube at GT-world centre c, rotation R_w.
simu::physics::Scene camera_scene(const std::string& dir, const Vec3& c, const Mat3& R_w) {
  simu::physics::Scene s;
  simu::physics::SceneObject o;
  o.id = "obj00_box";
  o.mesh_path = dir + "/cube.obj";
  o.scale = Vec3::Constant(kSide);
  o.R = cam_R().transpose() * R_w;
  o.t = cam_R().transpose() * (c - cam_t());
  s.objects.push_back(o);
  return s;
}

}  // namespace

// The ground truth read back and carried through both camera poses scores IoU 1 before and after.
TEST(GtCompare, GroundTruthThroughTheCameraScoresOne) {
  const std::string dir = simu::testing::temp_dir("gt_compare_same");
  const Vec3 c = Vec3::Constant(kH / 2);
  const WorldGt gt = load_world_gt(write_gt(dir, c));
  ASSERT_EQ(gt.objects.size(), 1u);
  EXPECT_NEAR(gt.camera.t_world_cam.x(), 0.3, 1e-12);
  const auto s = camera_scene(dir, c, Mat3::Identity());
  const auto rows = compare_with_gt(s, s, {}, gt);
  ASSERT_EQ(rows.size(), 1u);
  ASSERT_TRUE(rows[0].before && rows[0].after) << rows[0].note;
  EXPECT_NEAR(*rows[0].before, 1.0, 1e-12);
  EXPECT_NEAR(*rows[0].after, 1.0, 1e-12);
  // The same pose read as if it were already in the GT world (the frame ignored) misses entirely.
  simu::physics::Scene wrong = s;
  wrong.camera.R_world_cam = cam_R();  // claims the scene world is the GT world
  wrong.camera.t_world_cam = cam_t();
  EXPECT_LT(*compare_with_gt(wrong, wrong, {}, gt)[0].before, 0.05);
  simu::fs::remove_tree(dir);
}

// A copy shifted by d = 12 voxels along the GT world's x axis: IoU (L - d) / (L + d) of two offset
// boxes, to within the lattice (each filled box spans L / h + 1 voxels per axis: 39 / 63 here).
TEST(GtCompare, ShiftedCopyScoresTheOffsetBoxesIou) {
  const std::string dir = simu::testing::temp_dir("gt_compare_shift");
  const Vec3 c = Vec3::Constant(kH / 2);
  const WorldGt gt = load_world_gt(write_gt(dir, c));
  const double d = 12 * kH;
  const auto before = camera_scene(dir, c, Mat3::Identity());
  // A quarter turn about the world's y axis maps the cube onto itself: only the shift counts.
  const Mat3 quarter = Eigen::AngleAxisd(M_PI / 2, Vec3::UnitY()).toRotationMatrix();
  const auto after = camera_scene(dir, c + Vec3(d, 0, 0), quarter);
  std::map<std::string, ProbeOutcome> outcomes{{"obj00_box", {"resample", true, false}}};
  const auto rows = compare_with_gt(before, after, outcomes, gt);
  ASSERT_TRUE(rows[0].after) << rows[0].note;
  EXPECT_NEAR(*rows[0].after, (kSide - d) / (kSide + d), 0.01);
  EXPECT_NEAR(*rows[0].after, 39.0 / 63.0, 1e-9);
  const json j = gt_rows_json(rows, "gt.json");
  EXPECT_EQ(j["objects"][0]["branch"], "resample");
  EXPECT_NEAR(j["mean_after"].get<double>(), 39.0 / 63.0, 1e-9);
  EXPECT_NE(format_gt_table(rows).find("resample (replaced)"), std::string::npos);
  EXPECT_FALSE(j["objects"][0]["forced_resample"].get<bool>());
  // Resampled because decision.force_resample named it: the table and the JSON say so.
  auto forced = rows;
  forced[0].probe.forced = true;
  EXPECT_NE(format_gt_table(forced).find("resample, forced (replaced)"), std::string::npos);
  EXPECT_TRUE(gt_rows_json(forced, "gt.json")["objects"][0]["forced_resample"].get<bool>());
  simu::fs::remove_tree(dir);
}

// The GT box in the camera frame is the AABB of the turned cube: centre R^T (c - t), half-extent
// |R^T| (side / 2) per axis (the AABB of a rotated box); the scene holding the GT scores box IoU 1.
TEST(GtCompare, GroundTruthBoxesInTheCameraFrame) {
  const std::string dir = simu::testing::temp_dir("gt_compare_boxes");
  const Vec3 c(0.1, -0.2, 0.05);
  const WorldGt gt = load_world_gt(write_gt(dir, c));
  const auto boxes = gt_boxes_in_camera(gt);
  ASSERT_EQ(boxes.count("obj00_box"), 1u);
  const auto& b = boxes.at("obj00_box");
  const Mat3 Rt = cam_R().transpose();
  const Vec3 centre = Rt * (c - cam_t());
  const Vec3 half = Rt.cwiseAbs() * Vec3::Constant(kSide / 2);
  EXPECT_LT((b.min - (centre - half)).norm(), 1e-9);
  EXPECT_LT((b.max - (centre + half)).norm(), 1e-9);
  // The predicted object of a scene holding the GT (camera frame) has the same world AABB.
  const auto s = camera_scene(dir, c, Mat3::Identity());
  simu::physics::PlacedShape p;
  p.canonical = simu::physics::read_mesh(dir + "/cube.obj");
  p.scale = s.objects[0].scale, p.R = s.objects[0].R, p.t = s.objects[0].t;
  EXPECT_NEAR(simu::physics::box_iou(simu::physics::world_aabb(p.world()), b), 1.0, 1e-9);
  simu::fs::remove_tree(dir);
}

// settled_scene takes each object's evaluation-settle pose from the probe's report by id (input or
// final), keeps objects without one, and names the object of a malformed pose; the settled GT scores 1.
TEST(GtCompare, SettledSceneTakesTheEvaluationPoses) {
  const std::string dir = simu::testing::temp_dir("gt_compare_settled");
  const Vec3 c = Vec3::Constant(kH / 2);
  const WorldGt gt = load_world_gt(write_gt(dir, c));
  const auto truth = camera_scene(dir, c, Mat3::Identity());
  const auto moved = camera_scene(dir, c + Vec3(0.3, 0, 0), Mat3::Identity());  // misses the GT entirely
  auto pose_j = [](const simu::physics::SceneObject& o) {
    const Mat3& R = o.R;
    return json{{"R", {{R(0, 0), R(0, 1), R(0, 2)}, {R(1, 0), R(1, 1), R(1, 2)}, {R(2, 0), R(2, 1), R(2, 2)}}},
                {"t", {o.t.x(), o.t.y(), o.t.z()}}};
  };
  // The final scene settled back onto the truth; the input scene has no settled pose (kept).
  const json report = {{"objects", {{{"id", "obj00_box"}, {"evaluation_pose", pose_j(truth.objects[0])}}}}};
  const auto after = settled_scene(moved, report, /*input=*/false);
  const auto before = settled_scene(moved, report, /*input=*/true);
  EXPECT_LT((after.objects[0].t - truth.objects[0].t).norm(), 1e-12);
  EXPECT_LT((before.objects[0].t - moved.objects[0].t).norm(), 1e-12);
  const auto rows = compare_with_gt(before, after, {}, gt);
  EXPECT_NEAR(*rows[0].after, 1.0, 1e-12);
  EXPECT_LT(*rows[0].before, 0.05);
  const json bad = {{"objects", {{{"id", "obj00_box"}, {"evaluation_pose", {{"R", 1}, {"t", {0, 0}}}}}}}};
  EXPECT_NE(simu::testing::error_of([&] { settled_scene(moved, bad, false); }).find("obj00_box"), std::string::npos);
  simu::fs::remove_tree(dir);
}

// An object missing from the final scene: unset with a note, counted 0 in the mean; the probe's report
// is read by id.
TEST(GtCompare, MissingObjectAndProbeReport) {
  const std::string dir = simu::testing::temp_dir("gt_compare_missing");
  const Vec3 c = Vec3::Constant(kH / 2);
  const WorldGt gt = load_world_gt(write_gt(dir, c));
  const auto rows = compare_with_gt(camera_scene(dir, c, Mat3::Identity()), simu::physics::Scene{}, {}, gt);
  EXPECT_TRUE(rows[0].before);
  EXPECT_FALSE(rows[0].after);
  EXPECT_NE(rows[0].note.find("not in the final scene"), std::string::npos);
  EXPECT_EQ(gt_rows_json(rows, "gt.json")["mean_after"].get<double>(), 0.0);
  const json report = {{"objects", {{{"id", "a"}, {"branch", "stretch"}, {"reverted", true}},
                                    {{"id", "b"}, {"branch", "resample"}, {"resample", {{"resampled", false}}}},
                                    {{"id", "c"}, {"branch", "resample"}, {"flags", json::array({"forced_resample"})}}}}};
  const auto out = probe_outcomes(report);
  EXPECT_EQ(out.at("a").branch, "stretch");
  EXPECT_TRUE(out.at("a").reverted);
  EXPECT_FALSE(out.at("b").resampled);
  EXPECT_FALSE(out.at("b").forced);
  EXPECT_TRUE(out.at("c").forced);
  EXPECT_NE(simu::testing::error_of([&] { load_world_gt(dir + "/nope.json"); }).find("nope.json"), std::string::npos);
  simu::fs::remove_tree(dir);
}
