// Helpers of the physics tests (no torch): temporary directories, box meshes, scene files.
#pragma once

#include <unistd.h>

#include <filesystem>
#include <string>

#include "common/fs.h"
#include "physics/mesh.h"
#include "physics/scene.h"

namespace simu::testing {

// A fresh temporary directory for one test.
inline std::string physics_temp_dir(const std::string& name) {
  auto p = std::filesystem::temp_directory_path() / ("simu_physics_" + name + "_" + std::to_string(::getpid()));
  simu::fs::remove_tree(p.string());
  std::filesystem::create_directories(p);
  return p.string();
}

// Writes a canonical box mesh (AABB-centred; half extents h, longest side 1 expected) and returns its path.
inline std::string write_box(const std::string& dir, const std::string& name, const physics::Vec3& half) {
  const std::string path = dir + "/" + name + ".obj";
  physics::write_mesh(physics::box_mesh(half), path);
  return path;
}

}  // namespace simu::testing
