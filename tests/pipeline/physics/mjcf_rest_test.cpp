// The probe's scene.xml is simulation-ready in every MuJoCo a user opens it in: for each committed
// scene (tests/testdata/scenes/*) and the demo scene (configs/demo_scene.yaml, seed 21, as synth_bench --write
// makes it), the written file is stepped 5 s from its written state and every free object must move
// less than 2 mm without a MuJoCo warning, both in MuJoCo 2.2 (the library we link) and in the PyPI
// `mujoco` of the project's venv (tests/pipeline/physics/mjcf_rest_check.py). The last test writes the file
// with the contact parameters the probe used before issue 18 (margin = gap = 4 mm, Euler) and shows
// that the check catches it in current MuJoCo.
#include <gtest/gtest.h>

#include <mujoco/mujoco.h>

#include <sys/wait.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "common/config.h"
#include "common/log.h"
#include "test_files.h"
#include "pipeline/physics/mjcf.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/synthetic.h"
#include "pipeline/physics/physics_test_util.h"

using namespace simu::physics;
using simu::testing::physics_temp_dir;

namespace {

constexpr double kSeconds = 5.0;  // the paper's evaluation settle
constexpr double kLimit = 0.002;  // m

// The scenes: committed ones, then the demo scene written into dir.
std::vector<std::string> scenes(const std::string& dir) {
  std::vector<std::string> out;
  for (const auto& e : std::filesystem::directory_iterator("tests/testdata/scenes"))
    if (std::filesystem::exists(e.path() / "scene.json")) out.push_back((e.path() / "scene.json").string());
  std::sort(out.begin(), out.end());
  YAML::Node node = simu::config::load_file("configs/demo_scene.yaml");
  simu::config::Reader r(node, "configs/demo_scene.yaml");
  auto syn_r = r.child("synthetic");
  const SyntheticConfig syn = SyntheticConfig::from(syn_r);
  const SyntheticScene s = generate_scene(syn, 21, "synth_0000");  // synth_bench --scenes 1 --seed 21 (scripts/demo.sh)
  write_scene_dir(s, dir + "/demo_scene");
  out.push_back(dir + "/demo_scene/scene.json");
  return out;
}

ProbeConfig config(const std::vector<std::string>& sets = {}) {
  std::vector<std::string> all = {"collision.use_coacd=false", "evaluation.evaluate_input=false"};
  all.insert(all.end(), sets.begin(), sets.end());
  return ProbeConfig::load("configs/probe.yaml", all);
}

// Steps a written scene.xml in MuJoCo 2.2; returns the largest free-body motion and the warnings.
std::pair<double, int> rest_in_mujoco22(const std::string& xml) {
  auto m = load_mjcf_file(xml);
  auto d = make_data(m.get());
  mj_forward(m.get(), d.get());
  int warnings = take_warnings(d.get());
  std::vector<int> free;
  for (int b = 1; b < m->nbody; ++b)
    if (m->body_jntnum[b] >= 1 && m->jnt_type[m->body_jntadr[b]] == mjJNT_FREE) free.push_back(b);
  std::vector<Vec3> start;
  for (int b : free) start.push_back(Eigen::Map<const Vec3>(d->xpos + 3 * b));
  double worst = 0;
  const int steps = static_cast<int>(std::lround(kSeconds / m->opt.timestep));
  for (int s = 0; s < steps; ++s) {
    mj_step(m.get(), d.get());
    warnings |= take_warnings(d.get());
    for (size_t k = 0; k < free.size(); ++k)
      worst = std::max(worst, (Eigen::Map<const Vec3>(d->xpos + 3 * free[k]) - start[k]).norm());
  }
  return {worst, warnings};
}

// Runs the PyPI mujoco check; returns its exit status and output.
std::pair<int, std::string> rest_in_pypi_mujoco(const std::vector<std::string>& files) {
  std::string cmd = simu::testing::python_exe() + " tests/pipeline/physics/mjcf_rest_check.py";
  for (const auto& f : files) cmd += " " + f;
  cmd += " 2>&1";
  std::string out;
  FILE* p = popen(cmd.c_str(), "r");
  if (!p) return {-1, "popen failed"};
  std::array<char, 4096> buf;
  while (fgets(buf.data(), buf.size(), p)) out += buf.data();
  const int rc = pclose(p);
  return {WIFEXITED(rc) ? WEXITSTATUS(rc) : -1, out};
}

bool pypi_mujoco_available() {
  return std::system((simu::testing::python_exe() + " -c 'import mujoco' >/dev/null 2>&1").c_str()) == 0;
}

}  // namespace

// Every committed scene and the demo scene: the written file rests in MuJoCo 2.2 and in PyPI mujoco.
TEST(MjcfRest, ProbeOutputRestsInMuJoCo22AndCurrentMuJoCo) {
  const auto dir = physics_temp_dir("mjcf_rest");
  const ProbeConfig cfg = config();
  std::vector<std::string> xmls;
  for (const auto& scene : scenes(dir)) {
    const std::string out = dir + "/out_" + std::filesystem::path(scene).parent_path().filename().string();
    const ProbeResult r = run_probe(load_scene(scene), cfg, out);
    const std::string xml = out + "/scene.xml";
    ASSERT_TRUE(std::filesystem::exists(xml)) << scene;
    // Visual meshes are in the file and read from OBJ files beside it.
    EXPECT_NE(r.mjcf.find("class=\"visual\""), std::string::npos) << scene;
    const auto [moved, warnings] = rest_in_mujoco22(xml);
    simu::log::info("MuJoCo {}: {} max free-body motion in {} s: {:.3f} mm", mj_versionString(), xml, kSeconds, 1000 * moved);
    EXPECT_LT(moved, kLimit) << scene << ": MuJoCo 2.2 moved a resting object " << moved << " m";
    EXPECT_EQ(warnings, 0) << scene << ": MuJoCo 2.2 warnings " << describe_warnings(warnings);
    xmls.push_back(xml);
  }
  if (!pypi_mujoco_available()) GTEST_FAIL() << "PyPI mujoco is not installed in " << simu::testing::python_exe() << " (scripts/setup.sh installs it)";
  const auto [rc, out] = rest_in_pypi_mujoco(xmls);
  std::printf("%s", out.c_str());
  EXPECT_EQ(rc, 0) << out;
}

// The contact parameters of the file before issue 18 (margin = gap = 4 mm, Euler): current MuJoCo
// lifts resting objects by millimetres, and the check above says so.
TEST(MjcfRest, CheckCatchesTheOldMarginGapFile) {
  if (!pypi_mujoco_available()) GTEST_SKIP() << "PyPI mujoco is not installed in " << simu::testing::python_exe();
  const auto dir = physics_temp_dir("mjcf_rest_old");
  const auto all = scenes(dir);
  const ProbeConfig cfg = config({"physics.margin=0.004", "physics.gap=0.004", "physics.integrator=Euler"});
  const std::string out = dir + "/out";
  run_probe(load_scene(all.front()), cfg, out);
  const auto [moved22, warnings22] = rest_in_mujoco22(out + "/scene.xml");
  simu::log::info("old parameters, MuJoCo {}: {:.3f} mm", mj_versionString(), 1000 * moved22);
  const auto [rc, text] = rest_in_pypi_mujoco({out + "/scene.xml"});
  std::printf("%s", text.c_str());
  EXPECT_NE(rc, 0) << "the old file should fail the rest check in current MuJoCo:\n" << text;
}
