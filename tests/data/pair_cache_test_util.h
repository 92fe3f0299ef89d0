// Helpers shared by the pair cache tests (pair_cache_test.cpp, pair_cache_inputs_test.cpp).
#pragma once

#include <hdf5.h>
#include <gtest/gtest.h>

#include <functional>
#include <mutex>
#include <string>

#include "data/pair_cache.h"

namespace simu::testing {

// Runs f with an HDF5 file opened read-write under the toolkit's HDF5 lock (test-only surgery).
inline void with_h5(const std::string& path, const std::function<void(hid_t)>& f) {
  std::lock_guard<std::recursive_mutex> lock(simu::data::hdf5_mutex());
  hid_t file = H5Fopen(path.c_str(), H5F_ACC_RDWR, H5P_DEFAULT);
  ASSERT_GE(file, 0);
  f(file);
  ASSERT_GE(H5Fclose(file), 0);
}

}  // namespace simu::testing
