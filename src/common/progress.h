// Progress display for long loops of the command-line programs: one rewritten line on a terminal,
// a plain line every 10% otherwise (logs, CI). Call it as progress(done, total).
//
//   simu::Progress progress{"build", "pairs"};
//   for (...) progress(done, total);
#pragma once

#include <chrono>
#include <cstdint>
#include <string>

namespace simu {

class Progress {
 public:
  // what: the line's prefix; unit: what is counted (the rate reads "<unit>/s").
  explicit Progress(std::string what, std::string unit = "pairs");
  // Shows done/total, the percentage, the rate and the remaining time. done == total ends the line.
  void operator()(int64_t done, int64_t total);

 private:
  std::string what_, unit_;
  bool tty_;
  std::chrono::steady_clock::time_point t0_, last_{};
  int64_t last_decile_ = -1;
};

}  // namespace simu
