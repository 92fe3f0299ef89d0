// LoRA config: domain checks, PEFT target_modules matching on RE2, adapter_config.json parsing.
#include "lora/lora_config.h"

#include <re2/re2.h>

#include <cmath>
#include <filesystem>
#include <optional>

#include "common/error.h"
#include "common/fs.h"
#include "common/text.h"

namespace simu::lora {

namespace {

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

// The first value of cfg outside its domain: which field ("r", "alpha", "dropout", "target_modules")
// and what is wrong, so each caller can name the key its own file uses.
struct Problem {
  const char* field;
  std::string message;
};

// Compiles a target_modules regex for full matching; nullptr + why on failure.
std::unique_ptr<re2::RE2> compile(const std::string& pattern, std::string& why) {
  if (pattern.size() > kMaxPatternLength) {
    why = fmt::format("regex of {} characters is longer than the {} accepted", pattern.size(), kMaxPatternLength);
    return nullptr;
  }
  re2::RE2::Options o;
  o.set_log_errors(false);
  o.set_max_mem(64 << 20);  // bounded automaton memory; a pattern needing more is refused
  auto re = std::make_unique<re2::RE2>(pattern, o);
  if (!re->ok()) {
    why = fmt::format("regex '{}' cannot be used: {} (RE2 syntax: Python's usual regex features, without "
                      "lookaround or back-references)",
                      pattern.size() > 80 ? pattern.substr(0, 80) + "..." : pattern, re->error());
    return nullptr;
  }
  return re;
}

std::optional<Problem> find_problem(const LoraConfig& c) {
  if (c.r < 1 || c.r > kMaxRank) return Problem{"r", fmt::format("expected an integer in 1..{}, got {}", kMaxRank, c.r)};
  if (!std::isfinite(c.alpha) || c.alpha <= 0 || c.alpha > kMaxAlpha)
    return Problem{"alpha", fmt::format("expected a finite number in (0, {:g}], got {}", kMaxAlpha, c.alpha)};
  if (!std::isfinite(c.dropout) || c.dropout < 0 || c.dropout >= 1)
    return Problem{"dropout", fmt::format("expected a number in [0, 1), got {}", c.dropout)};
  if (c.target_regex.empty() && c.target_suffixes.empty())
    return Problem{"target_modules", "is empty (expected a regex or a list of module names)"};
  if (!c.target_regex.empty()) {
    std::string why;
    if (!compile(c.target_regex, why)) return Problem{"target_modules", why};
  }
  if (c.target_suffixes.size() > kMaxTargets)
    return Problem{"target_modules", fmt::format("has {} entries, more than the {} accepted", c.target_suffixes.size(),
                                                 kMaxTargets)};
  for (const auto& s : c.target_suffixes) {
    if (s.empty()) return Problem{"target_modules", "has an empty entry"};
    if (s.size() > kMaxPatternLength)
      return Problem{"target_modules",
                     fmt::format("has an entry of {} characters, longer than the {} accepted", s.size(), kMaxPatternLength)};
  }
  return std::nullopt;
}

}  // namespace

double LoraConfig::scale() const {
  return use_rslora ? alpha / std::sqrt(static_cast<double>(r)) : alpha / static_cast<double>(r);
}

void LoraConfig::validate() const {
  if (auto p = find_problem(*this)) fail("lora: {} {}", p->field, p->message);
}

std::vector<std::string> LoraConfig::default_targets() {
  return {"self_attn.to_qkv.shape", "self_attn.to_out.shape", "cross_attn.shape.to_q", "cross_attn.shape.to_kv",
          "cross_attn.shape.to_out"};
}

LoraConfig LoraConfig::from(config::Reader& reader) {
  LoraConfig c;
  reader.field("r", c.r);
  reader.field("alpha", c.alpha);
  reader.field("dropout", c.dropout);
  reader.field("use_rslora", c.use_rslora);
  // target_modules: a string is PEFT's regex form, a list its suffix form.
  if (reader.has("target_modules")) {
    const YAML::Node node = reader.raw("target_modules");
    if (node.IsScalar()) {
      c.target_regex = node.Scalar();
      c.target_suffixes.clear();
      if (c.target_regex.empty())
        fail("{}: key '{}': expected a non-empty regex or a list of module names", reader.file(),
             reader.full("target_modules"));
    } else if (node.IsSequence()) {
      c.target_suffixes.clear();
      for (const auto& item : node) {
        if (!item.IsScalar())
          fail("{}: key '{}': expected a regex string or a list of strings, got a list holding a {}", reader.file(),
               reader.full("target_modules"), item.IsSequence() ? "list" : item.IsMap() ? "mapping" : "null");
        c.target_suffixes.push_back(item.Scalar());
      }
    } else {
      fail("{}: key '{}': expected a regex string or a list of module-name suffixes", reader.file(),
           reader.full("target_modules"));
    }
  }
  if (auto p = find_problem(c)) fail("{}: key '{}': {}", reader.file(), reader.full(p->field), p->message);
  return c;
}

// ---------------------------------------------------------------- matching

TargetMatcher::TargetMatcher(const LoraConfig& cfg) {
  cfg.validate();
  if (!cfg.target_regex.empty()) {
    std::string why;
    re_ = compile(cfg.target_regex, why);
    if (!re_) fail("lora: target_modules {}", why);
  } else {
    suffixes_ = cfg.target_suffixes;
  }
}

TargetMatcher::~TargetMatcher() = default;
TargetMatcher::TargetMatcher(TargetMatcher&&) noexcept = default;
TargetMatcher& TargetMatcher::operator=(TargetMatcher&&) noexcept = default;

bool TargetMatcher::matches(const std::string& path) const {
  if (re_) return re2::RE2::FullMatch(path, *re_);
  for (const auto& s : suffixes_)
    if (path == s || (path.size() > s.size() && ends_with(path, s) && path[path.size() - s.size() - 1] == '.'))
      return true;
  return false;
}

std::vector<std::string> TargetMatcher::matching_entries(const std::string& path) const {
  std::vector<std::string> out;
  for (const auto& s : suffixes_)
    if (path == s || (path.size() > s.size() && ends_with(path, s) && path[path.size() - s.size() - 1] == '.'))
      out.push_back(s);
  return out;
}

// ---------------------------------------------------------------- adapter_config.json

namespace {

// True when a JSON field is absent, null, false, or an empty object/list/string.
bool unset(const nlohmann::json& j, const char* key) {
  if (!j.contains(key)) return true;
  const auto& v = j.at(key);
  return v.is_null() || (v.is_boolean() && !v.get<bool>()) || (v.is_object() && v.empty()) ||
         (v.is_array() && v.empty()) || (v.is_string() && v.get<std::string>().empty());
}

// PEFT's key for each LoraConfig field.
const char* peft_key(const char* field) {
  const std::string f = field;
  if (f == "alpha") return "lora_alpha";
  if (f == "dropout") return "lora_dropout";
  return field;
}

}  // namespace

LoraConfig peft_config_from_json(const std::string& text, const std::string& path) {
  using nlohmann::json;
  const json j = text::parse_json(text, path);
  if (!j.is_object()) fail("{}: expected a JSON object at the top level, got {}", path, j.type_name());
  auto expect = [&](bool ok, const char* key, const char* what) {
    if (!ok)
      fail("{}: key '{}': expected {}, got {}", path, key, what,
           j.contains(key) ? text::excerpt(j.at(key)) : std::string("nothing (missing)"));
  };
  // Only plain LoRA is implemented: refuse every PEFT feature that would change the math.
  expect(j.contains("peft_type") && j["peft_type"].is_string() && j["peft_type"].get<std::string>() == "LORA",
         "peft_type", "\"LORA\"");
  expect(!j.contains("bias") || j["bias"].is_null() || (j["bias"].is_string() && j["bias"].get<std::string>() == "none"),
         "bias", "\"none\" (the only bias mode supported)");
  for (const char* key : {"use_dora", "fan_in_fan_out", "lora_bias", "rank_pattern", "alpha_pattern", "modules_to_save",
                          "layers_to_transform", "layers_pattern", "exclude_modules", "layer_replication",
                          "target_parameters", "use_qalora", "use_bdlora"})
    if (!unset(j, key)) fail("{}: key '{}' = {} is not supported by this toolkit", path, key, text::excerpt(j.at(key)));

  LoraConfig cfg;
  expect(j.contains("r") && j["r"].is_number_integer(), "r", "an integer");
  cfg.r = j["r"].is_number_unsigned() && j["r"].get<uint64_t>() > static_cast<uint64_t>(INT64_MAX) ? INT64_MAX
                                                                                                 : j["r"].get<int64_t>();
  expect(j.contains("lora_alpha") && j["lora_alpha"].is_number(), "lora_alpha", "a number");
  cfg.alpha = j["lora_alpha"].get<double>();
  if (j.contains("lora_dropout") && !j["lora_dropout"].is_null()) {
    expect(j["lora_dropout"].is_number(), "lora_dropout", "a number");
    cfg.dropout = j["lora_dropout"].get<double>();
  }
  if (j.contains("use_rslora") && !j["use_rslora"].is_null()) {
    expect(j["use_rslora"].is_boolean(), "use_rslora", "true or false");
    cfg.use_rslora = j["use_rslora"].get<bool>();
  }
  expect(j.contains("target_modules") && (j["target_modules"].is_string() || j["target_modules"].is_array()),
         "target_modules", "a regex string or a list of module names");
  const json& tm = j["target_modules"];
  cfg.target_suffixes.clear();
  if (tm.is_string()) {
    cfg.target_regex = tm.get<std::string>();
    expect(!cfg.target_regex.empty(), "target_modules", "a non-empty regex");
  } else {
    for (const auto& item : tm) {
      expect(item.is_string(), "target_modules", "a list of strings");
      cfg.target_suffixes.push_back(item.get<std::string>());
    }
  }
  if (auto p = find_problem(cfg)) fail("{}: key '{}': {}", path, peft_key(p->field), p->message);
  return cfg;
}

LoraConfig read_peft_config(const std::string& dir) {
  const std::string path = (std::filesystem::path(dir) / kPeftConfigFile).string();
  if (!std::filesystem::is_regular_file(path))
    fail_hint("a PEFT LoRA directory holds adapter_config.json and adapter_model.safetensors", "{}: missing", path);
  return peft_config_from_json(fs::read_file(path), path);
}

}  // namespace simu::lora
