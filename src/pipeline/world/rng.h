// The shape world's random numbers: a SplitMix64 stream with its own uniform and normal draws, so
// the draws are the same on every standard library (std::uniform_real_distribution's algorithm is
// implementation-defined; meshes and poses also go through libm's sin / cos / exp / log).
#pragma once

#include "common/random.h"

#include <cmath>
#include <cstdint>
#include <string>

namespace simu::world {

class Rng {
 public:
  explicit Rng(uint64_t seed) : state_(seed) {}
  // The next 64 random bits (SplitMix64: state advances by the golden-ratio constant).
  uint64_t next() {
    const uint64_t x = splitmix64(state_);
    state_ += 0x9E3779B97F4A7C15ULL;
    return x;
  }
  // Uniform in [0, 1) with 53 random bits.
  double unit() { return double(next() >> 11) * 0x1.0p-53; }
  // Uniform in [a, b).
  double uniform(double a, double b) { return a + (b - a) * unit(); }
  // Log-uniform in [a, b) (a, b > 0).
  double log_uniform(double a, double b) { return std::exp(uniform(std::log(a), std::log(b))); }
  // Uniform integer in [0, n) (n > 0; the modulo bias is below 2^-40 for n < 2^24).
  int below(int n) { return int(next() % uint64_t(n)); }
  // Standard normal (Box-Muller, one value per call).
  double normal() {
    const double u1 = 1.0 - unit(), u2 = unit();
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(6.283185307179586476925 * u2);
  }
  bool chance(double p) { return unit() < p; }

 private:
  uint64_t state_;
};

// A 64-bit hash of a string and a number (FNV-1a of the text, mixed with the number by SplitMix64).
inline uint64_t hash_key(const std::string& text, uint64_t n) {
  uint64_t h = 1469598103934665603ULL;
  for (unsigned char c : text) h = (h ^ c) * 1099511628211ULL;
  return splitmix64(h ^ splitmix64(n));
}

}  // namespace simu::world
