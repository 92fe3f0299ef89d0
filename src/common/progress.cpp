#include "common/progress.h"

#include <fmt/format.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>

namespace simu {

namespace {
// "1h02m03s" / "2m03s" / "3s" ("?" before the first item).
std::string eta_text(double s) {
  if (!std::isfinite(s) || s < 0) return "?";
  const auto t = static_cast<int64_t>(s + 0.5);
  if (t >= 3600) return fmt::format("{}h{:02d}m{:02d}s", t / 3600, (t / 60) % 60, t % 60);
  if (t >= 60) return fmt::format("{}m{:02d}s", t / 60, t % 60);
  return fmt::format("{}s", t);
}
}  // namespace

Progress::Progress(std::string what, std::string unit)
    : what_(std::move(what)), unit_(std::move(unit)), tty_(::isatty(STDERR_FILENO) != 0),
      t0_(std::chrono::steady_clock::now()) {}

void Progress::operator()(int64_t done, int64_t total) {
  const auto now = std::chrono::steady_clock::now();
  const double secs = std::chrono::duration<double>(now - t0_).count();
  const double rate = secs > 0 ? done / secs : 0.0;
  const double pct = total > 0 ? 100.0 * done / total : 100.0;
  const double eta = rate > 0 ? (total - done) / rate : NAN;
  const auto line =
      fmt::format("{} {}/{} ({:.0f}%) {:.1f} {}/s ETA {}", what_, done, total, pct, rate, unit_, eta_text(eta));
  if (tty_) {
    // Redrawn line, at most every 100 ms, always at the end.
    if (done == total || now - last_ > std::chrono::milliseconds(100)) {
      std::fprintf(stderr, "\r%s\033[K%s", line.c_str(), done == total ? "\n" : "");
      std::fflush(stderr);
      last_ = now;
    }
  } else {
    // One plain line per decile.
    const int64_t decile = total > 0 ? done * 10 / total : 10;
    if (decile != last_decile_) {
      std::fprintf(stderr, "%s\n", line.c_str());
      std::fflush(stderr);
      last_decile_ = decile;
    }
  }
}

}  // namespace simu
