#include "common/source_dir.h"

namespace simu {

// SIMU_SOURCE_DIR is a compile definition of this file alone (CMakeLists.txt).
const std::string& source_dir() {
  static const std::string dir = SIMU_SOURCE_DIR;
  return dir;
}

}  // namespace simu
