// LoRA hyper-parameters and PEFT's target_modules matching, free of torch (the fuzz targets and
// the config checks build this file alone).
//
// target_modules follows PEFT (tuners_utils.check_target_module_exists):
//   - a string is a regular expression that must match the WHOLE module path (re.fullmatch);
//   - a list matches a module whose path equals an entry or ends with "." + entry.
// Regexes run on RE2 (linear time in the path, bounded memory, no recursion): a pattern from a
// downloaded adapter_config.json or a hand-edited YAML can neither hang nor crash the program.
// RE2 accepts Python's usual syntax (classes, \d \w \s, groups, (?:...), (?P<name>...), lazy
// quantifiers, (?i)); lookaround and back-references are refused with an error naming the pattern.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/config.h"

namespace re2 {
class RE2;
}

namespace simu::lora {

// Limits of the domain a LoRA config is accepted in (values outside are errors at load).
inline constexpr int64_t kMaxRank = 65536;
inline constexpr double kMaxAlpha = 1e6;
inline constexpr size_t kMaxPatternLength = 4096;  // target_modules regex, or one list entry
inline constexpr size_t kMaxTargets = 4096;        // entries of a target_modules list

// Hyper-parameters of the adapters (PEFT LoraConfig's subset that this toolkit supports).
struct LoraConfig {
  int64_t r = 64;            // rank, 1..kMaxRank
  double alpha = 128.0;      // lora_alpha, finite, (0, kMaxAlpha]
  double dropout = 0.0;      // lora_dropout on the adapter's input (training mode only), [0, 1)
  bool use_rslora = false;   // scale = alpha / sqrt(r) instead of alpha / r
  // PEFT target_modules. When target_regex is non-empty it is the string form (a regex over the
  // whole module path, see above). Otherwise target_suffixes is the list form. Default: the 5
  // shape-branch attention projections.
  std::string target_regex;
  std::vector<std::string> target_suffixes = default_targets();

  // scale = alpha / r (or alpha / sqrt(r)).
  double scale() const;
  // Throws simu::Error (without a file name; callers prefix theirs) on a value outside its domain:
  // r outside 1..kMaxRank, alpha not finite or outside (0, kMaxAlpha], dropout outside [0, 1), no
  // targets, an empty or over-long entry, a regex RE2 cannot compile (the message says why).
  void validate() const;
  // The 5 shape-branch projections of each block (self_attn.to_qkv.shape, self_attn.to_out.shape,
  // cross_attn.shape.to_q, cross_attn.shape.to_kv, cross_attn.shape.to_out).
  static std::vector<std::string> default_targets();
  // Reads r, alpha, dropout, use_rslora, target_modules (a string = regex, or a list of suffixes)
  // and validates; errors name reader.file() and the key.
  static LoraConfig from(config::Reader& reader);
};

// PEFT's target_modules test over module paths, compiled once.
class TargetMatcher {
 public:
  // Throws simu::Error like LoraConfig::validate for an unusable pattern.
  explicit TargetMatcher(const LoraConfig& cfg);
  ~TargetMatcher();
  TargetMatcher(TargetMatcher&&) noexcept;
  TargetMatcher& operator=(TargetMatcher&&) noexcept;
  bool is_regex() const { return re_ != nullptr; }
  // True when the module path is targeted (regex: full match; list: equal or ends with ".entry").
  bool matches(const std::string& path) const;
  // List form: the entries that target path (empty for the regex form or no match).
  std::vector<std::string> matching_entries(const std::string& path) const;

 private:
  std::unique_ptr<re2::RE2> re_;
  std::vector<std::string> suffixes_;
};

// Parses the text of a PEFT adapter_config.json (path names it in messages). Only plain LoRA is
// implemented: every PEFT feature that would change the math is refused, naming the key. Errors are
// simu::Error "<path>: ..." naming the key and what was expected.
LoraConfig peft_config_from_json(const std::string& text, const std::string& path);
// Reads <dir>/adapter_config.json.
LoraConfig read_peft_config(const std::string& dir);

// PEFT LoRA directory: adapter_config.json + adapter_model.safetensors (PEFT 0.21 layout).
inline constexpr const char* kPeftConfigFile = "adapter_config.json";
inline constexpr const char* kPeftWeightsFile = "adapter_model.safetensors";

}  // namespace simu::lora
