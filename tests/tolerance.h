// The rounding model every numerical tolerance of the suites derives from (no torch: the torch-free
// suites use it too). A bound at a use site names its computation in a one-line comment, e.g.
// "one 64-term fp32 product: gamma(64)" or "bf16 inputs, fp32 accumulation: 3 bf16 roundings".
//
// Model (Higham, Accuracy and Stability of Numerical Algorithms, 2nd ed., Lemma 3.1, 3.3, 3.5): a
// result that passes through n roundings in series (an n-term sum or dot product; along a network,
// the sum of the reduction lengths on its longest dependency path) is within gamma(n) = n u / (1 - n u)
// of the exact result, relative to the magnitude of its terms, in any order of evaluation. So the
// bound holds for any kernel set (ATen default / AVX2 / AVX-512, MKL, oneDNN), blocking and thread
// split. Two algebraically equal evaluations differ by at most 2 gamma(n). The torch suites compare
// relative to the largest |value| (test_util.h rel_err), of the order of the terms in these
// normalised layers (LayerNorm / RMSNorm before every product, residual streams).
#pragma once

namespace simu::testing {

// Unit roundoff u: one rounding to nearest changes a value by at most u relative.
inline constexpr double kFp64Unit = 0x1p-53;  // 1.1e-16
inline constexpr double kFp32Unit = 0x1p-24;  // 6.0e-8
inline constexpr double kFp16Unit = 0x1p-11;  // 4.9e-4
inline constexpr double kBf16Unit = 0x1p-8;   // 3.9e-3

// Worst-case relative error of n roundings in series in precision u: n u / (1 - n u).
inline constexpr double gamma(double n, double u = kFp32Unit) { return n * u / (1 - n * u); }

// Two evaluations of the same algebra, each within gamma(n) of the exact value.
inline constexpr double two_paths(double n, double u = kFp32Unit) { return 2 * gamma(n, u); }

// float64 geometry of the physics and reconstruct suites, on metre-scale values (kernel-independent:
// no ATen there, fixed compiler flags; the bounds still follow the model above):
// a handful of operations in series;
inline constexpr double kFp64Short = gamma(9, kFp64Unit);  // 1.0e-15
// a closed-form chain of up to ~9,000 roundings (poses and transforms applied over meshes of a few
// thousand vertices, sums of areas or volumes over their faces);
inline constexpr double kFp64Chain = gamma(9000, kFp64Unit);  // 1.0e-12
// such a chain amplified up to 1,000 times by a solve or fit (Eigen's symmetric eigen-solver for OBB
// axes: vectors within u |C| / gap, gaps >= 1e-3 |C| for the boxes tested; least squares with
// condition numbers up to 1e3).
inline constexpr double kFp64Solve = gamma(9e6, kFp64Unit);  // 1.0e-9

}  // namespace simu::testing
