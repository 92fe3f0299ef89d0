// Best-of-N resampling in the probe: several candidate shapes per object are settled in the probe's
// scene (earlier objects static) and the one that moves least is kept; every candidate's figure is
// reported. The candidates' stability differs in ways known from free-fall geometry.
#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <cmath>

#include "pipeline/physics/mesh.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/physics_test_util.h"
#include "tolerance.h"

using namespace simu::physics;
using simu::testing::physics_temp_dir;
using simu::testing::write_box;

namespace {

SceneObject box_object(const std::string& id, const std::string& mesh, const Vec3& size, const Vec3& t) {
  return simu::testing::placed_object(id, mesh, size, t);
}

// An empty scene: floor z = 0, gravity -z.
Scene floor_scene() {
  Scene s;
  s.gravity = Vec3(0, 0, -1);
  s.floor = Plane{"floor", Vec3::Zero(), Vec3::UnitZ()};
  return s;
}

ProbeShapeCandidate candidate(const std::string& label, const Vec3& size, const Mat3& R = Mat3::Identity()) {
  ProbeShapeCandidate c;
  c.label = label;
  c.mesh = box_mesh(Vec3::Constant(0.5));  // canonical unit cube
  c.scale = size;
  c.R = R;
  return c;
}

}  // namespace

// Scene: a 10 cm slab on the floor (placed first, static for the candidates), and a 20 cm cube whose
// reconstruction hovers 6 cm above the slab (rho = 0.06 / 0.2 = 0.3 -> resample). The stretched OBB
// spans z in [0.10, 0.36] (top kept, bottom on the slab): centre z = 0.23, side 0.26.
// Candidates, all placed at that centre:
//   0 "small":  10 cm cube -> falls onto the slab: 0.23 - (0.10 + 0.05) = 0.08 m (0.18 m without the slab);
//   1 "fit":    0.2 x 0.2 x 0.26 box, its bottom exactly on the slab -> moves ~0;
//   2 "tilted": the same box turned 35 deg about x -> pushed out of the slab, topples: moves centimetres;
//   3 "huge":   a 2 m cube -> penetration resolution needs > 0.3 m: not ok.
TEST(ProbeBestOfN, KeepsTheCandidateThatMovesLeast) {
  const auto dir = physics_temp_dir("best_of_n");
  Scene s = floor_scene();
  const auto mesh = write_box(dir, "cube", Vec3::Constant(0.5));
  s.objects.push_back(box_object("slab", mesh, Vec3(0.6, 0.6, 0.1), Vec3(0, 0, 0.05)));
  s.objects.push_back(box_object("box", mesh, Vec3::Constant(0.2), Vec3(0, 0, 0.1 + 0.06 + 0.1)));
  const ProbeConfig cfg = simu::testing::quick_probe_config();  // 1 s final settle, no CoACD
  const Mat3 tilt = Eigen::AngleAxisd(35.0 * M_PI / 180.0, Vec3::UnitX()).toRotationMatrix();
  int calls = 0;
  ResampleFn fn = [&](const std::vector<ProbeResampleRequest>& reqs) {
    ++calls;
    std::vector<ProbeResampleResult> out(reqs.size());
    for (auto& o : out) {
      o.ok = true;
      o.message = "4 candidates";
      o.candidates = {candidate("small", Vec3::Constant(0.1)), candidate("fit", Vec3(0.2, 0.2, 0.26)),
                      candidate("tilted", Vec3(0.2, 0.2, 0.26), tilt), candidate("huge", Vec3::Constant(2.0))};
    }
    return out;
  };
  const auto r = run_probe(s, cfg, dir + "/out", fn);
  EXPECT_EQ(calls, 1);
  const auto& d = r.diagnostics[1];
  ASSERT_EQ(d.branch, ProbeBranch::Resample) << d.message;
  // The 6 cm fall within 2 mm (contact sink, the impact's last step) over 0.2 m; the centre as much.
  EXPECT_NEAR(d.diagnosis.rho, 0.3, 0.01);
  EXPECT_NEAR(d.obb_target.center.z(), 0.23, 2e-3);
  ASSERT_EQ(d.candidates.size(), 4u) << d.message;
  for (const auto& c : d.candidates)
    std::printf("candidate %-7s ok %d displacement %.4f m rotation %.1f deg %s\n", c.label.c_str(), c.ok, c.displacement,
                c.rotation_deg, c.message.c_str());
  // The known figures.
  EXPECT_TRUE(d.candidates[0].ok);
  // Lands on the (static) slab, not the floor: 8 cm, the target's 2 mm and the sink and bounce (4 mm).
  EXPECT_NEAR(d.candidates[0].displacement, 0.08, 6e-3);
  EXPECT_TRUE(d.candidates[1].ok);
  EXPECT_LT(d.candidates[1].displacement, 4e-3);  // on the slab already: the target's 2 mm and the sink
  EXPECT_TRUE(d.candidates[2].ok);
  EXPECT_GT(d.candidates[2].displacement, 0.02);
  EXPECT_GT(d.candidates[2].rotation_deg, 10.0);
  EXPECT_FALSE(d.candidates[3].ok);
  EXPECT_NE(d.candidates[3].message.find("penetration"), std::string::npos) << d.candidates[3].message;
  // The fitting box wins and is what the scene ends with (its scale, at the OBB centre before settling).
  EXPECT_EQ(d.chosen_candidate, 1);
  EXPECT_TRUE(d.resampled);
  EXPECT_NEAR((d.t_resampled - Vec3(0, 0, 0.23)).norm(), 0.0, 2e-3);  // the target centre's 2 mm
  EXPECT_NEAR((r.scene.objects[1].scale - Vec3(0.2, 0.2, 0.26)).norm(), 0.0, simu::testing::kFp64Chain);
  EXPECT_NEAR(r.scene.objects[1].t.z(), 0.23, 5e-3);  // and its final settle (sink, last step)
  EXPECT_NEAR(d.obb_final.extents.z(), 0.26, 2e-3);
  // The report lists each candidate's figure and the winner.
  const auto rep = report_json(r);
  const auto& rs = rep["objects"][1]["resample"];
  ASSERT_EQ(rs["candidates"].size(), 4u);
  EXPECT_EQ(rs["chosen_candidate"].get<int>(), 1);
  EXPECT_TRUE(rs["candidates"][1]["chosen"].get<bool>());
  EXPECT_EQ(rs["candidates"][0]["label"].get<std::string>(), "small");
  EXPECT_NEAR(rs["candidates"][0]["displacement"].get<double>(), d.candidates[0].displacement, simu::testing::kFp64Chain);
  // Before: the placed 0.2 m box (its OBB fit's mm); after: the target's 2 mm.
  EXPECT_NEAR(rep["objects"][1]["change"]["obb_extents_before"][2].get<double>(), 0.2, 2e-3);
  EXPECT_NEAR(rep["objects"][1]["change"]["obb_extents_after"][2].get<double>(), 0.26, 2e-3);
}

// No candidate passes its checks -> nothing replaces the object: it keeps its input shape, flagged
// no_stable_candidate and resample_failed, and every candidate's figures are reported: a 3 m and a
// 2 m cube centred 0.13 m above the floor penetrate it by 1.37 m and 0.87 m.
TEST(ProbeBestOfN, NoStableCandidateKeepsTheInputShape) {
  const auto dir = physics_temp_dir("best_of_n_fail");
  Scene s = floor_scene();
  const auto mesh = write_box(dir, "cube", Vec3::Constant(0.5));
  s.objects.push_back(box_object("box", mesh, Vec3::Constant(0.2), Vec3(0, 0, 0.16)));
  ProbeConfig cfg = simu::testing::quick_probe_config();
  cfg.final_settle_time = 0.5;
  ResampleFn fn = [&](const std::vector<ProbeResampleRequest>& reqs) {
    std::vector<ProbeResampleResult> out(reqs.size());
    for (auto& o : out) {
      o.ok = true;
      o.candidates = {candidate("huger", Vec3::Constant(3.0)), candidate("huge", Vec3::Constant(2.0))};
    }
    return out;
  };
  const auto r = run_probe(s, cfg, "", fn);
  const auto& d = r.diagnostics[0];
  ASSERT_EQ(d.branch, ProbeBranch::Resample);
  ASSERT_EQ(d.candidates.size(), 2u);
  EXPECT_FALSE(d.candidates[0].ok);
  EXPECT_FALSE(d.candidates[1].ok);
  // The penetration resolution's total push for a 3 m / 2 m cube, to the loop's 7 mm step (1 cm).
  EXPECT_NEAR(d.candidates[0].penetration, 1.37, 0.01);
  EXPECT_NEAR(d.candidates[1].penetration, 0.87, 0.01);
  EXPECT_EQ(d.chosen_candidate, -1);
  EXPECT_FALSE(d.resampled);
  EXPECT_NE(std::find(d.flags.begin(), d.flags.end(), "no_stable_candidate"), d.flags.end());
  EXPECT_NE(std::find(d.flags.begin(), d.flags.end(), "resample_failed"), d.flags.end());
  EXPECT_NE(d.message.find("shallowest #1"), std::string::npos) << d.message;
  // The input shape (a 0.2 m cube) is kept.
  EXPECT_NEAR(r.scene.objects[0].scale.z(), 0.2, simu::testing::kFp64Chain);
  const auto rep = report_json(r);
  EXPECT_FALSE(rep["objects"][0]["resample"]["resampled"].get<bool>());
}
