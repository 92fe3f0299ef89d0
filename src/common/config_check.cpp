#include "common/config_check.h"

#include <cmath>

#include <fmt/ranges.h>

#include "common/error.h"

namespace simu::config {

void check_in(const Reader& r, const std::string& key, double v, double lo, double hi, bool lo_open,
              const char* domain) {
  if (!std::isfinite(v) || v > hi || (lo_open ? v <= lo : v < lo))
    fail("{}: key '{}': expected a finite number in {}, got {}", r.file(), r.full(key), domain, v);
}

void check_int_in(const Reader& r, const std::string& key, int64_t v, int64_t lo, int64_t hi) {
  if (v >= lo && v <= hi) return;
  const std::string range = hi == std::numeric_limits<int64_t>::max() ? fmt::format(">= {}", lo) : fmt::format("in {}..{}", lo, hi);
  fail("{}: key '{}': expected an integer {}, got {}", r.file(), r.full(key), range, v);
}

void choice_field(Reader& r, const char* key, std::string& value, std::initializer_list<const char*> allowed) {
  r.field(key, value);
  for (const char* a : allowed)
    if (value == a) return;
  fail("{}: key '{}': expected '{}', got '{}'", r.file(), r.full(key), fmt::join(allowed, "' or '"), value);
}

}  // namespace simu::config
