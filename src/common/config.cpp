#include "common/config.h"

#include <filesystem>

namespace simu::config {

YAML::Node load_file(const std::string& path, const std::vector<std::string>& overrides) {
  if (!std::filesystem::exists(path)) fail_hint("check the path given with --config", "config file '{}' does not exist", path);
  YAML::Node root;
  try {
    root = YAML::LoadFile(path);
  } catch (const YAML::Exception& e) {
    fail("{}: line {}, column {}: {}", path, e.mark.line + 1, e.mark.column + 1, e.msg);
  }
  if (root.IsNull()) root = YAML::Node(YAML::NodeType::Map);
  if (!root.IsMap()) fail("{}: expected a mapping at the top level", path);
  for (const auto& o : overrides) apply_override(root, o, path);
  return root;
}

namespace {
void set_path(YAML::Node node, const std::vector<std::string>& parts, size_t i, const YAML::Node& value,
              const std::string& assignment) {
  if (i + 1 == parts.size()) {
    node[parts[i]] = value;
    return;
  }
  YAML::Node next = node[parts[i]];
  if (!next.IsDefined() || next.IsNull()) {
    node[parts[i]] = YAML::Node(YAML::NodeType::Map);
    next = node[parts[i]];
  }
  if (!next.IsMap()) fail("--set {}: '{}' is not a mapping", assignment, parts[i]);
  set_path(next, parts, i + 1, value, assignment);
}
}  // namespace

void apply_override(YAML::Node& root, const std::string& assignment, const std::string& file) {
  const auto eq = assignment.find('=');
  if (eq == std::string::npos || eq == 0) fail("--set '{}': expected key.path=value", assignment);
  const std::string key = assignment.substr(0, eq);
  const std::string text = assignment.substr(eq + 1);
  std::vector<std::string> parts;
  size_t start = 0;
  for (size_t p = 0; p <= key.size(); ++p) {
    if (p == key.size() || key[p] == '.') {
      if (p == start) fail("--set '{}': empty component in key path", assignment);
      parts.push_back(key.substr(start, p - start));
      start = p + 1;
    }
  }
  YAML::Node value;
  try {
    value = YAML::Load(text);
  } catch (const YAML::Exception& e) {
    fail("--set '{}' ({}): value is not valid YAML: {}", assignment, file, e.msg);
  }
  set_path(root, parts, 0, value, assignment);
}

Reader::Reader(YAML::Node node, std::string file, std::string path)
    : Reader(std::move(node), std::move(file), std::move(path), std::make_shared<Seen>()) {}

Reader::Reader(YAML::Node node, std::string file, std::string path, std::shared_ptr<Seen> seen)
    : node_(std::move(node)), file_(std::move(file)), path_(std::move(path)), seen_(std::move(seen)) {
  if (!node_.IsDefined() || node_.IsNull()) node_ = YAML::Node(YAML::NodeType::Map);
  if (!node_.IsMap()) fail("{}: key '{}': expected a mapping", file_, path_.empty() ? "<top>" : path_);
}

bool Reader::has(const std::string& key) const {
  const YAML::Node v = node_[key];
  return v.IsDefined();
}

std::vector<std::string> Reader::keys() const {
  std::vector<std::string> out;
  for (const auto& kv : node_) out.push_back(kv.first.as<std::string>());
  return out;
}

Reader Reader::child(const std::string& key) {
  seen_->maps.insert(full(key));
  YAML::Node v = has(key) ? node_[key] : YAML::Node(YAML::NodeType::Map);
  if (!v.IsMap() && !v.IsNull()) fail("{}: key '{}': expected a mapping", file_, full(key));
  return Reader(v, file_, full(key), seen_);
}

YAML::Node Reader::raw(const std::string& key) {
  seen_->values.insert(full(key));
  return node_[key];
}

void Reader::collect_unknown(const YAML::Node& node, const std::string& path, std::vector<std::string>& out) const {
  for (const auto& kv : node) {
    const std::string k = kv.first.as<std::string>();
    const std::string p = path.empty() ? k : path + "." + k;
    if (seen_->values.count(p)) continue;
    if (seen_->maps.count(p) && kv.second.IsMap()) {
      collect_unknown(kv.second, p, out);
      continue;
    }
    if (seen_->maps.count(p) && kv.second.IsNull()) continue;
    out.push_back(p);
  }
}

void Reader::finish() const {
  std::vector<std::string> unknown;
  collect_unknown(node_, path_, unknown);
  if (unknown.empty()) return;
  std::string list;
  for (const auto& u : unknown) list += (list.empty() ? "'" : ", '") + u + "'";
  fail_hint("remove the key or check its spelling against the documented config", "{}: unknown key{} {}", file_,
            unknown.size() > 1 ? "s" : "", list);
}

}  // namespace simu::config
