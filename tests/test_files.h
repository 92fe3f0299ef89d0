// Test helpers without torch (every suite): where the fixtures are, temporary directories, the message
// of an expected simu::Error.
#pragma once

#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <functional>
#include <string>

#include "common/error.h"
#include "common/source_dir.h"
#include "tolerance.h"  // the derived bounds every suite uses (simu::testing::kFp64Chain, gamma)

namespace simu::testing {

// ../shared beside the repository root, or $SIMU_SHARED_DIR.
inline std::string shared_dir() {
  if (const char* env = std::getenv("SIMU_SHARED_DIR")) return env;
  return (std::filesystem::path(simu::source_dir()) / ".." / "shared").lexically_normal().string();
}
inline std::string fixture(const std::string& name) { return shared_dir() + "/fixtures/" + name; }
inline std::string source_dir() { return simu::source_dir(); }
// The CMake build folder and the Python interpreter CMake found (defined in test_main.cpp, the one
// test file compiled with their absolute paths).
std::string build_dir();
std::string python_exe();
// A fresh temporary directory for one test.
inline std::string temp_dir(const std::string& name) {
  // A counter keeps directories unique within a process (remove with simu::fs::remove_tree, never
  // std::filesystem::remove_all: libtorch.so exports a copy of it that crashes on non-empty directories).
  static int counter = 0;
  auto p = std::filesystem::temp_directory_path() /
           ("simu_test_" + name + "_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
  std::filesystem::create_directories(p);
  return p.string();
}

// The message of the simu::Error that f throws, "" when it throws none.
inline std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const simu::Error& e) {
    return e.what();
  }
  return "";
}

}  // namespace simu::testing
