// Physics metrics of the probe's settles (supplementary "Metrics") on hand-made scenes whose answers
// are known independently: a box resting on the floor (stable, no penetration), a box sunk 2 cm
// (penetrating before correction, not after the probe), a box dropped from 1 m (displacement 1 m,
// peak kinetic energy m g h), report.json contents, and the overlay PNG.
#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <filesystem>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

#include "common/fs.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/physics_test_util.h"
#include "tolerance.h"

using namespace simu::physics;
using simu::testing::physics_temp_dir;
using simu::testing::write_box;

namespace {

// The test room with a 160 x 120 camera at (0, -2, 0.3) looking along +y.
Scene room() {
  Scene s = simu::testing::test_room(200, 160, 120);
  s.camera.R_world_cam << 1, 0, 0, 0, 0, 1, 0, -1, 0;
  s.camera.t_world_cam = Vec3(0, -2, 0.3);
  return s;
}

SceneObject box(const std::string& id, const std::string& mesh, double size, const Vec3& t) {
  return simu::testing::placed_object(id, mesh, Vec3::Constant(size), t);
}

ProbeConfig quick() { return simu::testing::quick_probe_config(); }

}  // namespace

// A 30 cm cube whose bottom face lies exactly on the floor: stays put over the 5 s settle, no contact
// deeper than 2 mm at the start or the end, counted stable.
TEST(PhysicsMetrics, BoxRestingOnTheFloorIsStableWithoutPenetration) {
  const auto dir = physics_temp_dir("metrics_rest");
  Scene s = room();
  s.objects.push_back(box("box", write_box(dir, "cube", Vec3::Constant(0.5)), 0.3, Vec3(0, 0, 0.15)));
  const PhysicsEvaluation ev = evaluate_physics(s, quick(), 5.0);
  ASSERT_TRUE(ev.ran) << ev.message;
  const SettleRecord& r = ev.objects[0];
  EXPECT_EQ(r.category, MetricCategory::Free);
  EXPECT_FALSE(r.physics_disabled);
  EXPECT_FALSE(r.initially_penetrating);
  // Placed exactly on the floor: MuJoCo's convex collision finds depth 0 to its tolerance (1e-6 m);
  // then resting: the contact sink (kContactSinkM). The overdamped (ratio 2) sink of 0.2 mm turns only
  // part of m g sink = 13.5 kg x 9.81 x 2e-4 m = 0.026 J into motion: 0.01 J.
  EXPECT_LT(r.initial_penetration, 1e-6);
  EXPECT_LT(r.max_penetration, simu::testing::kContactSinkM);
  EXPECT_LT(r.displacement, simu::testing::kContactSinkM);
  EXPECT_LT(r.peak_kinetic_energy, 0.01);
  EXPECT_EQ(ev.metrics.stability_count, 1);
  EXPECT_DOUBLE_EQ(ev.metrics.stability, 100.0);
  EXPECT_DOUBLE_EQ(ev.metrics.penetration_ratio, 0.0);
}

// A 20 cm cube sunk 2 cm into the floor: before correction its deepest contact is 2 cm (> 2 mm), it
// counts as initially penetrating and is left out of the stability denominator. After the probe
// (pushed out, stretched down to the floor, settled) the evaluation finds no penetration and it is stable.
TEST(PhysicsMetrics, SunkBoxPenetratesBeforeCorrectionNotAfter) {
  const auto dir = physics_temp_dir("metrics_sunk");
  Scene s = room();
  s.objects.push_back(box("box", write_box(dir, "cube", Vec3::Constant(0.5)), 0.2, Vec3(0, 0, 0.1 - 0.02)));
  const PhysicsEvaluation before = evaluate_physics(s, quick(), 5.0);
  ASSERT_TRUE(before.ran) << before.message;
  // 2 cm by construction, measured by MuJoCo's collision on the convex hulls (1 mm: its mesh margin).
  EXPECT_NEAR(before.objects[0].initial_penetration, 0.02, 1e-3);
  EXPECT_TRUE(before.objects[0].initially_penetrating);
  EXPECT_EQ(before.metrics.stability_count, 0);
  EXPECT_DOUBLE_EQ(before.metrics.initial_penetration_ratio, 100.0);
  // MuJoCo's soft contact pushes it out during the settle: about 2 cm of motion, energy released.
  // (2 cm pushed out, the contact sink's 2 mm either way, and 2 mm of overshoot of the push)
  EXPECT_NEAR(before.objects[0].displacement, 0.02, 4e-3);
  EXPECT_GT(before.objects[0].peak_kinetic_energy, 0.0);

  const ProbeResult r = run_probe(s, quick(), "");
  const SettleRecord& after = r.diagnostics[0].evaluation;
  EXPECT_FALSE(after.physics_disabled) << r.diagnostics[0].message;
  EXPECT_FALSE(after.initially_penetrating);
  // Resting after the correction: the contact sink; the displacement adds the correction's residual 3 mm.
  EXPECT_LT(after.initial_penetration, simu::testing::kContactSinkM);
  EXPECT_LT(after.max_penetration, simu::testing::kContactSinkM);
  EXPECT_LT(after.displacement, 0.005);
  EXPECT_EQ(r.evaluation.metrics.stability_count, 1);
  EXPECT_DOUBLE_EQ(r.evaluation.metrics.stability, 100.0);
  EXPECT_DOUBLE_EQ(r.evaluation.metrics.penetration_ratio, 0.0);
  EXPECT_DOUBLE_EQ(r.evaluation.metrics.initial_penetration_ratio, 0.0);
}

// A 20 cm cube (density 500 kg/m^3: m = 500 * 0.2^3 = 4 kg) released with its bottom 1 m above the
// floor falls 1 m and comes to rest: displacement 1 m, peak kinetic energy m g h = 39.24 J (at impact).
TEST(PhysicsMetrics, BoxDroppedFromOneMetre) {
  const auto dir = physics_temp_dir("metrics_drop");
  Scene s = room();
  SceneObject o = box("box", write_box(dir, "cube", Vec3::Constant(0.5)), 0.2, Vec3(0, 0, 1.0 + 0.1));
  o.density = 500;
  s.objects.push_back(o);
  const PhysicsEvaluation ev = evaluate_physics(s, quick(), 5.0);
  ASSERT_TRUE(ev.ran) << ev.message;
  const SettleRecord& r = ev.objects[0];
  const double mass = 500.0 * 0.2 * 0.2 * 0.2, g = 9.81, h = 1.0;
  // A 1 m fall: the landing's sink and bounce (~1 cm); the kinetic energy at impact m g h, less the
  // implicit integrator's damping over ~0.45 s (3%).
  EXPECT_NEAR(r.displacement, h, 0.01);
  EXPECT_NEAR(r.peak_kinetic_energy, mass * g * h, 0.03 * mass * g * h);
  EXPECT_NEAR(ev.scene_peak_energy, r.peak_kinetic_energy, simu::testing::kFp64Solve);
  EXPECT_LT(r.max_penetration, simu::testing::kContactSinkM);
  // 1 m > 5 cm: not stable.
  EXPECT_DOUBLE_EQ(ev.metrics.stability, 0.0);
  EXPECT_NEAR(ev.metrics.mean_displacement, h, 0.01);  // the one object's, as above
}

// A frame on two wall pins is a hanging object: recorded, left out of the stability denominator. The
// probe's report.json carries the per-object records and the metrics; a bad object is disabled.
TEST(PhysicsMetrics, ReportCarriesRecordsAndMetrics) {
  const auto dir = physics_temp_dir("metrics_report");
  Scene s = room();
  SceneObject f = box("frame", write_box(dir, "frame", Vec3(0.5, 0.02, 0.4)), 0.5, Vec3(0, 1 - 0.002 - 0.01, 1.5));
  f.dof = PoseDof::LineAnchored;
  s.objects.push_back(f);
  s.objects.push_back(box("box", write_box(dir, "cube", Vec3::Constant(0.5)), 0.2, Vec3(0.5, 0.3, 0.1)));
  s.objects.push_back(box("missing", dir + "/nope.obj", 0.2, Vec3(-0.5, 0.3, 0.1)));
  const ProbeResult r = run_probe(s, quick(), dir + "/out");
  EXPECT_EQ(r.diagnostics[0].evaluation.category, MetricCategory::Hanging);
  EXPECT_FALSE(r.diagnostics[0].evaluation.physics_disabled);
  EXPECT_LT(r.diagnostics[0].evaluation.displacement, 0.01);  // stays on its pins (the pins' equality spring: < 1 cm)
  EXPECT_TRUE(r.diagnostics[2].evaluation.physics_disabled);
  EXPECT_EQ(r.evaluation.metrics.stability_count, 1);  // the box only
  EXPECT_EQ(r.evaluation.metrics.evaluated_count, 2);
  EXPECT_EQ(r.evaluation.metrics.disabled_count, 1);
  const auto j = nlohmann::json::parse(simu::fs::read_file(dir + "/out/report.json"));
  ASSERT_TRUE(j.contains("metrics"));
  EXPECT_DOUBLE_EQ(j["metrics"]["stability"].get<double>(), r.evaluation.metrics.stability);
  EXPECT_EQ(j["metrics"]["evaluated_count"].get<int>(), 2);
  const auto& e0 = j["objects"][0];
  EXPECT_EQ(e0["evaluation"]["category"], "hanging");
  EXPECT_EQ(e0["final_settle"]["category"], "hanging");
  for (const char* key : {"displacement", "initial_penetration", "final_penetration", "peak_kinetic_energy",
                          "initially_penetrating", "physics_disabled"})
    EXPECT_TRUE(e0["evaluation"].contains(key)) << key;
  EXPECT_TRUE(j["objects"][2]["evaluation"]["physics_disabled"].get<bool>());
}

// The probe writes DIR/overlay.png at the camera's image size.
TEST(PhysicsMetrics, ProbeWritesOverlayOfTheImageSize) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "overlay.png needs OpenCV (built with SIMU_WITH_OPENCV=OFF): the probe logs that it skips it";
#else
  const auto dir = physics_temp_dir("metrics_overlay");
  Scene s = room();
  s.objects.push_back(box("box", write_box(dir, "cube", Vec3::Constant(0.5)), 0.2, Vec3(0, 0, 0.16)));  // rho 0.3
  const ProbeResult r = run_probe(s, quick(), dir + "/out");
  ASSERT_TRUE(std::filesystem::exists(dir + "/out/overlay.png"));
  const cv::Mat img = cv::imread(dir + "/out/overlay.png", cv::IMREAD_UNCHANGED);
  ASSERT_FALSE(img.empty());
  EXPECT_EQ(img.cols, 160);
  EXPECT_EQ(img.rows, 120);
  EXPECT_EQ(img.channels(), 3);
  // Something was drawn: not every pixel is the grey background.
  cv::Mat grey(img.rows, img.cols, CV_8UC3, cv::Scalar(96, 96, 96));
  EXPECT_GT(cv::countNonZero(cv::Mat(cv::abs(img - grey)).reshape(1)), 0);
#endif
}
