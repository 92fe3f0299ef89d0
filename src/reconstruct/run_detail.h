// Internal helpers shared by run.cpp (the steps) and run_io.cpp (inputs, sidecar, report): not a
// public interface.
#pragma once

#include "reconstruct/run.h"

#include <nlohmann/json.hpp>

#include <string>

namespace simu::reconstruct::detail {

nlohmann::json vj(const Vec3& v);
// Three numbers (or one, for an isotropic scale) -> Vec3; throws naming `what`.
Vec3 vec3_of(const nlohmann::json& j, const std::string& what);
// A JSON file; throws naming the file when it cannot be opened or parsed.
nlohmann::json read_json_file(const std::string& path);
// reconstruct_report.json's content.
nlohmann::json report_json(const ReconstructResult& res, bool ran_probe);

}  // namespace simu::reconstruct::detail
