// Helpers shared by the torch test suites: test_files.h, the rounding model of every tolerance
// (tolerance.h) and tensor comparison with a tolerance.
#pragma once

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <functional>
#include <string>

#include "common/error.h"
#include "test_files.h"
#include "tolerance.h"

namespace simu::testing {

// max |a-b| / max(max|b|, 1e-6), computed in float64.
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
