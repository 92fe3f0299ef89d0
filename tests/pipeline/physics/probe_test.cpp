// Physics probe on hand-made scenes whose answers are known independently (free fall onto a
// floor, a box sunk into a table, a frame hanging on two pins, bad inputs).
#include <gtest/gtest.h>

#include <mujoco/mujoco.h>

#include <array>
#include <filesystem>
#include <fstream>

#include "pipeline/physics/mesh.h"
#include "pipeline/physics/mjcf.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/physics_test_util.h"
#include "tolerance.h"

using namespace simu::physics;
using simu::testing::physics_temp_dir;
using simu::testing::write_box;

namespace {

// The test room with a 640 x 480 camera (identity pose).
Scene room() { return simu::testing::test_room(500, 640, 480); }

SceneObject cube(const std::string& id, const std::string& mesh, double size, const Vec3& t) {
  return simu::testing::placed_object(id, mesh, Vec3::Constant(size), t);
}

ProbeConfig quick() { return simu::testing::quick_probe_config(); }

bool has_flag(const Diagnostics& d, const std::string& f) {
  return std::find(d.flags.begin(), d.flags.end(), f) != d.flags.end();
}

// Adds the 50 x 50 cm table slab (top face at z = 0.425) as a base; returns the unit cube's mesh path.
std::string add_table(const std::string& dir, Scene& s) {
  BaseBody table;
  table.id = "table";
  table.mesh_path = write_box(dir, "slab", Vec3(0.5, 0.5, 0.025));
  table.t = Vec3(0, 0, 0.4);
  s.bases.push_back(table);
  return write_box(dir, "cube", Vec3::Constant(0.5));
}

}  // namespace

// A 30 cm cube 3 cm above the floor falls 3 cm (v^2 = 2 g h independent: the first contact is where
// the bottom face meets z = 0); rho = 0.03 / 0.3 = 0.1 < 0.15 selects the stretch, which extends the
// bottom face to the floor and keeps the top face at 0.33 m.
TEST(Probe, HoveringBoxFallsThreeCentimetresAndIsStretched) {
  const auto dir = physics_temp_dir("hover");
  Scene s = room();
  const auto mesh = write_box(dir, "cube", Vec3::Constant(0.5));
  s.objects.push_back(cube("box", mesh, 0.3, Vec3(0, 0, 0.15 + 0.03)));
  const auto r = run_probe(s, quick(), dir + "/out");
  const auto& d = r.diagnostics[0];
  EXPECT_TRUE(d.flags.empty()) << d.message;
  // The fall: 3 cm less the contact sink (0.2 mm) and up to a timestep's motion at impact (0.77 m/s /
  // 480 Hz = 1.6 mm, ~0.8 mm on average): 1 mm; straight down: no sideways force on a flat face but
  // the solver's residual (1e-6 m).
  EXPECT_NEAR(d.dt_grv.z(), -0.03, 1e-3);
  EXPECT_NEAR(d.dt_grv.head<2>().norm(), 0.0, 1e-6);
  EXPECT_NEAR(d.dt_pen.norm(), 0.0, simu::testing::kFp64Solve);
  EXPECT_NEAR(d.diagnosis.rho, 0.1, 4e-3);  // the fall's 1 mm over 0.3 m, with room
  EXPECT_EQ(d.branch, ProbeBranch::Stretch);
  // Top face fixed at 0.33, bottom on the floor (after the final settle too).
  const auto& o = r.scene.objects[0];
  const double top = o.t.z() + 0.5 * o.scale.z(), bottom = o.t.z() - 0.5 * o.scale.z();
  // After the final settle: the fall's 1 mm and the contact sink's 2 mm.
  EXPECT_NEAR(top, 0.33, 3e-3);
  EXPECT_NEAR(bottom, 0.0, 3e-3);
  EXPECT_NEAR(o.scale.x(), 0.3, simu::testing::kFp64Chain);
  EXPECT_TRUE(std::filesystem::exists(dir + "/out/scene.json"));
  EXPECT_TRUE(std::filesystem::exists(dir + "/out/report.json"));
}

// A 20 cm cube sunk 2 cm into a table top (z = 0.425) is pushed up (against gravity) by the
// penetration loop by depth + 7 mm, then falls back 7 mm: net +2 cm, eta = -0.1 (shrink).
TEST(Probe, BoxSunkIntoTableIsPushedUp) {
  const auto dir = physics_temp_dir("sunk");
  Scene s = room();
  const auto mesh = add_table(dir, s);
  s.objects.push_back(cube("box", mesh, 0.2, Vec3(0, 0, 0.425 - 0.02 + 0.1)));
  const auto r = run_probe(s, quick(), dir + "/out");
  const auto& d = r.diagnostics[0];
  EXPECT_FALSE(d.physics_disabled) << d.message;
  // Pushed out upward by the depth plus the loop's 7 mm step, less than depth + two steps (3.4 cm);
  // sideways only by the solver's noise on a flat contact (1 mm); depth and net motion within the
  // contact sink (kContactSinkM); eta = net / 0.2 m within 2 mm / 0.2 = 0.01.
  EXPECT_GT(d.dt_pen.z(), 0.02);
  EXPECT_LT(d.dt_pen.z(), 0.035);
  EXPECT_NEAR(d.dt_pen.head<2>().norm(), 0.0, 1e-3);
  EXPECT_NEAR(d.pen_max_depth, 0.02, simu::testing::kContactSinkM);
  EXPECT_NEAR((d.dt_pen + d.dt_grv).z(), 0.02, simu::testing::kContactSinkM);
  EXPECT_NEAR(d.diagnosis.eta, -0.1, 0.01);
  EXPECT_EQ(d.branch, ProbeBranch::Stretch);
  // Final: resting on the table.
  const auto& o = r.scene.objects[0];
  EXPECT_NEAR(o.t.z() - 0.5 * o.scale.z(), 0.425, 4e-3);  // the sink twice (both settles)
}

// diagnostics.gravity = false (the ablation's "+ Pen." row): the sunk cube is pushed up as above but
// never dropped, decided or stretched (branch none, its 20 cm kept); the hovering cube of the first test
// keeps its 30 cm (no stretch to the floor) and reaches the floor only in the final settle.
TEST(Probe, WithoutGravityDiagnosticsOnlyPenetrationIsResolved) {
  const auto dir = physics_temp_dir("pen_only");
  Scene s = room();
  const auto mesh = add_table(dir, s);
  s.objects.push_back(cube("sunk", mesh, 0.2, Vec3(0, 0, 0.425 - 0.02 + 0.1)));
  s.objects.push_back(cube("hover", mesh, 0.3, Vec3(1.0, 0, 0.15 + 0.03)));
  ProbeConfig cfg = quick();
  cfg.gravity_diagnostics = false;
  const auto r = run_probe(s, cfg, dir + "/out");
  const auto& sunk = r.diagnostics[0];
  const auto& hover = r.diagnostics[1];
  EXPECT_FALSE(sunk.physics_disabled) << sunk.message;
  // The push: depth + one 7 mm step, as in BoxSunkIntoTableIsPushedUp; no fall measured.
  EXPECT_GT(sunk.dt_pen.z(), 0.02);
  EXPECT_LT(sunk.dt_pen.z(), 0.035);
  EXPECT_EQ(sunk.dt_grv.norm(), 0.0);
  EXPECT_EQ(hover.dt_grv.norm(), 0.0);
  EXPECT_EQ(sunk.branch, ProbeBranch::None);
  EXPECT_EQ(hover.branch, ProbeBranch::None);
  // Shapes kept; both at rest on their supports after the final settle (the contact sink, twice).
  const auto& o0 = r.scene.objects[0];
  const auto& o1 = r.scene.objects[1];
  EXPECT_NEAR(o0.scale.z(), 0.2, simu::testing::kFp64Chain);
  EXPECT_NEAR(o1.scale.z(), 0.3, simu::testing::kFp64Chain);
  EXPECT_NEAR(o0.t.z() - 0.5 * o0.scale.z(), 0.425, 4e-3);
  EXPECT_NEAR(o1.t.z() - 0.5 * o1.scale.z(), 0.0, 4e-3);
  // report.json: where the 5 s evaluation settles left the hovering cube, from the input (3 cm up) and
  // from the final scene: resting on the floor, its centre at half its side (the sink, twice).
  const auto j = report_json(r);
  EXPECT_NEAR(j["objects"][1]["evaluation_input_pose"]["t"][2].get<double>(), 0.15, 4e-3);
  EXPECT_NEAR(j["objects"][1]["evaluation_pose"]["t"][2].get<double>(), 0.15, 4e-3);
  EXPECT_NEAR(j["objects"][1]["evaluation_pose"]["R"][2][2].get<double>(), 1.0, 1e-3);  // still upright
}

// A 50 x 40 cm frame 2 cm thick, 2 mm off the wall, hung by two pins: it stays on the wall
// through the diagnostic and the final settle (small rotation about the pin line only).
TEST(Probe, FrameOnTwoPinsStaysOnTheWall) {
  const auto dir = physics_temp_dir("frame");
  Scene s = room();
  const auto mesh = write_box(dir, "frame", Vec3(0.5, 0.02, 0.4));
  SceneObject f = cube("frame", mesh, 0.5, Vec3(0, 1 - 0.002 - 0.01, 1.5));
  f.dof = PoseDof::LineAnchored;
  s.objects.push_back(f);
  // A free box on the floor under it, processed in the same run.
  s.objects.push_back(cube("box", write_box(dir, "cube", Vec3::Constant(0.5)), 0.2, Vec3(0, 0.5, 0.1)));
  const auto r = run_probe(s, quick(), dir + "/out");
  const auto& d = r.diagnostics[0];
  EXPECT_FALSE(d.physics_disabled) << d.message;
  EXPECT_EQ(d.branch, ProbeBranch::Anchored);
  ASSERT_EQ(d.pins_world.size(), 2u);
  // Pins at the top-back corners: y near the wall, z at the top, x at the left and right ends.
  // From the mesh file's fp32 vertices (u of a 0.25 m half-size: 1.5e-8 m) and float64 placement.
  for (const auto& p : d.pins_world) {
    EXPECT_NEAR(p.z(), 1.5 + 0.2, 1e-6);
    EXPECT_NEAR(p.y(), 1 - 0.002, 1e-6);
  }
  EXPECT_NEAR(std::abs(d.pins_world[0].x() - d.pins_world[1].x()), 0.5, 1e-6);
  EXPECT_NEAR(d.wall_points[0].y(), 1.0, simu::testing::kFp64Solve);
  const auto& o = r.scene.objects[0];
  EXPECT_FALSE(r.diagnostics[0].reverted);
  EXPECT_LT((o.t - f.t).norm(), 0.03);  // still where it hung (a swing about the pins of a few cm at most)
  const double wall_gap = 1.0 - (o.t.y() + 0.005);
  EXPECT_GT(wall_gap, -simu::testing::kContactSinkM);  // not through the wall (a contact's sink at most)
  EXPECT_LT(wall_gap, 0.05);    // not fallen away from it
  // The box on the floor stays put.
  EXPECT_LT((r.scene.objects[1].t - Vec3(0, 0.5, 0.1)).norm(), 0.01);
}

// The written scene.xml is a standalone MuJoCo model: it loads and simulates without warnings.
TEST(Probe, WrittenMjcfLoadsAndSimulatesInMuJoCo) {
  const auto dir = physics_temp_dir("mjcf");
  Scene s = room();
  const auto mesh = write_box(dir, "cube", Vec3(0.5, 0.3, 0.2));
  s.objects.push_back(cube("a", mesh, 0.3, Vec3(0, 0, 0.2)));
  s.objects.push_back(cube("b", mesh, 0.2, Vec3(0.05, 0, 0.4)));
  const auto r = run_probe(s, quick(), dir + "/out");
  auto m = load_mjcf_file(dir + "/out/scene.xml");
  EXPECT_EQ(m->nbody, 3);  // world + 2 objects
  EXPECT_NEAR(m->opt.timestep, 1.0 / 480, simu::testing::kFp64Solve);
  EXPECT_TRUE(m->opt.enableflags & mjENBL_MULTICCD);
  EXPECT_EQ(m->opt.integrator, mjINT_IMPLICIT);  // the paper's integrator
  // Each object: its mesh as a visual geom (group 2, no contacts) in its own colour, hulls in group 3.
  std::vector<std::array<float, 4>> visual_rgba;
  for (int g = 0; g < m->ngeom; ++g) {
    if (m->geom_bodyid[g] == 0) continue;
    const std::string name = mj_id2name(m.get(), mjOBJ_GEOM, g);
    if (name.find("/visual") != std::string::npos) {
      EXPECT_EQ(m->geom_group[g], 2) << name;
      EXPECT_EQ(m->geom_contype[g] | m->geom_conaffinity[g], 0) << name;
      visual_rgba.push_back({m->geom_rgba[4 * g], m->geom_rgba[4 * g + 1], m->geom_rgba[4 * g + 2], m->geom_rgba[4 * g + 3]});
    } else {
      EXPECT_EQ(m->geom_group[g], 3) << name;
      EXPECT_NE(m->geom_contype[g], 0) << name;
    }
  }
  ASSERT_EQ(visual_rgba.size(), 2u);
  EXPECT_NE(visual_rgba[0], visual_rgba[1]);
  // Contact margins written for users are zero (MuJoCo versions combine non-zero ones differently).
  for (int g = 0; g < m->ngeom; ++g) EXPECT_EQ(m->geom_margin[g], 0.0);
  auto d = make_data(m.get());
  for (int i = 0; i < 480; ++i) mj_step(m.get(), d.get());
  EXPECT_EQ(take_warnings(d.get()), 0);
  // Resting: the objects hardly move in one more second.
  for (int b = 1; b < m->nbody; ++b) EXPECT_LT(Eigen::Map<const Vec3>(d->xpos + 3 * b).z(), 1.0);
}

// Bad inputs never stop the run: each bad object gets a flag and a message, the good one is processed.
TEST(Probe, BadInputsAreFlaggedNotFatal) {
  const auto dir = physics_temp_dir("bad");
  const auto mesh = write_box(dir, "cube", Vec3::Constant(0.5));
  // A degenerate (flat, zero-area) mesh file.
  {
    Mesh flat;
    flat.V.resize(3, 3);
    flat.V << 0, 0, 0, 1, 0, 0, 2, 0, 0;
    flat.F.resize(1, 3);
    flat.F << 0, 1, 2;
    std::ofstream(dir + "/flat.obj") << "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n";
  }
  // An empty mesh file and a non-manifold one (three fins on one edge, plus a box's corners).
  std::ofstream(dir + "/empty.obj") << "# nothing\n";
  std::ofstream(dir + "/fins.obj") << "v -0.5 -0.5 -0.5\nv -0.5 0.5 0.5\nv 0.5 0 0\nv -0.5 0 0.5\nv 0.5 -0.5 0.5\n"
                                      "f 1 2 3\nf 1 2 4\nf 1 2 5\nf 3 4 5\n";
  std::ofstream(dir + "/scene.json") << R"({
    "gravity": [0,0,-1], "floor": {"point": [0,0,0], "normal": [0,0,1]},
    "walls": [{"id": "back", "point": [0,1,0], "normal": [0,-1,0]}],
    "objects": [
      {"id": "good", "mesh": "cube.obj", "scale": 0.2, "t": [0,0,0.1]},
      {"id": "missing", "mesh": "nope.obj", "scale": 0.2, "t": [1,0,0.1]},
      {"id": "nan", "mesh": "cube.obj", "scale": 0.2, "t": [0,null,0.1]},
      {"id": "flat", "mesh": "flat.obj", "scale": 0.2, "t": [0.5,0,0.1]},
      {"id": "below", "mesh": "cube.obj", "scale": 0.2, "t": [0,0,-3]},
      {"id": "behind", "mesh": "cube.obj", "scale": 0.2, "t": [0,2,0.5]},
      {"id": "hang_nowall", "mesh": "cube.obj", "scale": 0.2, "t": [0,0,1], "dof": "point_anchored", "wall": "none"},
      {"id": "negscale", "mesh": "cube.obj", "scale": -0.2, "t": [0.3,0,0.1]},
      {"id": "empty", "mesh": "empty.obj", "scale": 0.2, "t": [-0.5,0,0.1]},
      {"id": "fins", "mesh": "fins.obj", "scale": 0.2, "t": [-0.5,-0.5,0.1]}
    ]})";
  const Scene s = load_scene(dir + "/scene.json");
  ProbeResult r;
  ASSERT_NO_THROW(r = run_probe(s, quick(), dir + "/out"));
  ASSERT_EQ(r.diagnostics.size(), 10u);
  EXPECT_TRUE(r.diagnostics[0].flags.empty()) << r.diagnostics[0].message;
  EXPECT_EQ(r.diagnostics[0].order, 0);
  EXPECT_TRUE(has_flag(r.diagnostics[1], "mesh_error"));
  EXPECT_NE(r.diagnostics[1].message.find("nope.obj"), std::string::npos) << r.diagnostics[1].message;
  EXPECT_TRUE(has_flag(r.diagnostics[2], "bad_input"));
  EXPECT_TRUE(has_flag(r.diagnostics[3], "mesh_error")) << r.diagnostics[3].message;
  EXPECT_TRUE(has_flag(r.diagnostics[4], "outside_room"));
  EXPECT_TRUE(has_flag(r.diagnostics[5], "outside_room"));
  EXPECT_TRUE(has_flag(r.diagnostics[6], "no_wall"));
  EXPECT_TRUE(has_flag(r.diagnostics[7], "bad_input"));
  EXPECT_NE(r.diagnostics[7].message.find("scale"), std::string::npos) << r.diagnostics[7].message;
  EXPECT_TRUE(has_flag(r.diagnostics[8], "mesh_error"));
  EXPECT_NE(r.diagnostics[8].message.find("empty.obj"), std::string::npos) << r.diagnostics[8].message;
  for (int i = 1; i < 9; ++i) EXPECT_TRUE(r.diagnostics[i].physics_disabled) << i;
  // The non-manifold mesh is flagged, named, and still simulated through its convex hull.
  EXPECT_TRUE(has_flag(r.diagnostics[9], "non_manifold")) << r.diagnostics[9].message;
  EXPECT_NE(r.diagnostics[9].message.find("fins.obj"), std::string::npos) << r.diagnostics[9].message;
  EXPECT_FALSE(r.diagnostics[9].physics_disabled) << r.diagnostics[9].message;
  // The good object is solved as if alone.
  EXPECT_FALSE(r.diagnostics[0].physics_disabled);
  EXPECT_LT(r.diagnostics[0].evaluation.displacement, 0.01);
  EXPECT_TRUE(std::filesystem::exists(dir + "/out/report.json"));
  EXPECT_NO_THROW(load_mjcf_file(dir + "/out/scene.xml"));
}

// A large gravity-axis displacement (rho >= 0.15) selects resampling; without a resampler the
// hand-off (target OBB whose top face is the pre-simulation top, auxiliary mask) is written; with
// one, its mesh is placed at the target OBB centre.
TEST(Probe, LargeDropSelectsResampleAndHandsOff) {
  const auto dir = physics_temp_dir("resample");
  Scene s = room();
  s.camera.R_world_cam << 1, 0, 0, 0, 0, 1, 0, -1, 0;  // camera looking along +y, image y down = -z
  s.camera.t_world_cam = Vec3(0, -2, 0.3);
  const auto mesh = write_box(dir, "cube", Vec3::Constant(0.5));
  s.objects.push_back(cube("box", mesh, 0.2, Vec3(0, 0, 0.1 + 0.06)));  // rho = 0.3
  const auto r = run_probe(s, quick(), dir + "/out");
  const auto& d = r.diagnostics[0];
  EXPECT_EQ(d.branch, ProbeBranch::Resample);
  EXPECT_NEAR(d.diagnosis.rho, 0.3, 0.01);  // 6 cm fall within 2 mm (sink, last step) over 0.2 m
  EXPECT_TRUE(has_flag(d, "needs_resample"));
  ASSERT_EQ(r.resample_requests.size(), 1u);
  const auto& q = r.resample_requests[0];
  // The stretched box: the fall's 2 mm on its extent and centre.
  EXPECT_NEAR(q.target_obb.extents.z(), 0.26, 2e-3);
  EXPECT_NEAR(q.target_obb.center.z() + 0.13, 0.26, 2e-3);  // top face kept at 0.26
  EXPECT_TRUE(std::filesystem::exists(dir + "/out/resample/box/request.json"));
#ifdef SIMU_HAVE_OPENCV
  ASSERT_FALSE(q.aux_mask.empty());
  EXPECT_GT(cv::countNonZero(q.aux_mask), 0);
#endif
  // With a resampler: a flatter box returned; it is placed at the target centre, then settles.
  ResampleFn rs = [&](const std::vector<ProbeResampleRequest>& reqs) {
    std::vector<ProbeResampleResult> out(reqs.size());
    for (auto& o : out) {
      o.ok = true;
      o.mesh = box_mesh(Vec3(0.5, 0.5, 0.5));
      o.scale = Vec3(0.2, 0.2, 0.26);
    }
    return out;
  };
  const auto r2 = run_probe(s, quick(), dir + "/out2", rs);
  EXPECT_FALSE(has_flag(r2.diagnostics[0], "resample_failed")) << r2.diagnostics[0].message;
  EXPECT_NEAR(r2.scene.objects[0].t.z(), 0.13, 5e-3);  // the target's 2 mm, then its settle's sink and last step
  EXPECT_NEAR(r2.scene.objects[0].scale.z(), 0.26, simu::testing::kFp64Chain);
}

// decision.force_resample: of two boxes that fall 3 cm (rho 0.1 < 0.15: the rule stretches both), the
// named one is resampled (flagged, its rule's branch and rho kept in the diagnosis) and is the only one
// handed to the resampler; the other is stretched as without the key. An id the scene lacks is an error
// naming the key and the id.
TEST(Probe, ForceResampleResamplesTheNamedObjectWhateverItsRho) {
  const auto dir = physics_temp_dir("force_resample");
  Scene s = room();
  const auto mesh = write_box(dir, "cube", Vec3::Constant(0.5));
  s.objects.push_back(cube("a", mesh, 0.3, Vec3(-0.4, 0.5, 0.15 + 0.03)));
  s.objects.push_back(cube("b", mesh, 0.3, Vec3(0.4, 0.5, 0.15 + 0.03)));
  ProbeConfig cfg = quick();
  cfg.force_resample = {"b"};
  std::vector<std::string> handed;
  ResampleFn rs = [&](const std::vector<ProbeResampleRequest>& reqs) {
    for (const auto& q : reqs) handed.push_back(q.object_id);
    return std::vector<ProbeResampleResult>(reqs.size());  // not ok: the object keeps its input shape
  };
  const auto r = run_probe(s, cfg, "", rs);
  const auto &a = r.diagnostics[0], &b = r.diagnostics[1];
  EXPECT_LT(a.diagnosis.rho, cfg.rho_threshold);
  EXPECT_LT(b.diagnosis.rho, cfg.rho_threshold);
  EXPECT_EQ(a.branch, ProbeBranch::Stretch);
  EXPECT_FALSE(has_flag(a, "forced_resample"));
  EXPECT_EQ(b.branch, ProbeBranch::Resample);
  EXPECT_EQ(b.diagnosis.branch, Branch::Stretch);  // what the rule said
  EXPECT_TRUE(has_flag(b, "forced_resample")) << b.message;
  EXPECT_EQ(handed, std::vector<std::string>{"b"});
  ASSERT_EQ(r.resample_requests.size(), 1u);
  EXPECT_EQ(r.resample_requests[0].object_id, "b");
  // Without the key both are stretched and nothing is handed over.
  handed.clear();
  const auto plain = run_probe(s, quick(), "", rs);
  EXPECT_EQ(plain.diagnostics[1].branch, ProbeBranch::Stretch);
  EXPECT_TRUE(handed.empty());
  // A misspelt id stops the run, naming the key and the id.
  cfg.force_resample = {"c"};
  try {
    (void)run_probe(s, cfg, "", rs);
    ADD_FAILURE() << "no error for an unknown id";
  } catch (const std::exception& e) {
    EXPECT_NE(std::string(e.what()).find("decision.force_resample"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("'c'"), std::string::npos) << e.what();
  }
}

// Two pins on a coarse, slightly tilted frame: the top region holds one corner, but the pins must
// still be the frame's top-left and top-right (apart by most of its width), not one point twice.
TEST(Probe, TwoPinsOnATiltedCoarseFrameAreApart) {
  // A 1 m wide, 0.8 m tall, 4 cm deep frame (8 vertices), tilted 8 degrees about the wall normal: the
  // top 10% of its height then holds only the higher top corner.
  Mesh frame = box_mesh(Vec3(0.5, 0.02, 0.4));
  const Eigen::Matrix3d R = Eigen::AngleAxisd(8.0 * M_PI / 180.0, Vec3::UnitY()).toRotationMatrix();
  for (Eigen::Index i = 0; i < frame.V.rows(); ++i)
    frame.V.row(i) = (R * frame.V.row(i).transpose() + Vec3(0, 0.5, 1.5)).transpose();
  Plane wall;  // the wall y = 0.54 behind the frame, facing -y; gravity -z
  wall.point = Vec3(0, 0.54, 0);
  wall.normal = Vec3(0, -1, 0);
  const auto pins = choose_pins(frame, wall, Vec3(0, 0, -9.81), 2, 0.1);
  ASSERT_EQ(pins.size(), 2u);
  // The lateral axis is x: the pins sit near the two top corners, about 1 m apart.
  EXPECT_GT(std::abs(pins[0].x() - pins[1].x()), 0.9);
  // Both on the top edge (within the tilt's height change across the width: sin 8 deg x 1 m).
  const double top = frame.V.col(2).maxCoeff();
  for (const auto& p : pins) EXPECT_GT(p.z(), top - std::sin(8.0 * M_PI / 180.0) * 1.0 - simu::testing::kFp64Solve);
  // Back side (towards the wall).
  for (const auto& p : pins) EXPECT_GT(p.y(), 0.5);
}
