// Tests the `reconstruct` program end to end on the CPU (run.h): a small synthetic photo
// (synthetic_camera.h: floor, two walls, a table with objects, a hanging object) with a label PNG, the
// sidecar, depth as a 16-bit PNG + K; every object brings its ground-truth mesh with SAM 3D-like pose
// errors (bring your own lift) except one, lifted by the Stage-1 port with the small fixture models
// (random weights; three samples, the one with the lowest render-and-compare score kept); plus bad input: a sidecar entry naming a label the image does not have and an
// object whose mesh file will not load. Checks: the run finishes, the skipped objects are listed with
// their reason, the others are in the pre-simulation scene, up within 1 degree of the truth, gravity
// = -up, and the probe's scene.xml loads in MuJoCo.
#include <gtest/gtest.h>

#include <cstdio>
#include <sys/wait.h>

#include <nlohmann/json.hpp>

#include <cstdlib>
#include <filesystem>
#include <fstream>

#include "common/fs.h"
#include "data/safetensors.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/reconstruct/planes.h"
#include "pipeline/reconstruct/synthetic_camera.h"
#include "test_util.h"
#include "tolerance.h"

#ifdef SIMU_HAVE_MUJOCO
#include <mujoco/mujoco.h>
#endif

using json = nlohmann::json;
using namespace simu::reconstruct;

namespace {
std::pair<int, std::string> run(const std::string& cmd, const std::string& log) {
  const int st = std::system((cmd + " > " + log + " 2>&1").c_str());
  std::ifstream f(log);
  std::string out((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  return {WIFEXITED(st) ? WEXITSTATUS(st) : -1, out};
}
// The fixture decoder made to occupy the whole grid (random weights occupy nothing; see lift_test.cpp).
std::string full_decoder(const std::string& dir) {
  auto w = simu::data::load_safetensors(simu::testing::fixture("ss_decoder_small.safetensors"));
  w["out_layer.2.weight"] = torch::zeros_like(w["out_layer.2.weight"]);
  w["out_layer.2.bias"] = torch::full_like(w["out_layer.2.bias"], 2.0);
  const std::string path = dir + "/ss_decoder_full.safetensors";
  simu::data::save_safetensors(path, w);
  return path;
}
// The reconstruct command on a written synthetic photo in `in` with the small fixture models (random
// weights, the full-cube decoder written into dir), CPU, 2 sampling steps, one convex hull per mesh.
std::string fixture_command(const std::string& dir, const std::string& in) {
  const auto fix = [](const std::string& n) { return simu::testing::fixture(n); };
  return simu::testing::build_dir() + "/reconstruct --device cpu --seed 3 --random-weights" + " --generator-config " +
         fix("ss_generator_small.json") + " --generator-weights " + fix("ss_generator_small.safetensors") +
         " --decoder-config " + fix("ss_decoder_small.json") + " --decoder-weights " + full_decoder(dir) +
         " --embedder-config " + simu::testing::source_dir() + "/configs/demo_embedder_small.json --steps 2" +
         " --image " + in + "/image.png --masks " + in + "/labels.png --objects " + in + "/objects.json --depth " + in +
         "/depth.png --intrinsics " + in + "/K.json --no-coacd --set final.settle_time=0.2 --set evaluation.settle_time=0.2";
}
}  // namespace

#if defined(SIMU_HAVE_OPENCV) && defined(SIMU_HAVE_MUJOCO)
TEST(ReconstructCli, EndToEndSmallSyntheticPhoto) {
  const auto dir = simu::testing::temp_dir("reconstruct_e2e");
  CameraSceneConfig cfg;
  cfg.generator.width = 200;
  cfg.generator.height = 150;
  cfg.generator.fx = 175;
  cfg.generator.min_objects = cfg.generator.max_objects = 3;
  cfg.generator.max_hanging = 1;
  const CameraScene s = generate_camera_scene(cfg, 11, "e2e");
  const std::string in = dir + "/photo";
  write_camera_scene(s, in);
  // Sidecar edits: the first free object is lifted by the port (no mesh), the second's mesh is
  // garbage, and an entry names label value 99 (absent from the label image).
  json side = json::parse(simu::fs::read_file(in + "/objects.json"));
  std::string lifted, broken;
  for (auto& e : side["objects"]) {
    if (!e.contains("mesh") || e.value("base", false)) continue;
    if (lifted.empty()) {
      lifted = e["id"];
      e.erase("mesh");
      e.erase("pose");
    } else if (broken.empty()) {
      broken = e["id"];
      std::ofstream(in + "/broken.obj") << "this is not a mesh\n";
      e["mesh"] = "broken.obj";
    }
  }
  ASSERT_FALSE(broken.empty());
  side["objects"].push_back({{"label_value", 99}, {"id", "ghost"}, {"label", "cup"}});
  std::ofstream(in + "/objects.json") << side.dump(2);
  const std::string out = dir + "/out";
  // Three shapes for the lifted object: each aligned, the lowest render-and-compare score kept.
  const std::string cmd = fixture_command(dir, in) + " --lift-samples 3 --out " + out;
  const auto [rc, log] = run(cmd, dir + "/reconstruct.log");
  // Exit 1: objects were skipped (the others reconstructed).
  ASSERT_EQ(rc, 1) << log;
  const json rep = json::parse(simu::fs::read_file(out + "/reconstruct_report.json"));
  bool ghost = false, bad_mesh = false;
  for (const auto& k : rep.at("skipped")) {
    const std::string why = k.at("why");
    ghost |= k.at("object") == "ghost" && why.find("label_99") != std::string::npos;
    bad_mesh |= k.at("object") == broken && why.find("broken.obj") != std::string::npos;
  }
  EXPECT_TRUE(ghost) << rep.dump(2);
  EXPECT_TRUE(bad_mesh) << rep.dump(2);
  // Up from the two walls, within 1 degree; gravity = -up, also in the scene file.
  const Vec3 up(rep["planes"]["up"][0], rep["planes"]["up"][1], rep["planes"]["up"][2]);
  EXPECT_LT(angle_deg(up, s.up), 1.0) << rep["planes"].dump();  // the wall fits' acceptance (planes_test)
  EXPECT_EQ(rep["planes"]["up_source"], "walls");
  const json scene = json::parse(simu::fs::read_file(out + "/input/scene.json"));
  EXPECT_NEAR(scene.at("gravity")[1].get<double>(), -up.y(), simu::testing::kFp64Solve);
  // Every object but the broken one is in the scene (the table as a base); the lifted one says so.
  size_t n_expected = 0;
  for (const auto& o : s.objects) n_expected += !o.is_base && o.id != broken;
  EXPECT_EQ(scene.at("objects").size(), n_expected);
  EXPECT_EQ(scene.at("bases").size(), 1u);
  bool lifted_ok = false, kept_lowest = false;
  for (const auto& o : rep.at("objects"))
    if (o.at("id") == lifted)
      for (const auto& st : o.at("steps")) {
        const std::string step = st.get<std::string>();
        lifted_ok |= step.rfind("lifted (3 usable samples of 3)", 0) == 0;
        // "kept sample K of 3 by ... (scores a, b, c)": sample K has the lowest score.
        int k = -1;
        double sc[3];
        if (std::sscanf(step.c_str(), "kept sample %d of 3 by its agreement with the depth and mask (scores %lf, %lf, %lf)", &k,
                        &sc[0], &sc[1], &sc[2]) == 4) {
          ASSERT_TRUE(k >= 0 && k < 3) << step;
          kept_lowest = sc[k] <= sc[0] && sc[k] <= sc[1] && sc[k] <= sc[2];
        }
      }
  EXPECT_TRUE(lifted_ok) << rep.dump(2);
  EXPECT_TRUE(kept_lowest) << rep.dump(2);
  // The probe's MJCF loads in MuJoCo.
  ASSERT_TRUE(std::filesystem::exists(out + "/probe/scene.xml")) << log;
  char err[1000] = "";
  mjModel* m = mj_loadXML((out + "/probe/scene.xml").c_str(), nullptr, err, sizeof(err));
  EXPECT_NE(m, nullptr) << err;
  if (m) {
    EXPECT_GE(m->nbody, int(n_expected) + 1);
    mj_deleteModel(m);
  }
}
#endif

#if defined(SIMU_HAVE_OPENCV) && defined(SIMU_HAVE_MUJOCO)
// --align-resampled (not in the paper): every free object brings its ground-truth mesh (with the synthetic
// photo's pose errors) and is then resampled (rho threshold 1e-9) by the small random-weight port, two
// candidates each, twice: with and without the option. The fixture decoder's shapes are cubes whose
// scale comes from random pose weights; at that scale they penetrate their neighbours, so the probe's
// best-of-N check finds no stable candidate and keeps the input shape ("resample_failed"). Aligned to the
// object's depth, a cube is the object's size, and the probe takes it. Checked: more objects are replaced
// with the option than without, at least one.
TEST(ReconstructCli, AlignResampledCandidatesFitTheDepth) {
  const auto dir = simu::testing::temp_dir("reconstruct_align_resampled");
  CameraSceneConfig cfg;
  cfg.generator.width = 200;
  cfg.generator.height = 150;
  cfg.generator.fx = 175;
  cfg.generator.min_objects = cfg.generator.max_objects = 3;
  cfg.generator.max_hanging = 0;
  const CameraScene s = generate_camera_scene(cfg, 11, "ar");
  const std::string in = dir + "/photo";
  write_camera_scene(s, in);  // every object brings its ground-truth mesh
  const std::string base_cmd = fixture_command(dir, in) + " --samples 2 --set decision.rho_threshold=1e-9";
  // The objects the probe resampled and replaced (branch resample, no resample_failed flag).
  auto replaced = [](const std::string& out) {
    const json rep = json::parse(simu::fs::read_file(out + "/probe/report.json"));
    int n = 0;
    for (const auto& d : rep.at("objects")) {
      if (d.at("branch") != "resample") continue;
      bool failed = false;
      for (const auto& f : d.at("flags")) failed |= f.get<std::string>() == "resample_failed";
      n += !failed;
    }
    return n;
  };
  const auto [rc0, log0] = run(base_cmd + " --out " + dir + "/plain", dir + "/plain.log");
  ASSERT_LE(rc0, 1) << log0;
  const auto [rc1, log1] = run(base_cmd + " --align-resampled --out " + dir + "/aligned", dir + "/aligned.log");
  ASSERT_LE(rc1, 1) << log1;
  const int n0 = replaced(dir + "/plain"), n1 = replaced(dir + "/aligned");
  EXPECT_GE(n1, 1);
  EXPECT_GT(n1, n0);
  std::printf("objects replaced by a resampled candidate: plain %d, aligned %d\n", n0, n1);
}
#endif
