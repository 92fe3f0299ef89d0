// A parallel for-each over indices on plain threads (the probe's scenes, the synthetic benchmark).
#pragma once

#include <cstdint>
#include <functional>

namespace simu {

// Calls fn(i) for every i in [0, n) on min(threads, n) threads (at least one), which take the next
// index from a shared counter (indices start in order; completion order is free), and returns when
// all are done. When fn throws, no further index is started and the first exception is rethrown
// after every thread has stopped. fn must be safe to call concurrently for different indices.
void parallel_for_each(int64_t n, int threads, const std::function<void(int64_t)>& fn);

}  // namespace simu
