// Helpers shared by the test suites: where the fixtures are, tensor comparison with tolerances.
#pragma once

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <functional>
#include <string>

#include "common/error.h"

namespace simu::testing {

// ../shared beside the repository root, or $SIMU_SHARED_DIR.
inline std::string shared_dir() {
  if (const char* env = std::getenv("SIMU_SHARED_DIR")) return env;
  return (std::filesystem::path(SIMU_SOURCE_DIR) / ".." / "shared").lexically_normal().string();
}
inline std::string fixture(const std::string& name) { return shared_dir() + "/fixtures/" + name; }
inline std::string source_dir() { return SIMU_SOURCE_DIR; }
inline std::string build_dir() { return SIMU_BUILD_DIR; }
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

// max |a-b| / max(max|b|, 1e-6), computed in float64.
// The message of the simu::Error that f throws, "" when it throws none.
inline std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const simu::Error& e) {
    return e.what();
  }
  return "";
}

inline double rel_err(const torch::Tensor& a, const torch::Tensor& b) {
  auto a64 = a.detach().to(torch::kCPU, torch::kFloat64);
  auto b64 = b.detach().to(torch::kCPU, torch::kFloat64);
  const double denom = std::max(b64.abs().max().item<double>(), 1e-6);
  return (a64 - b64).abs().max().item<double>() / denom;
}

// Asserts same shape and rel_err <= tol; the message names the tensor.
inline ::testing::AssertionResult close(const torch::Tensor& got, const torch::Tensor& want, double tol,
                                        const std::string& what = "") {
  if (got.sizes() != want.sizes())
    return ::testing::AssertionFailure() << what << ": shape " << got.sizes() << " vs expected " << want.sizes();
  if (!torch::isfinite(got.to(torch::kFloat64)).all().item<bool>())
    return ::testing::AssertionFailure() << what << ": non-finite values";
  const double e = rel_err(got, want);
  if (e > tol) return ::testing::AssertionFailure() << what << ": relative error " << e << " > " << tol;
  return ::testing::AssertionSuccess();
}

}  // namespace simu::testing

// Skips a test on a machine without CUDA, with the reason.
#define SIMU_REQUIRE_CUDA()                                                        \
  do {                                                                             \
    if (!torch::cuda::is_available()) GTEST_SKIP() << "needs a CUDA device (none here)"; \
  } while (0)
