#include "common/config_check.h"

#include <cmath>

#include "common/error.h"

namespace simu::config {

void check_in(const Reader& r, const std::string& key, double v, double lo, double hi, bool lo_open,
              const char* domain) {
  if (!std::isfinite(v) || v > hi || (lo_open ? v <= lo : v < lo))
    fail("{}: key '{}': expected a finite number in {}, got {}", r.file(), r.full(key), domain, v);
}

}  // namespace simu::config
