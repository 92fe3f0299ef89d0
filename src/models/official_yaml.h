// Reading the official Hydra-style YAML configs (`_target_` class paths, optional keys): helpers the
// models' config readers share (flow model, generator).
#pragma once

#include <yaml-cpp/yaml.h>

#include <string>

#include "common/config.h"
#include "common/error.h"

namespace simu::models {

// The class name of a node's `_target_` (official names are full Python paths; compare by the last
// component); "" when the node has none.
inline std::string short_target(const YAML::Node& node) {
  if (!node || !node.IsMap() || !node["_target_"]) return "";
  std::string t = node["_target_"].as<std::string>();
  const auto dot = t.rfind('.');
  return dot == std::string::npos ? t : t.substr(dot + 1);
}

// node[key] as T, or fallback when absent or null; a value of the wrong type is an error naming the
// file, the key and the expected type.
template <typename T>
T get_or(const YAML::Node& node, const std::string& key, const T& fallback, const std::string& file) {
  if (!node[key] || node[key].IsNull()) return fallback;
  try {
    return node[key].as<T>();
  } catch (const YAML::Exception&) {
    fail("{}: key '{}': expected {}, got '{}'", file, key, config::type_name<T>(),
         node[key].IsScalar() ? node[key].Scalar() : std::string("a non-scalar"));
  }
}

}  // namespace simu::models
