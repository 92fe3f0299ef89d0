// Where the repository's sources are (configs/, tests' data): the one place that knows the absolute
// path, so that no other compile command carries it and ccache can share objects between checkouts.
#pragma once

#include <string>

namespace simu {

// The repository root this build was configured from (CMake's CMAKE_SOURCE_DIR), without a trailing slash.
const std::string& source_dir();

}  // namespace simu
