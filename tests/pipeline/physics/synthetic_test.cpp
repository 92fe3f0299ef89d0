// Synthetic scene generator: ground truth consistent with its supports, injected errors as recorded,
// masks rendered, the ideal-probe decisions matching the injected error types, files written and
// read back through the scene loader; the benchmark's "after" metrics score the probe's output.
#include "pipeline/physics/synthetic.h"

#include "test_files.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include <filesystem>

using namespace simu::physics;

namespace {
Mesh placed(const Mesh& m, const Vec3& s, const Mat3& R, const Vec3& t) {
  Mesh w = m;
  w.V = (m.V * (R * s.asDiagonal()).transpose()).rowwise() + t.transpose();
  return w;
}
}  // namespace

// Canonical primitives follow the SAM3D convention.
TEST(Synthetic, CanonicalPrimitives) {
  for (const Mesh& m : {canonical_box_mesh(Vec3(0.2, 0.5, 0.1)), lathe_mesh({{0, 0.02}, {0.1, 0.05}, {0.3, 0.05}})}) {
    const Vec3 lo = m.V.colwise().minCoeff().transpose(), hi = m.V.colwise().maxCoeff().transpose();
    EXPECT_LT((lo + hi).norm(), simu::testing::kFp64Chain);
    EXPECT_NEAR((hi - lo).maxCoeff(), 1.0, simu::testing::kFp64Chain);
  }
  // Lathe: closed and outward (positive signed volume = pi r^2 h for a cylinder, up to the polygon).
  const Mesh cyl = lathe_mesh({{0, 0.5}, {1.0, 0.5}}, 64);
  double vol = 0;
  for (Eigen::Index f = 0; f < cyl.F.rows(); ++f) {
    const Vec3 a = cyl.V.row(cyl.F(f, 0)), b = cyl.V.row(cyl.F(f, 1)), c = cyl.V.row(cyl.F(f, 2));
    vol += a.dot(b.cross(c)) / 6;
  }
  const double polygon_area = 0.5 * 64 * 0.25 * std::sin(2 * 3.14159265358979 / 64);
  EXPECT_NEAR(vol, polygon_area * 1.0, simu::testing::kFp64Solve);
}

// Ground truth rests on its support; errors are applied as recorded; oracle decisions match.
TEST(Synthetic, GroundTruthErrorsAndDecisions) {
  SyntheticConfig cfg;
  int n_free = 0, n_cut = 0, n_hang = 0;
  for (uint64_t seed = 0; seed < 12; ++seed) {
    cfg.layout = seed % 2 ? "shelf" : "tabletop";
    const SyntheticScene s = generate_scene(cfg, seed, "t");
    ASSERT_FALSE(s.objects.empty());
    for (const SyntheticObject& o : s.objects) {
      const Mesh gt = placed(o.gt_mesh, o.gt_scale, o.gt_R, o.gt_t);
      const Mesh pr = placed(o.pred_mesh, o.pred_scale, o.pred_R, o.pred_t);
      if (o.dof != PoseDof::Free) {
        ++n_hang;
        // Hanging objects stay in front of the wall.
        EXPECT_LT(gt.V.col(2).maxCoeff(), s.walls[0].point.z());
        continue;
      }
      ++n_free;
      EXPECT_NEAR(gt.V.col(1).maxCoeff(), o.support_y, simu::testing::kFp64Solve) << o.id;
      const double h = gt.V.col(1).maxCoeff() - gt.V.col(1).minCoeff();
      // Injected error as recorded: bottom offsets / cut heights / top kept.
      switch (o.error) {
        case InjectedError::Hover: EXPECT_NEAR(pr.V.col(1).maxCoeff(), o.support_y - o.magnitude, simu::testing::kFp64Solve); break;
        case InjectedError::Sink: EXPECT_NEAR(pr.V.col(1).maxCoeff(), o.support_y + o.magnitude, simu::testing::kFp64Solve); break;
        case InjectedError::BottomCut:
          ++n_cut;
          EXPECT_NEAR(pr.V.col(1).minCoeff(), gt.V.col(1).minCoeff(), simu::testing::kFp64Solve);
          EXPECT_NEAR(pr.V.col(1).maxCoeff() - pr.V.col(1).minCoeff(), (1 - o.magnitude) * h, simu::testing::kFp64Solve);
          break;
        default: break;
      }
      EXPECT_EQ(o.modal_mask.width, cfg.width);
    }
    // The ideal probe + rho criterion picks the expected branch for every free object.
    const SceneEvaluation ev = evaluate_scene(s, CorrectionConfig{});
    for (const ObjectOutcome& oc : ev.objects) {
      EXPECT_EQ(oc.got, oc.expected) << oc.id << " error " << to_string(oc.error) << " rho " << oc.rho;
      // Upright errors: the stretch lands the bottom exactly on the support. A tilted object is
      // stretched along its tilted OBB axis, so its lowest point lands only approximately.
      if (oc.got == Branch::Stretch && oc.error != InjectedError::Rotation)
        EXPECT_LT(oc.support_gap_after, simu::testing::kFp64Solve) << oc.id << " " << to_string(oc.error);
      // (a rotation error is not the stretch's to undo: it keeps at most a fifth of the gap, plus the
      // mesh files' fp32 storage, 1e-6 m)
      if (oc.error == InjectedError::Rotation) EXPECT_LE(oc.support_gap_after, 0.2 * oc.support_gap_before + 1e-6) << oc.id;
    }
    // Stretching cannot make the boxes worse than the errors on average.
    EXPECT_GE(ev.box_after.iou + simu::testing::kFp64Solve, ev.box_before.iou - 0.05);
  }
  EXPECT_GT(n_free, 30);
  EXPECT_GT(n_cut, 3);
  EXPECT_GT(n_hang, 2);
}

// Written scenes load back through the scene loader with their synthetic records and masks.
TEST(Synthetic, WriteAndReload) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "mask PNGs need OpenCV (built with SIMU_WITH_OPENCV=OFF)";
#endif
  SyntheticConfig cfg;
  cfg.write_depth = true;
  const SyntheticScene s = generate_scene(cfg, 3, "w");
  const std::string dir = simu::testing::temp_dir("synthetic_write");
  write_scene_dir(s, dir);
  const Scene sc = load_scene(dir + "/scene.json");
  ASSERT_EQ(sc.objects.size(), s.objects.size());
  for (size_t i = 0; i < sc.objects.size(); ++i) {
    EXPECT_TRUE(sc.objects[i].error.empty()) << sc.objects[i].error;
    EXPECT_TRUE(std::filesystem::exists(sc.objects[i].mesh_path));
    EXPECT_TRUE(std::filesystem::exists(sc.objects[i].mask_path));
    EXPECT_EQ(sc.objects[i].extra["synthetic"]["error"], to_string(s.objects[i].error));
    EXPECT_LT((sc.objects[i].t - s.objects[i].pred_t).norm(), simu::testing::kFp64Solve);
  }
  EXPECT_TRUE(std::filesystem::exists(dir + "/depth.png"));
  EXPECT_TRUE(std::filesystem::exists(dir + "/rgb.png"));
}

#include "pipeline/physics/overlay.h"
#include "tolerance.h"

// The committed default set (tests/testdata/scenes) loads, and every free object has a modal mask of the
// camera's size with pixels in it.
TEST(Synthetic, CommittedDefaultScenes) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "mask PNGs need OpenCV (built with SIMU_WITH_OPENCV=OFF)";
#endif
  const std::string root = simu::testing::source_dir() + "/tests/testdata/scenes";
  int scenes = 0;
  for (const auto& e : std::filesystem::directory_iterator(root)) {
    const Scene sc = load_scene((e.path() / "scene.json").string());
    ++scenes;
    EXPECT_FALSE(sc.objects.empty());
    for (const SceneObject& o : sc.objects) {
      EXPECT_TRUE(o.error.empty()) << o.id << ": " << o.error;
      if (o.dof != PoseDof::Free) continue;
      const BinaryMask m = read_mask(o.mask_path);
      EXPECT_EQ(m.width, sc.camera.width);
      EXPECT_GT(m.count(), 0) << o.id;
      EXPECT_TRUE(o.extra.contains("synthetic"));
    }
  }
  EXPECT_EQ(scenes, 3);
}

namespace {
// World AABB of a box of full extents e placed at (R, t), from its 8 corners.
Box3 box_aabb(const Vec3& e, const Mat3& R, const Vec3& t) {
  Box3 b{Vec3::Constant(1e300), Vec3::Constant(-1e300)};
  for (int c = 0; c < 8; ++c) {
    const Vec3 local(((c & 1) ? 0.5 : -0.5) * e.x(), ((c & 2) ? 0.5 : -0.5) * e.y(), ((c & 4) ? 0.5 : -0.5) * e.z());
    const Vec3 w = R * local + t;
    b.min = b.min.cwiseMin(w), b.max = b.max.cwiseMax(w);
  }
  return b;
}
// IoU of two axis-aligned boxes (written out here, not metrics.h's box_iou).
double aabb_iou(const Box3& a, const Box3& b) {
  const Vec3 lo = a.min.cwiseMax(b.min), hi = a.max.cwiseMin(b.max);
  const double inter = (hi - lo).cwiseMax(0.0).prod();
  return inter / ((a.max - a.min).prod() + (b.max - b.min).prod() - inter);
}
}  // namespace

// The "after" column scores the probe's corrected scene, not a stretch re-applied to the input. A
// 10 x 16 x 10 cm box is reconstructed tilted 12 degrees about the camera axis, balanced on one bottom
// edge 1 mm above the floor: the diagnostics see (almost) no displacement, so the stretch is the
// identity and a stretch re-applied to the input keeps the tilt; the probe's final joint settle
// tips it back onto its face about that edge, which (by construction) puts it on its ground truth.
// A second object lies behind the back wall: the probe disables it and it is scored at its input
// pose, invalid for the strict variants, without a decision.
TEST(Synthetic, AfterMetricsUseTheProbesSettledScene) {
  constexpr double kPi = 3.14159265358979323846;
  const double floor_y = 0.4, wall_z = 1.6, theta = 12 * kPi / 180;
  SyntheticScene s;
  s.name = "topple";
  s.layout = "tabletop";
  s.camera.fx = s.camera.fy = 280;
  s.camera.width = 320, s.camera.height = 240, s.camera.cx = 160, s.camera.cy = 120;
  s.camera.R_world_cam = Eigen::AngleAxisd(-15 * kPi / 180, Vec3::UnitX()).toRotationMatrix();
  s.floor = Plane{"floor", Vec3(0, floor_y, 0), Vec3(0, -1, 0)};
  s.walls.push_back(Plane{"back", Vec3(0, 0, wall_z), Vec3(0, 0, -1)});
  // The tilted box: ground truth upright on the floor; reconstruction rotated by theta about the
  // bottom edge p (x = +5 cm, on the floor), lifted 1 mm.
  const Vec3 ext(0.10, 0.16, 0.10);
  SyntheticObject box;
  box.id = "box", box.label = "box", box.error = InjectedError::Rotation, box.magnitude = 12;
  box.gt_mesh = canonical_box_mesh(ext), box.gt_scale = Vec3::Constant(0.16);
  box.gt_t = Vec3(0, floor_y - 0.08, 1.0);
  box.support_y = floor_y;
  const Mat3 Rz = Eigen::AngleAxisd(theta, Vec3::UnitZ()).toRotationMatrix();
  const Vec3 p(0.05, floor_y, 1.0);
  box.pred_mesh = box.gt_mesh, box.pred_scale = box.gt_scale, box.pred_R = Rz;
  box.pred_t = p + Rz * (box.gt_t - p) - Vec3(0, 0.001, 0);
  box.gt_box = box_aabb(ext, Mat3::Identity(), box.gt_t);
  // It really stands on the edge p: its lowest corner is p, 1 mm up, and its centre of mass lies
  // over the footprint side (x < p.x), so gravity tips it back.
  const Box3 tilted = box_aabb(ext, Rz, box.pred_t);
  ASSERT_NEAR(tilted.max.y(), floor_y - 0.001, simu::testing::kFp64Chain);
  ASSERT_LT(box.pred_t.x(), p.x());
  // A 8 cm cube behind the back wall (outside the room): disabled by the probe.
  SyntheticObject out;
  out.id = "outside", out.label = "box";
  out.gt_mesh = out.pred_mesh = canonical_box_mesh(Vec3::Ones());
  out.gt_scale = out.pred_scale = Vec3::Constant(0.08);
  out.gt_t = out.pred_t = Vec3(0.35, floor_y - 0.04, wall_z + 0.1);
  out.support_y = floor_y;
  out.gt_box = box_aabb(Vec3::Constant(0.08), Mat3::Identity(), out.gt_t);
  s.objects = {box, out};
  for (SyntheticObject& o : s.objects)
    o.modal_mask = render_silhouette(s.camera, placed(o.gt_mesh, o.gt_scale, o.gt_R, o.gt_t));

  // The probe on the scene (meshes written; masks are not read without a resampler).
  const std::string dir = simu::testing::temp_dir("synthetic_topple");
  std::filesystem::create_directories(dir + "/meshes");
  for (const SyntheticObject& o : s.objects) write_obj(dir + "/meshes/" + o.id + ".obj", o.pred_mesh);
  ProbeConfig pc;
  pc.collision.use_coacd = false;
  pc.write_outputs = false;
  pc.final_settle_time = 1.5;
  pc.metrics_settle_time = 1.0;
  const ProbeResult pr = run_probe(to_probe_scene(s, dir), pc, "");
  ASSERT_EQ(pr.diagnostics.size(), 2u);
  const Diagnostics& d = pr.diagnostics[0];
  ASSERT_FALSE(d.physics_disabled) << d.message;
  EXPECT_EQ(d.branch, ProbeBranch::Stretch);
  EXPECT_LT(d.diagnosis.rho, 0.02);  // resting already: the sink and a step over 0.16 m
  EXPECT_FALSE(d.reverted) << d.message;
  // The output pose is the geometric prediction: flat (tilt undone) on the ground truth.
  const SceneObject& settled = pr.scene.objects[0];
  EXPECT_LT(Eigen::AngleAxisd(settled.R).angle(), 1.0 * kPi / 180);
  EXPECT_LT((settled.t - box.gt_t).norm(), 0.005);  // the settle's sink and a few mm of slip
  EXPECT_TRUE(pr.diagnostics[1].physics_disabled);

  const SceneEvaluation ev = evaluate_probe_output(s, pr);
  ASSERT_EQ(ev.objects.size(), 2u);
  // 3D: "before" is the tilted input (independent AABB of its corners); "after" the settled box.
  // The outside cube is where its ground truth is, before and after (IoU 1).
  const double stale = aabb_iou(tilted, box.gt_box);  // what a re-applied (identity) stretch scores
  const double settled_iou = aabb_iou(box_aabb(ext.cwiseProduct(settled.scale) / 0.16, settled.R, settled.t), box.gt_box);
  EXPECT_LT(stale, 0.75);  // a 12 degree tilt's AABB against the upright one (geometry: ~0.7)
  EXPECT_GT(settled_iou, 0.92);  // the geometric prediction (IoU 1) up to a few mm of slip
  EXPECT_NEAR(ev.box_before.iou, 0.5 * (stale + 1.0), simu::testing::kFp64Solve);
  // The evaluation recomputes the settled box from the written scene (fp32 mesh files: 1e-6 of IoU).
  EXPECT_NEAR(ev.box_after.iou, 0.5 * (settled_iou + 1.0), 1e-6);
  // Strict "free only" variant: the disabled cube counts 0 after, 1 before.
  EXPECT_NEAR(ev.box_after.iou_fo, 0.5 * settled_iou, 1e-6);
  EXPECT_NEAR(ev.box_before.iou_fo, 0.5 * (stale + 1.0), simu::testing::kFp64Solve);
  // 2D: the settled box covers its ground-truth mask; the tilted one does not.
  EXPECT_GT(ev.mask_after.iou, 0.95);
  EXPECT_LT(ev.mask_before.iou, ev.mask_after.iou - 0.05);
  // Decisions: the box's is the probe's; the disabled cube has none.
  EXPECT_TRUE(ev.objects[0].decided);
  EXPECT_EQ(ev.objects[0].got, Branch::Stretch);
  EXPECT_FALSE(ev.objects[1].decided);
  // Support gap after: the settled box rests on the floor.
  EXPECT_LT(ev.objects[0].support_gap_after, 0.003);  // the contact sink and the settle's last step
  // The disabled cube is scored at its input pose, invalid.
  const std::vector<CorrectedObject> objs = probe_output_objects(s, pr);
  EXPECT_FALSE(objs[1].valid);
  EXPECT_LT((objs[1].t - out.pred_t).norm(), simu::testing::kFp64Chain);
  EXPECT_TRUE(objs[0].valid);
  // The physics "after" column starts from the same output: the evaluation settle's displacement is
  // measured from the corrected scene's pose, and the settled box barely moves in it.
  ASSERT_TRUE(pr.evaluation.ran) << pr.evaluation.message;
  EXPECT_NEAR(pr.evaluation.objects[0].displacement, (pr.evaluation.t[0] - settled.t).norm(), simu::testing::kFp64Solve);
  EXPECT_LT(pr.evaluation.objects[0].displacement, 0.003);
}
