// libFuzzer target: a YAML config (training config, probe config: every config of the toolkit goes
// through config::load_text + config::Reader) with --set overrides, and its lora: section
// (LoraConfig::from, target matching). Input: the YAML text, optionally followed by a line
// "#--set" and one override "a.b=value" per line.
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "common/config.h"
#include "common/error.h"
#include "lora/lora_config.h"

namespace {

// Reads every value of a mapping the way typed configs do (scalars as numbers, strings, lists).
void walk(simu::config::Reader& r, int depth) {
  for (const auto& key : r.keys()) {
    const YAML::Node v = r.node()[key];
    if (!v.IsDefined()) continue;  // a key with no scalar name (null, list, mapping as a key)
    try {
      if (v.IsMap() && depth < 8) {
        auto c = r.child(key);
        walk(c, depth + 1);
      } else if (v.IsSequence()) {
        (void)r.get<std::vector<double>>(key, {});
      } else if (const std::string t = v.IsScalar() ? v.Scalar() : std::string();
                 !t.empty() && std::string("0123456789+-.").find(t[0]) != std::string::npos) {
        // Number-like scalars as numbers (their malformed ones, "1.2.3", "-", ".nan", take the error
        // path); the rest as strings. Reading every scalar as a number first threw ~16 exceptions per
        // input and made exceptions (ASan unwinding) most of the target's time.
        (void)r.get<double>(key, 0.0);
      } else {
        (void)r.get<std::string>(key, "");
      }
    } catch (const simu::Error&) {
      try {
        (void)r.get<std::string>(key, "");
      } catch (const simu::Error&) {
      }
    }
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  std::string text(reinterpret_cast<const char*>(data), size);
  std::vector<std::string> sets;
  if (const auto at = text.find("\n#--set\n"); at != std::string::npos) {
    std::string rest = text.substr(at + 8);
    text.resize(at + 1);
    size_t start = 0;
    while (start <= rest.size() && sets.size() < 16) {
      const auto nl = rest.find('\n', start);
      const std::string line = rest.substr(start, nl == std::string::npos ? std::string::npos : nl - start);
      if (!line.empty()) sets.push_back(line);
      if (nl == std::string::npos) break;
      start = nl + 1;
    }
  }
  try {
    YAML::Node root = simu::config::load_text(text, "fuzz.yaml", sets);
    simu::config::Reader r(root, "fuzz.yaml");
    if (r.has("lora")) {
      auto l = r.child("lora");
      const auto cfg = simu::lora::LoraConfig::from(l);
      const simu::lora::TargetMatcher m(cfg);
      (void)m.matches("reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape");
    }
    walk(r, 0);
    r.finish();
  } catch (const simu::Error&) {
  }
  return 0;
}
