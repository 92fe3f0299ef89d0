#include "common/config.h"

#include <algorithm>
#include <filesystem>

#include "common/fs.h"
#include "common/text.h"

namespace simu::config {

namespace {

// Upper bound of the nesting yaml-cpp would recurse through for this text: per line, the indentation
// plus the block indicators ("- ", "? ", ": ") on it, plus the flow brackets open at that point.
int yaml_depth_bound(const std::string& text) {
  int deepest = 0, flow = 0;
  size_t i = 0;
  while (i < text.size()) {
    int indent = 0, indicators = 0;
    while (i < text.size() && text[i] == ' ') ++indent, ++i;
    char quote = 0;
    for (; i < text.size() && text[i] != '\n'; ++i) {
      const char c = text[i];
      if (quote) {
        if (c == '\\' && quote == '"') ++i;
        else if (c == quote) quote = 0;
        continue;
      }
      if (c == '#' && (i == 0 || text[i - 1] == ' ' || text[i - 1] == '\t')) {
        while (i < text.size() && text[i] != '\n') ++i;
        break;
      }
      if (c == '"' || c == '\'') quote = c;
      else if (c == '[' || c == '{') ++flow;
      else if ((c == ']' || c == '}') && flow > 0) --flow;
      else if ((c == '-' || c == '?' || c == ':') && (i + 1 == text.size() || text[i + 1] == ' ' || text[i + 1] == '\n'))
        ++indicators;
      deepest = std::max(deepest, indent + indicators + flow);
    }
    deepest = std::max(deepest, indent + indicators + flow);
    ++i;
  }
  return deepest;
}

// Number of values of the tree with aliases expanded, stopping once it passes limit.
int64_t count_values(const YAML::Node& root, int64_t limit) {
  int64_t n = 0;
  std::vector<YAML::Node> stack{root};
  while (!stack.empty() && n <= limit) {
    YAML::Node node = stack.back();
    stack.pop_back();
    ++n;
    if (node.IsSequence()) {
      for (const auto& item : node) stack.push_back(item);
    } else if (node.IsMap()) {
      for (const auto& kv : node) {
        stack.push_back(kv.first);
        stack.push_back(kv.second);
      }
    }
  }
  return n;
}

}  // namespace

YAML::Node load_text(const std::string& text, const std::string& name, const std::vector<std::string>& overrides) {
  if (text.size() > kMaxConfigBytes)
    fail("{}: {} bytes is larger than the {} MiB a config may have", name, text.size(), kMaxConfigBytes >> 20);
  simu::text::check_utf8(text, name);
  if (yaml_depth_bound(text) > kMaxConfigDepth)
    fail("{}: nested deeper than {} levels (indentation, '- ' items or brackets)", name, kMaxConfigDepth);
  YAML::Node root;
  try {
    root = YAML::Load(text);
  } catch (const YAML::Exception& e) {
    fail("{}: line {}, column {}: {}", name, e.mark.line + 1, e.mark.column + 1, e.msg);
  } catch (const std::exception& e) {
    fail("{}: not valid YAML: {}", name, e.what());
  }
  if (count_values(root, kMaxConfigNodes) > kMaxConfigNodes)
    fail("{}: more than {} values once YAML aliases are expanded", name, kMaxConfigNodes);
  if (root.IsNull()) root = YAML::Node(YAML::NodeType::Map);
  if (!root.IsMap()) fail("{}: expected a mapping at the top level", name);
  // Keys must be plain scalars (a list or mapping as a key has no dotted path).
  for (const auto& kv : root)
    if (!kv.first.IsScalar()) fail("{}: a top-level key is a {}, expected a name", name, kv.first.IsMap() ? "mapping" : "list");
  for (const auto& o : overrides) apply_override(root, o, name);
  return root;
}

YAML::Node load_file(const std::string& path, const std::vector<std::string>& overrides) {
  if (!std::filesystem::exists(path)) fail_hint("check the path given with --config", "config file '{}' does not exist", path);
  if (!std::filesystem::is_regular_file(path)) fail("config file '{}' is not a regular file", path);
  if (std::filesystem::file_size(path) > kMaxConfigBytes)
    fail("{}: {} bytes is larger than the {} MiB a config may have", path, std::filesystem::file_size(path),
         kMaxConfigBytes >> 20);
  return load_text(simu::fs::read_file(path), path, overrides);
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
  simu::text::check_utf8(assignment, fmt::format("--set '{}'", assignment));
  if (yaml_depth_bound(text) > kMaxConfigDepth) fail("--set '{}': value nested deeper than {} levels", assignment, kMaxConfigDepth);
  YAML::Node value;
  try {
    value = YAML::Load(text);
  } catch (const std::exception& e) {
    const auto* ye = dynamic_cast<const YAML::Exception*>(&e);
    fail("--set '{}' ({}): value is not valid YAML: {}", assignment, file, ye ? ye->msg : std::string(e.what()));
  }
  if (count_values(value, kMaxConfigNodes) > kMaxConfigNodes)
    fail("--set '{}': more than {} values once YAML aliases are expanded", assignment, kMaxConfigNodes);
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
  for (const auto& kv : node_) out.push_back(kv.first.IsScalar() ? kv.first.Scalar() : std::string("<non-scalar key>"));
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
    const std::string k = kv.first.IsScalar() ? kv.first.Scalar() : std::string("<non-scalar key>");
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
