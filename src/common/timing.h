// Wall-clock timing for reports and benchmarks (never for pass/fail decisions).
#pragma once

#include <chrono>

namespace simu {

using Clock = std::chrono::steady_clock;

// Seconds elapsed since t0 on the steady clock.
inline double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

}  // namespace simu
