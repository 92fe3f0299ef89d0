// Deterministic integer mixing shared by every seeded component (seeds, epoch orders, noise keys).
#pragma once

#include <cstdint>

namespace simu {

// splitmix64 finalizer (Steele, Lea & Flood 2014): a bijective 64-bit mix; one step of the SplitMix64
// generator, so splitmix64(0) is that generator's first output from state 0 (0xE220A8397B1DCDAF).
constexpr uint64_t splitmix64(uint64_t x) {
  x += 0x9E3779B97F4A7C15ULL;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ULL;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBULL;
  return x ^ (x >> 31);
}

}  // namespace simu
