// The probe's typed config (configs/probe.yaml, ProbeConfig::from) and the probe program's input and
// output handling: every key read, typed and overridable with --set, unknown keys and wrong types
// named, the paper's numbers in the shipped file, gravity magnitudes out of range refused, distinct
// output folders for --scenes, no overwrite without --overwrite, MuJoCo's log kept out of the
// working directory.
#include <gtest/gtest.h>

#include <unistd.h>

#include <sys/wait.h>

#include <functional>
#include <tuple>
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "common/error.h"
#include "test_files.h"
#include "pipeline/physics/probe.h"
#include "pipeline/physics/probe_batch.h"
#include "pipeline/physics/physics_test_util.h"

using namespace simu::physics;
using simu::testing::physics_temp_dir;
using simu::testing::write_box;

namespace {

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

// Output and exit status of a shell command.
std::pair<int, std::string> run(const std::string& cmd) {
  std::string out;
  FILE* p = popen((cmd + " 2>&1").c_str(), "r");
  std::array<char, 4096> buf;
  while (p && fgets(buf.data(), buf.size(), p)) out += buf.data();
  const int rc = p ? pclose(p) : -1;
  return {WIFEXITED(rc) ? WEXITSTATUS(rc) : -1, out};
}

// One cube resting on a floor.
std::string small_scene(const std::string& dir, const std::string& extra_top = "") {
  write_box(dir, "cube", Vec3::Constant(0.5));
  std::ofstream(dir + "/scene.json") << R"({"gravity": [0,0,-1], )" << extra_top
                                     << R"("floor": {"point": [0,0,0], "normal": [0,0,1]},
    "objects": [{"id": "cube", "mesh": "cube.obj", "scale": 0.2, "t": [0,0,0.1]}]})";
  return dir + "/scene.json";
}

ProbeConfig quick() {
  ProbeConfig c;
  c.collision.use_coacd = false;
  c.final_settle_time = 0.2;
  c.metrics_settle_time = 0.2;
  c.evaluate_input = false;
  return c;
}

}  // namespace

// The shipped file holds the paper's numbers (supplementary "Physics-mode parameters", "Penetration
// Resolution", "Metrics"; Sec. 3.5 for rho) and every key of the config.
TEST(ProbeConfig, ShippedFileHasThePapersNumbersAndEveryKey) {
  const ProbeConfig c = ProbeConfig::load("configs/probe.yaml");
  EXPECT_DOUBLE_EQ(c.physics.timestep, 1.0 / 480.0);
  EXPECT_EQ(c.physics.integrator, "implicit");
  EXPECT_EQ(c.physics.solref_timeconst, 0.01);
  EXPECT_EQ(c.physics.solref_dampratio, 2.0);
  EXPECT_EQ(c.physics.friction, Vec3(1.0, 0.95, 0.01));
  EXPECT_EQ(c.physics.condim, 4);
  EXPECT_EQ(c.physics.margin, 0.0);
  EXPECT_EQ(c.physics.gap, 0.0);
  EXPECT_EQ(c.push_extra, 0.007);
  EXPECT_EQ(c.max_pen_iterations, 200);
  EXPECT_EQ(c.max_pen_total, 0.3);
  EXPECT_EQ(c.rho_threshold, 0.15);
  EXPECT_EQ(c.metrics_settle_time, 5.0);
  EXPECT_EQ(c.metrics.penetration_depth, 0.002);
  EXPECT_EQ(c.metrics.stable_displacement, 0.05);
  // Every key is in the file (the file's values equal the built-in defaults key by key).
  const YAML::Node file = YAML::LoadFile("configs/probe.yaml");
  const auto defaults = ProbeConfig{}.describe();
  const auto loaded = c.describe();
  ASSERT_EQ(defaults.size(), loaded.size());
  for (size_t k = 0; k < defaults.size(); ++k) {
    const auto dot = defaults[k].key.find('.');
    EXPECT_TRUE(file[defaults[k].key.substr(0, dot)][defaults[k].key.substr(dot + 1)].IsDefined()) << defaults[k].key;
    EXPECT_EQ(defaults[k].value, loaded[k].value) << defaults[k].key;
  }
}

// --set applies to every key; a value of the wrong type is an error naming the file and the key.
TEST(ProbeConfig, EveryKeyTakesSetAndRejectsTheWrongType) {
  for (const auto& k : ProbeConfig{}.describe()) {
    const std::string err = error_of([&] { ProbeConfig::load("configs/probe.yaml", {k.key + "={a: 1}"}); });
    EXPECT_NE(err.find(k.key), std::string::npos) << k.key << ": " << err;
    EXPECT_NE(err.find("configs/probe.yaml"), std::string::npos) << err;
  }
  // A valid value applies.
  const ProbeConfig c = ProbeConfig::load("configs/probe.yaml",
                                          {"decision.rho_threshold=0.2", "physics.friction=[0.5, 0.5, 0.005]",
                                           "physics.integrator=Euler", "collision.use_coacd=false",
                                           "penetration.max_iterations=50", "collision.cache_dir=/tmp/x"});
  EXPECT_EQ(c.rho_threshold, 0.2);
  EXPECT_EQ(c.physics.friction, Vec3(0.5, 0.5, 0.005));
  EXPECT_EQ(c.physics.integrator, "Euler");
  EXPECT_FALSE(c.collision.use_coacd);
  EXPECT_EQ(c.max_pen_iterations, 50);
  EXPECT_EQ(c.collision.cache_dir, "/tmp/x");
  EXPECT_TRUE(c.force_resample.empty());
  // decision.force_resample takes a list of ids or one id.
  EXPECT_EQ(ProbeConfig::load("configs/probe.yaml", {"decision.force_resample=[a, b_2]"}).force_resample,
            (std::vector<std::string>{"a", "b_2"}));
  EXPECT_EQ(ProbeConfig::load("", {"decision.force_resample=obj02_wedge"}).force_resample,
            std::vector<std::string>{"obj02_wedge"});
  // An integer key given a fraction, a bool key given a number.
  EXPECT_NE(error_of([] { ProbeConfig::load("", {"penetration.max_iterations=2.5"}); }).find("penetration.max_iterations"),
            std::string::npos);
  EXPECT_NE(error_of([] { ProbeConfig::load("", {"physics.multiccd=3"}); }).find("physics.multiccd"), std::string::npos);
}

// Unknown keys (typos) and values outside their domain are errors naming the key.
TEST(ProbeConfig, UnknownKeysAndOutOfDomainValuesFail) {
  std::string err = error_of([] { ProbeConfig::load("configs/probe.yaml", {"physics.timestepp=0.001"}); });
  EXPECT_NE(err.find("unknown key 'physics.timestepp'"), std::string::npos) << err;
  err = error_of([] { ProbeConfig::load("configs/probe.yaml", {"nosuchsection.x=1"}); });
  EXPECT_NE(err.find("nosuchsection"), std::string::npos) << err;
  for (const char* bad : {"physics.timestep=-0.001", "physics.timestep=.nan", "physics.solref_timeconst=0",
                          "decision.rho_threshold=-1", "evaluation.settle_time=1e300", "physics.integrator=leapfrog",
                          "physics.condim=5", "physics.friction=[1, 2]", "evaluation.penetration_depth=.inf"}) {
    const std::string key = std::string(bad).substr(0, std::string(bad).find('='));
    err = error_of([&] { ProbeConfig::load("configs/probe.yaml", {bad}); });
    EXPECT_NE(err.find(key), std::string::npos) << bad << ": " << err;
  }
}

// The program: --set on an unknown key fails (exit 1, key named); --help lists every key's default.
TEST(ProbeConfig, ProgramSetAndHelp) {
  const std::string probe = simu::testing::build_dir() + "/probe";
  if (!std::filesystem::exists(probe)) GTEST_SKIP() << "build the probe program first";
  const auto dir = physics_temp_dir("probe_cli_set");
  const std::string scene = small_scene(dir);
  auto [rc, out] = run(probe + " --scene " + scene + " --out " + dir + "/o --set physics.bogus=1");
  EXPECT_EQ(rc, 1) << out;
  EXPECT_NE(out.find("physics.bogus"), std::string::npos) << out;
  EXPECT_FALSE(std::filesystem::exists(dir + "/o"));
  std::tie(rc, out) = run(probe + " --help");
  EXPECT_EQ(rc, 0);
  for (const auto& k : ProbeConfig{}.describe()) {
    EXPECT_NE(out.find(k.key), std::string::npos) << k.key;
  }
  EXPECT_NE(out.find("0.00208333333"), std::string::npos) << "timestep default 1/480 s";
}

// Gravity magnitude: negative, zero and absurd values are refused when the scene is read.
TEST(ProbeConfig, GravityMagnitudeOutOfRangeIsRefused) {
  for (const char* g : {"-9.81", "0", "1e300"}) {
    const auto dir = physics_temp_dir(std::string("gravity") + (g[0] == '-' ? "neg" : g));
    const std::string scene = small_scene(dir, std::string("\"gravity_magnitude\": ") + g + ", ");
    const std::string err = error_of([&] { load_scene(scene); });
    EXPECT_NE(err.find("gravity_magnitude"), std::string::npos) << g << ": " << err;
  }
  const auto dir = physics_temp_dir("gravity_ok");
  EXPECT_NO_THROW(load_scene(small_scene(dir, "\"gravity_magnitude\": 9.81, ")));
}

// --scenes: inputs with the same file name get distinct folders; the same file twice is refused.
TEST(ProbeConfig, ScenesWithTheSameFileNameGetDistinctFolders) {
  const std::vector<std::string> in = {"tests/testdata/scenes/synth_0000/scene.json", "tests/testdata/scenes/synth_0001/scene.json",
                                       "other/a.json"};
  const auto dirs = probe_output_dirs(in, "OUT");
  EXPECT_EQ(dirs[0], "OUT/synth_0000_scene");
  EXPECT_EQ(dirs[1], "OUT/synth_0001_scene");
  EXPECT_EQ(dirs[2], "OUT/a");
  EXPECT_EQ(probe_output_dirs({"x/scene.json"}, "OUT")[0], "OUT");
  // Same parent folder name in two places: one more level tells them apart.
  const auto deeper = probe_output_dirs({"/a/s1/synth_0000/scene.json", "/b/s2/synth_0000/scene.json"}, "OUT");
  EXPECT_EQ(deeper[0], "OUT/s1_synth_0000_scene");
  EXPECT_EQ(deeper[1], "OUT/s2_synth_0000_scene");
  const std::string err = error_of([&] { probe_output_dirs({in[0], "./" + in[0]}, "OUT"); });
  EXPECT_NE(err.find("same file"), std::string::npos) << err;
}

// The program on the three committed scenes writes three folders, each with its own report.
TEST(ProbeConfig, ProgramScenesWriteOneFolderEach) {
  const std::string probe = simu::testing::build_dir() + "/probe";
  if (!std::filesystem::exists(probe)) GTEST_SKIP() << "build the probe program first";
  const auto dir = physics_temp_dir("probe_cli_scenes");
  const auto [rc, out] =
      run(probe + " --config configs/probe.yaml --no-coacd --quiet --set final.settle_time=0.2 --set evaluation.settle_time=0.2 "
                  "--set evaluation.evaluate_input=false --out " + dir + "/out --scenes tests/testdata/scenes/synth_0000/scene.json "
                  "tests/testdata/scenes/synth_0001/scene.json tests/testdata/scenes/synth_0002/scene.json");
  ASSERT_EQ(rc, 0) << out;
  for (const char* s : {"synth_0000", "synth_0001", "synth_0002"})
    EXPECT_TRUE(std::filesystem::exists(dir + "/out/" + s + "_scene/report.json")) << s << "\n" << out;
}

// An existing output is refused without overwrite (and left intact); with it, replaced whole; no
// staging folder is left behind; MuJoCo's log does not land in the working directory.
TEST(ProbeConfig, OutputIsNotOverwrittenAndIsReplacedAtomically) {
  const auto dir = physics_temp_dir("probe_overwrite");
  const Scene s = load_scene(small_scene(dir));
  ProbeConfig cfg = quick();
  const std::string out = dir + "/out";
  std::filesystem::create_directories(out);
  std::ofstream(out + "/old.txt") << "previous run";
  std::string err = error_of([&] { run_probe(s, cfg, out); });
  EXPECT_NE(err.find("already exists"), std::string::npos) << err;
  EXPECT_TRUE(std::filesystem::exists(out + "/old.txt"));
  cfg.overwrite = true;
  // A contact buffer of one makes MuJoCo 2.2 warn; its log must not appear in the working directory.
  cfg.physics.nconmax = 1;
  const auto cwd = std::filesystem::current_path();
  std::filesystem::current_path(dir);
  err = error_of([&] { run_probe(s, cfg, out); });
  std::filesystem::current_path(cwd);
  EXPECT_EQ(err, "");
  EXPECT_FALSE(std::filesystem::exists(dir + "/MUJOCO_LOG.TXT"));
  EXPECT_FALSE(std::filesystem::exists(out + "/old.txt"));
  EXPECT_TRUE(std::filesystem::exists(out + "/report.json"));
  EXPECT_TRUE(std::filesystem::exists(out + "/scene.xml"));
  for (const auto& e : std::filesystem::directory_iterator(dir))
    EXPECT_EQ(e.path().filename().string().find(".out.staging"), std::string::npos) << e.path();
}
