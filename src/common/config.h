// Typed configuration from YAML (or JSON) files with strict key checking and command-line overrides.
//
// Every component has one config struct with defaults and a `from(config::Reader&)` that reads its
// fields. Reader remembers which keys were read; `finish()` reports the ones nobody read, so a typo
// in a config file is an error naming the file and the key path instead of a silent default.
#pragma once

#include <yaml-cpp/yaml.h>

#include <memory>
#include <set>
#include <string>
#include <vector>

#include "common/error.h"

namespace simu::config {

// Loads a YAML/JSON file and applies overrides of the form "a.b.c=value" (value parsed as YAML).
// Throws simu::Error naming the file on a missing file or a syntax error.
YAML::Node load_file(const std::string& path, const std::vector<std::string>& overrides = {});
// Same from text already read; name is the file named in messages. Untrusted text is checked before
// yaml-cpp sees it: at most kMaxConfigBytes, valid UTF-8 (line and column of the first bad byte),
// nesting at most kMaxConfigDepth (yaml-cpp recurses per level), and the loaded tree, aliases
// expanded, at most kMaxConfigNodes values.
YAML::Node load_text(const std::string& text, const std::string& name, const std::vector<std::string>& overrides = {});
inline constexpr size_t kMaxConfigBytes = 16u << 20;
inline constexpr int kMaxConfigDepth = 128;
inline constexpr int64_t kMaxConfigNodes = 1000000;
// Applies one "a.b.c=value" override to root, creating maps on the way.
void apply_override(YAML::Node& root, const std::string& assignment, const std::string& file = "");

// Human-readable name of a C++ field type for error messages ("an integer", "a list of numbers").
template <typename T>
std::string type_name();

class Reader {
 public:
  // node: the mapping to read; file: its file (for messages); path: its key path ("" for the root).
  Reader(YAML::Node node, std::string file, std::string path = "");

  // Reads `key` into value if present (value keeps its default otherwise).
  template <typename T>
  void field(const std::string& key, T& value) {
    if (has(key)) value = convert<T>(key);
  }
  // Returns `key` converted to T, or fallback when absent.
  template <typename T>
  T get(const std::string& key, const T& fallback) {
    return has(key) ? convert<T>(key) : fallback;
  }
  // Returns `key` converted to T; absent -> error "missing required key".
  template <typename T>
  T require(const std::string& key) {
    if (!has(key)) fail("{}: missing required key '{}' ({} expected)", file_, full(key), type_name<T>());
    return convert<T>(key);
  }
  // Sub-mapping reader; an absent key gives an empty mapping. A non-mapping value is an error.
  Reader child(const std::string& key);
  // The raw node under `key`, marked as read with everything below it (for free-form maps).
  YAML::Node raw(const std::string& key);
  bool has(const std::string& key) const;
  std::vector<std::string> keys() const;
  const YAML::Node& node() const { return node_; }
  const std::string& file() const { return file_; }
  // Dotted key path of `key` under this reader.
  std::string full(const std::string& key) const { return path_.empty() ? key : path_ + "." + key; }
  // Throws if any key under this reader's mapping was never read: "file: unknown key 'a.b'".
  void finish() const;

 private:
  struct Seen {
    std::set<std::string> values;  // full paths read as values (or raw subtrees)
    std::set<std::string> maps;    // full paths opened with child()
  };
  Reader(YAML::Node node, std::string file, std::string path, std::shared_ptr<Seen> seen);
  template <typename T>
  T convert(const std::string& key);
  void collect_unknown(const YAML::Node& node, const std::string& path, std::vector<std::string>& out) const;

  YAML::Node node_;
  std::string file_;
  std::string path_;
  std::shared_ptr<Seen> seen_;
};

template <typename T>
T Reader::convert(const std::string& key) {
  seen_->values.insert(full(key));
  const YAML::Node v = node_[key];
  try {
    if (v.IsNull()) throw YAML::Exception(YAML::Mark::null_mark(), "null");
    return v.as<T>();
  } catch (const std::exception&) {
    std::string got = v.IsScalar() ? "'" + v.Scalar() + "'" : (v.IsSequence() ? "a list" : v.IsMap() ? "a mapping" : "nothing");
    fail("{}: key '{}': expected {}, got {}", file_, full(key), type_name<T>(), got);
  }
}

template <typename T>
std::string type_name() {
  if constexpr (std::is_same_v<T, bool>) return "true or false";
  else if constexpr (std::is_integral_v<T>) return "an integer";
  else if constexpr (std::is_floating_point_v<T>) return "a number";
  else if constexpr (std::is_same_v<T, std::string>) return "a string";
  else if constexpr (std::is_same_v<T, std::vector<double>> || std::is_same_v<T, std::vector<float>>) return "a list of numbers";
  else if constexpr (std::is_same_v<T, std::vector<int>> || std::is_same_v<T, std::vector<int64_t>>) return "a list of integers";
  else if constexpr (std::is_same_v<T, std::vector<std::string>>) return "a list of strings";
  else return "a value";
}

}  // namespace simu::config
