// libFuzzer target: a probe scene file (src/pipeline/physics/scene.cpp load_scene: JSON, camera, gravity,
// planes, objects, bases) and the meshes it names (read_mesh through assimp: OBJ, PLY).
// Input: first byte selects what the rest is: 0-127 scene JSON, 128-191 an OBJ mesh, 192-255 a PLY.
// (assimp 5.2's PLY reader loops forever on some malformed headers; read_mesh checks PLY headers
// itself first: fuzz/regressions/fuzz_scene/assimp_ply_hang.bin.)
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "common/error.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/scene.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const uint8_t sel = data[0];
  const char* ext = sel < 128 ? ".json" : sel < 192 ? ".obj" : ".ply";
  const char* dir = std::getenv("SIMU_FUZZ_TMP");
  const std::string path =
      std::string(dir ? dir : "/tmp") + "/simu_fuzz_scene_" + std::to_string(::getpid()) + ext;
  FILE* f = std::fopen(path.c_str(), "wb");
  if (!f) return 0;
  std::fwrite(data + 1, 1, size - 1, f);
  std::fclose(f);
  try {
    if (sel < 128) {
      const auto scene = simu::physics::load_scene(path);
      (void)simu::physics::scene_to_json(scene, "/tmp");
    } else {
      const auto mesh = simu::physics::read_mesh(path);
      (void)simu::physics::mesh_problem(mesh);
    }
  } catch (const simu::Error&) {
  }
  return 0;
}
