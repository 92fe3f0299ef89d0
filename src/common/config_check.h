// Domain checks of values read by config::Reader, shared by the config structs' `from()` functions.
#pragma once

#include <cstdint>
#include <initializer_list>
#include <limits>
#include <string>

#include "common/config.h"

namespace simu::config {

// A number read from `key` of r: finite and in [lo, hi] (in (lo, hi] when lo_open), else throws
// "file: key 'a.b': expected a finite number in DOMAIN, got V" (domain as written, e.g. "(0, 1]").
void check_in(const Reader& r, const std::string& key, double v, double lo, double hi, bool lo_open,
              const char* domain);

// The check of int_field alone.
void check_int_in(const Reader& r, const std::string& key, int64_t v, int64_t lo, int64_t hi);
// Reads an integer `key` (when present) into value and checks that it lies in [lo, hi]: else throws
// "file: key 'a.b': expected an integer >= LO (or in LO..HI), got V".
template <class T>
void int_field(Reader& r, const char* key, T& value, int64_t lo, int64_t hi = std::numeric_limits<int64_t>::max()) {
  r.field(key, value);
  check_int_in(r, key, static_cast<int64_t>(value), lo, hi);
}
// Reads a string `key` (when present) that must be one of `allowed`: else throws naming file, key,
// the allowed values and the value.
void choice_field(Reader& r, const char* key, std::string& value, std::initializer_list<const char*> allowed);

}  // namespace simu::config
