// Scene file: round trip, relative paths, per-object errors that do not fail the scene.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "common/error.h"
#include "pipeline/physics/scene.h"
#include "pipeline/physics/physics_test_util.h"
#include "tolerance.h"

using namespace simu::physics;

namespace {
const char* kScene = R"({
  "image": "rgb.png",
  "camera": {"fx": 500, "fy": 510, "cx": 320, "cy": 240, "width": 640, "height": 480},
  "gravity": [0, 0, -2],
  "floor": {"point": [0,0,0], "normal": [0,0,1]},
  "walls": [{"id": "back", "offset": 1.5, "normal": [0,-1,0]}],
  "bases": [{"id": "table", "mesh": "table.obj", "t": [0,0,0.4]}],
  "objects": [
    {"id": "cup", "mesh": "meshes/cup.obj", "mask": "m/cup.png", "scale": 0.1,
     "R": [[0,-1,0],[1,0,0],[0,0,1]], "t": [0.1,0.2,0.85], "dof": "free", "note": "kept",
     "gt_box": {"min": [0,0,0], "max": [1,1,1]}},
    {"id": "frame", "mesh": "f.obj", "scale": [0.5, 0.4, 0.02], "t": [0,1.4,1.5], "dof": "line-anchored"},
    {"id": "badrot", "mesh": "x.obj", "R": [[1,0,0],[0,2,0],[0,0,1]], "t": [0,0,0]},
    {"id": "badscale", "mesh": "x.obj", "scale": -1, "t": [0,0,0]},
    {"id": "nan", "mesh": "x.obj", "t": [0, null, 0]},
    {"id": "cup", "mesh": "x.obj", "t": [0,0,0]},
    {"mesh": "x.obj", "t": [0,0,0]}
  ],
  "custom": 7
})";
}

TEST(Scene, ParsesAndFlagsBadObjects) {
  const auto dir = simu::testing::physics_temp_dir("scene_parse");
  const auto s = scene_from_json(nlohmann::json::parse(kScene), dir);
  EXPECT_EQ(s.camera.fy, 510);
  EXPECT_NEAR(s.gravity.z(), -1.0, simu::testing::kFp64Chain);
  ASSERT_EQ(s.walls.size(), 1u);
  EXPECT_NEAR(s.walls[0].distance(Vec3(0, 0, 0)), 1.5, simu::testing::kFp64Chain);  // -y normal, plane at y = 1.5
  ASSERT_EQ(s.objects.size(), 7u);
  EXPECT_TRUE(s.objects[0].error.empty()) << s.objects[0].error;
  EXPECT_EQ(s.objects[0].mesh_path, (std::filesystem::path(dir) / "meshes/cup.obj").string());
  EXPECT_NEAR(s.objects[0].to_world(Vec3(1, 0, 0)).y(), 0.2 + 0.1, simu::testing::kFp64Chain);  // R maps x to y
  EXPECT_EQ(s.objects[1].dof, PoseDof::LineAnchored);
  EXPECT_NEAR(s.objects[1].scale.z(), 0.02, simu::testing::kFp64Short);
  for (int k = 2; k < 7; ++k) EXPECT_FALSE(s.objects[k].error.empty()) << "object " << k;
  EXPECT_NE(s.objects[2].error.find("not a rotation"), std::string::npos) << s.objects[2].error;
  EXPECT_NE(s.objects[5].error.find("duplicate"), std::string::npos) << s.objects[5].error;
}

TEST(Scene, RoundTripKeepsValuesAndRelativePaths) {
  const auto dir = simu::testing::physics_temp_dir("scene_rt");
  auto s = scene_from_json(nlohmann::json::parse(kScene), dir);
  s.objects.resize(2);
  save_scene(s, dir + "/out.json");
  const auto j = nlohmann::json::parse(std::ifstream(dir + "/out.json"));
  EXPECT_EQ(j["objects"][0]["mesh"], "meshes/cup.obj");
  EXPECT_EQ(j["objects"][0]["note"], "kept");
  EXPECT_EQ(j["custom"], 7);
  const auto r = load_scene(dir + "/out.json");
  ASSERT_EQ(r.objects.size(), 2u);
  EXPECT_TRUE((r.objects[0].R - s.objects[0].R).cwiseAbs().maxCoeff() < simu::testing::kFp64Chain);
  EXPECT_TRUE((r.objects[1].scale - s.objects[1].scale).cwiseAbs().maxCoeff() < simu::testing::kFp64Chain);
  EXPECT_EQ(r.objects[0].mesh_path, s.objects[0].mesh_path);
  EXPECT_TRUE(r.objects[0].gt_box.has_value());
  EXPECT_EQ(r.walls[0].id, "back");
}

TEST(Scene, MalformedFileThrowsNamingIt) {
  const auto dir = simu::testing::physics_temp_dir("scene_bad");
  std::ofstream(dir + "/bad.json") << "{ not json";
  try {
    load_scene(dir + "/bad.json");
    FAIL() << "expected simu::Error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("bad.json"), std::string::npos);
  }
  EXPECT_THROW(load_scene(dir + "/missing.json"), simu::Error);
}

// A number too large for a double is nlohmann's out_of_range (not a parse_error): still an error
// naming the file, never std::terminate (fuzz/regressions/fuzz_scene/json_number_overflow.json.bin).
TEST(Scene, NumberOverflowThrowsNamingTheFile) {
  const auto dir = simu::testing::physics_temp_dir("scene_overflow");
  std::ofstream(dir + "/big.json") << R"({"gravity_magnitude": 0.778E2682402853032})";
  try {
    load_scene(dir + "/big.json");
    FAIL() << "expected simu::Error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("big.json"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("not valid JSON"), std::string::npos) << e.what();
  }
}
