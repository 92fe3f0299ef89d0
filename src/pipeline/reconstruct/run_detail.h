// Internal helpers shared by run.cpp (the steps), run_io.cpp (inputs, sidecar, report) and
// run_masks.cpp (masks and point maps): not a public interface.
#pragma once

#include "pipeline/reconstruct/run.h"

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

// run_masks.cpp
// The lift's point map [H, W, 3] (any dtype, any device) -> PointMap; invalid points become NaN.
PointMap to_point_map(const torch::Tensor& pm);
// A mask [H, W] -> Mask: pixels with a value > 0 set.
Mask to_mask(const torch::Tensor& t);
// Writes a mask PNG (255 = set); false (nothing written) without OpenCV.
bool write_mask(const Mask& m, const std::string& path);
// Square dilation of a mask by r pixels (separable running maximum).
Mask dilate(const Mask& m, int r);
// The valid points of a point map, every `stride`-th pixel, leaving out pixels under `exclude` (may be null).
Points sample_points(const PointMap& pm, int stride, const Mask* exclude);

}  // namespace simu::reconstruct::detail
