// Domain checks of values read by config::Reader, shared by the config structs' `from()` functions.
#pragma once

#include <string>

#include "common/config.h"

namespace simu::config {

// A number read from `key` of r: finite and in [lo, hi] (in (lo, hi] when lo_open), else throws
// "file: key 'a.b': expected a finite number in DOMAIN, got V" (domain as written, e.g. "(0, 1]").
void check_in(const Reader& r, const std::string& key, double v, double lo, double hi, bool lo_open,
              const char* domain);

}  // namespace simu::config
