// Synthetic scene generator: ground truth consistent with its supports, injected errors as recorded,
// masks rendered, the ideal-probe decisions matching the injected error types, files written and
// read back through the scene loader.
#include "pipeline/synthetic.h"

#include "test_util.h"

#include <gtest/gtest.h>

#include <filesystem>

using namespace simu::pipeline;

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
    EXPECT_LT((lo + hi).norm(), 1e-12);
    EXPECT_NEAR((hi - lo).maxCoeff(), 1.0, 1e-12);
  }
  // Lathe: closed and outward (positive signed volume = pi r^2 h for a cylinder, up to the polygon).
  const Mesh cyl = lathe_mesh({{0, 0.5}, {1.0, 0.5}}, 64);
  double vol = 0;
  for (Eigen::Index f = 0; f < cyl.F.rows(); ++f) {
    const Vec3 a = cyl.V.row(cyl.F(f, 0)), b = cyl.V.row(cyl.F(f, 1)), c = cyl.V.row(cyl.F(f, 2));
    vol += a.dot(b.cross(c)) / 6;
  }
  const double polygon_area = 0.5 * 64 * 0.25 * std::sin(2 * 3.14159265358979 / 64);
  EXPECT_NEAR(vol, polygon_area * 1.0, 1e-9);
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
      EXPECT_NEAR(gt.V.col(1).maxCoeff(), o.support_y, 1e-9) << o.id;
      const double h = gt.V.col(1).maxCoeff() - gt.V.col(1).minCoeff();
      // Injected error as recorded: bottom offsets / cut heights / top kept.
      switch (o.error) {
        case InjectedError::Hover: EXPECT_NEAR(pr.V.col(1).maxCoeff(), o.support_y - o.magnitude, 1e-9); break;
        case InjectedError::Sink: EXPECT_NEAR(pr.V.col(1).maxCoeff(), o.support_y + o.magnitude, 1e-9); break;
        case InjectedError::BottomCut:
          ++n_cut;
          EXPECT_NEAR(pr.V.col(1).minCoeff(), gt.V.col(1).minCoeff(), 1e-9);
          EXPECT_NEAR(pr.V.col(1).maxCoeff() - pr.V.col(1).minCoeff(), (1 - o.magnitude) * h, 1e-9);
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
        EXPECT_LT(oc.support_gap_after, 1e-9) << oc.id << " " << to_string(oc.error);
      if (oc.error == InjectedError::Rotation) EXPECT_LE(oc.support_gap_after, 0.2 * oc.support_gap_before + 1e-6) << oc.id;
    }
    // Stretching cannot make the boxes worse than the errors on average.
    EXPECT_GE(ev.box_after.iou + 1e-9, ev.box_before.iou - 0.05);
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
    EXPECT_LT((sc.objects[i].t - s.objects[i].pred_t).norm(), 1e-9);
  }
  EXPECT_TRUE(std::filesystem::exists(dir + "/depth.png"));
  EXPECT_TRUE(std::filesystem::exists(dir + "/rgb.png"));
}

#include "pipeline/overlay.h"

// The committed default set (tests/data/scenes) loads, and every free object has a modal mask of the
// camera's size with pixels in it.
TEST(Synthetic, CommittedDefaultScenes) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "mask PNGs need OpenCV (built with SIMU_WITH_OPENCV=OFF)";
#endif
  const std::string root = simu::testing::source_dir() + "/tests/data/scenes";
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
