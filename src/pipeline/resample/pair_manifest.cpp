// Manifest of build_pairs: JSON lines -> PairManifestRecord (kept apart from pair_builder.cpp so the
// fuzz target fuzz/fuzz_manifest.cpp compiles it without the models).
#include <cmath>
#include <filesystem>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <set>

#include "common/error.h"
#include "pipeline/resample/pair_builder.h"

namespace simu::resample {

namespace {

// A manifest path: absolute as is, else relative to the manifest's directory.
std::string resolve(const std::string& path, const std::string& base_dir) {
  if (path.empty() || std::filesystem::path(path).is_absolute() || base_dir.empty()) return path;
  return (std::filesystem::path(base_dir) / path).lexically_normal().string();
}

// The string value of key `key` ("" when absent); an error when present but not a non-empty string.
std::string string_field(const nlohmann::json& j, const char* key) {
  if (!j.contains(key)) return "";
  SIMU_CHECK(j[key].is_string() && !j[key].get<std::string>().empty(), "'{}' must be a non-empty string, got {}", key,
             j[key].dump());
  return j[key].get<std::string>();
}

}  // namespace

PairManifestRecord parse_manifest_line(const std::string& text, const std::string& base_dir) {
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(text);
  } catch (const std::exception& e) {
    fail("not valid JSON: {}", e.what());
  }
  SIMU_CHECK(j.is_object(), "expected a JSON object, got {}", j.type_name());
  static const std::set<std::string> known = {"id",        "kind",          "weight",   "image",
                                              "mask",      "full_image",    "full_mask", "corrupted_mask",
                                              "pointmap",  "full_pointmap", "gt_occupancy"};
  for (const auto& item : j.items())
    SIMU_CHECK(known.count(item.key()), "unknown key '{}' (known: id, kind, weight, image, mask, full_image, "
               "full_mask, corrupted_mask, pointmap, full_pointmap, gt_occupancy)", item.key());
  PairManifestRecord r;
  r.id = string_field(j, "id");
  SIMU_CHECK(!r.id.empty(), "missing 'id'");
  const std::string kind = string_field(j, "kind");
  if (kind == "occlusion_completion")
    r.kind = data::PairKind::OcclusionCompletion;
  else if (kind == "clean_preservation")
    r.kind = data::PairKind::CleanPreservation;
  else
    fail("'kind' must be \"occlusion_completion\" or \"clean_preservation\", got '{}'", kind);
  r.weight = data::default_weight(r.kind);
  if (j.contains("weight")) {
    SIMU_CHECK(j["weight"].is_number(), "'weight' must be a number, got {}", j["weight"].dump());
    const double w = j["weight"].get<double>();
    SIMU_CHECK(std::isfinite(w) && w >= 0 && w <= std::numeric_limits<float>::max(),
               "'weight' must be finite, >= 0 and fit in float32 (the cache stores float32), got {}", w);
    r.weight = static_cast<float>(w);
  }
  // Paths: required per kind, the other kind's keys refused.
  auto path = [&](const char* key, bool required) {
    std::string p = string_field(j, key);
    SIMU_CHECK(!required || !p.empty(), "{} record lacks '{}'", kind, key);
    return resolve(p, base_dir);
  };
  const bool occ = r.kind == data::PairKind::OcclusionCompletion;
  r.image = path("image", true);
  r.mask = path("mask", true);
  r.pointmap = path("pointmap", false);
  r.gt_occupancy = path("gt_occupancy", false);
  if (occ) {
    r.full_image = path("full_image", true);
    r.full_mask = path("full_mask", true);
    r.full_pointmap = path("full_pointmap", false);
    SIMU_CHECK(!j.contains("corrupted_mask"), "'corrupted_mask' belongs to clean_preservation records");
  } else {
    r.corrupted_mask = path("corrupted_mask", true);
    for (const char* k : {"full_image", "full_mask", "full_pointmap"})
      SIMU_CHECK(!j.contains(k), "'{}' belongs to occlusion_completion records", k);
  }
  return r;
}

ManifestParse parse_manifest(const std::string& text, const std::string& base_dir) {
  ManifestParse out;
  std::map<std::string, int64_t> first_line;
  size_t pos = 0;
  int64_t line_no = 0;
  while (pos <= text.size()) {
    size_t end = text.find('\n', pos);
    if (end == std::string::npos) end = text.size();
    std::string line = text.substr(pos, end - pos);
    pos = end + 1;
    ++line_no;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    const auto first = line.find_first_not_of(" \t");
    if (first == std::string::npos || line[first] == '#') {
      if (end == text.size()) break;
      continue;
    }
    ++out.records;
    try {
      auto r = parse_manifest_line(line, base_dir);
      r.line = line_no;
      auto [it, fresh] = first_line.emplace(r.id, line_no);
      if (!fresh) {
        out.issues.push_back({line_no, r.id, fmt::format("duplicate id (first on line {})", it->second)});
      } else {
        out.pairs.push_back(std::move(r));
      }
    } catch (const simu::Error& e) {
      out.issues.push_back({line_no, "", e.what()});
    }
    if (end == text.size()) break;
  }
  return out;
}

}  // namespace simu::resample
