// LoRA config checks and PEFT target matching (lora_config.h): matching agrees with Python's
// re.fullmatch / PEFT's list rule on a table of patterns and paths; hostile patterns (the issue's
// 100,000-character and 20,000-parenthesis ones, exponential backtracking) end with a clean error or
// a linear-time answer; values outside their domain and bad adapter_config.json name file and key.
#include <fmt/format.h>

#include <fstream>
#include <nlohmann/json.hpp>

#include "common/config.h"
#include "common/error.h"
#include "lora/lora_config.h"
#include "test_util.h"

namespace {

using simu::lora::LoraConfig;
using simu::lora::TargetMatcher;

using simu::testing::error_of;

LoraConfig regex_cfg(const std::string& re) {
  LoraConfig c;
  c.target_regex = re;
  c.target_suffixes.clear();
  return c;
}

const std::vector<std::string> kPaths = {
    "reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape",
    "reverse_fn.backbone.blocks.12.self_attn.to_out.shape",
    "reverse_fn.backbone.blocks.3.cross_attn.shape.to_q",
    "reverse_fn.backbone.blocks.3.cross_attn.shape.to_kv",
    "reverse_fn.backbone.blocks.3.cross_attn.6drotation_normalized.to_q",
    "reverse_fn.backbone.blocks.3.mlp.shape.mlp.0",
    "to_q",
    "xto_q",
    "a.to_q",
    "blocks.7.attn",
};

// Regex form: each pattern against each path, compared with Python's re.fullmatch (PEFT's rule).
TEST(LoraTargets, RegexFullMatchAgreesWithPythonRe) {
  const std::vector<std::string> patterns = {
      R"(.*blocks\.\d+\.(self_attn\.(to_qkv|to_out)\.shape|cross_attn\.shape\.(to_q|to_kv|to_out))$)",
      R"(.*to_q)", R"(to_q)", R"(.*\.to_(q|kv))", R"(reverse_fn\.backbone\.blocks\.[0-9]\..*)",
      R"(.*blocks\.(?:1\d|3)\..*shape.*)", R"((?i).*TO_Q)", R"(.*mlp\.shape\.mlp\.\d+)", R"([a-z_.]+)",
      R"(.*attn)", R"(.*?to_kv)", R"(\w+\.\w+)"};
  const std::string dir = simu::testing::temp_dir("lora_targets");
  nlohmann::json cases = {{"patterns", patterns}, {"paths", kPaths}};
  std::ofstream(dir + "/cases.json") << cases.dump();
  std::ofstream(dir + "/ref.py") << "import json, re, sys\n"
                                    "c = json.load(open(sys.argv[1]))\n"
                                    "print(json.dumps([[re.fullmatch(p, k) is not None for k in c['paths']] for p in c['patterns']]))\n";
  const std::string cmd = simu::testing::python_exe() + " " + dir + "/ref.py " + dir + "/cases.json > " + dir + "/out.json";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  std::ifstream in(dir + "/out.json");
  const auto want = nlohmann::json::parse(in);
  for (size_t p = 0; p < patterns.size(); ++p) {
    const TargetMatcher m(regex_cfg(patterns[p]));
    for (size_t k = 0; k < kPaths.size(); ++k)
      EXPECT_EQ(m.matches(kPaths[k]), want[p][k].get<bool>()) << "pattern " << patterns[p] << " path " << kPaths[k];
  }
}

// List form: equal to an entry or ends with "." + entry (PEFT), never a bare suffix.
TEST(LoraTargets, ListMatchesWholeNameOrDottedSuffix) {
  LoraConfig c;
  c.target_suffixes = {"to_q", "shape.to_kv", "blocks.7.attn"};
  const TargetMatcher m(c);
  EXPECT_FALSE(m.is_regex());
  const std::vector<bool> want = {false, false, true, true, true, false, true, false, true, true};
  for (size_t k = 0; k < kPaths.size(); ++k) EXPECT_EQ(m.matches(kPaths[k]), want[k]) << kPaths[k];
  EXPECT_EQ(m.matching_entries("a.b.shape.to_kv"), (std::vector<std::string>{"shape.to_kv"}));
}

// The issue's crash and hang inputs: a clean error, or an answer in linear time.
TEST(LoraTargets, HostilePatternsNeitherCrashNorHang) {
  // 100,000 x "x": longer than accepted -> error naming the limit.
  EXPECT_NE(error_of([] { TargetMatcher m(regex_cfg(std::string(100000, 'x'))); }).find("longer than the 4096"),
            std::string::npos);
  // 20,000 nested parentheses: refused the same way.
  EXPECT_NE(error_of([] { TargetMatcher m(regex_cfg(std::string(20000, '(') + "x" + std::string(20000, ')'))); }),
            "");
  // 2,000 nested parentheses (within the length limit): RE2 parses without recursion.
  {
    const std::string deep = std::string(2000, '(') + "x" + std::string(2000, ')');
    std::string err = error_of([&] {
      TargetMatcher m(regex_cfg(deep));
      EXPECT_TRUE(m.matches("x"));
      EXPECT_FALSE(m.matches("xx"));
    });
    if (!err.empty()) EXPECT_NE(err.find("cannot be used"), std::string::npos) << err;
  }
  // Catastrophic backtracking for std::regex / Python re: linear for RE2, on a long path too.
  const TargetMatcher m(regex_cfg("(.*.*.*.*)*X"));
  EXPECT_FALSE(m.matches(std::string(20000, 'a')));
  EXPECT_TRUE(m.matches(std::string(20000, 'a') + "X"));
  const TargetMatcher m2(regex_cfg("(a|aa)+$"));
  EXPECT_FALSE(m2.matches(std::string(5000, 'a') + "b"));
}

TEST(LoraTargets, UnsupportedSyntaxNamesThePatternAndRe2) {
  const std::string err = error_of([] { TargetMatcher m(regex_cfg(R"(.*(?=to_q))")); });
  EXPECT_NE(err.find("(?=to_q)"), std::string::npos) << err;
  EXPECT_NE(err.find("RE2"), std::string::npos) << err;
  EXPECT_NE(error_of([] { TargetMatcher m(regex_cfg(R"((a)\1)")); }), "");
  EXPECT_NE(error_of([] { TargetMatcher m(regex_cfg("(unclosed")); }), "");
}

// Values outside their domain are refused at load, naming the file and the key.
TEST(LoraConfigDomain, OutOfDomainValuesNameFileAndKey) {
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"{alpha: .inf}", "lora.alpha"},
      {"{alpha: .nan}", "lora.alpha"},
      {"{alpha: 9223372036854775807}", "lora.alpha"},
      {"{alpha: -1}", "lora.alpha"},
      {"{r: 0}", "lora.r"},
      {"{r: 1000000}", "lora.r"},
      {"{dropout: 1.0}", "lora.dropout"},
      {"{dropout: -0.1}", "lora.dropout"},
      {"{target_modules: ''}", "lora.target_modules"},
      {"{target_modules: [to_q, '']}", "lora.target_modules"},
      {"{target_modules: [[a]]}", "lora.target_modules"},
      {"{target_modules: {a: 1}}", "lora.target_modules"},
      {"{target_modules: '(?<=x)y'}", "lora.target_modules"},
      {"{r: abc}", "lora.r"},
  };
  for (const auto& [yaml, key] : cases) {
    YAML::Node n = YAML::Load(yaml);
    simu::config::Reader r(n, "train.yaml", "lora");
    const std::string err = error_of([&] { LoraConfig::from(r); });
    EXPECT_NE(err.find("train.yaml: key '" + key + "'"), std::string::npos) << yaml << " -> " << err;
  }
  // In range: accepted.
  YAML::Node n = YAML::Load("{r: 65536, alpha: 1000000, dropout: 0.999}");
  simu::config::Reader r(n, "train.yaml", "lora");
  EXPECT_EQ(LoraConfig::from(r).r, 65536);
}

// adapter_config.json: every problem names the file and the key (PEFT's names) and what was expected.
TEST(PeftConfigJson, ErrorsNameFileKeyAndExpectation) {
  const std::string ok = R"({"peft_type": "LORA", "r": 4, "lora_alpha": 8, "target_modules": ["to_q"]})";
  auto cfg = simu::lora::peft_config_from_json(ok, "a/adapter_config.json");
  EXPECT_EQ(cfg.r, 4);
  EXPECT_EQ(cfg.alpha, 8.0);
  const std::vector<std::pair<std::string, std::string>> cases = {
      {R"({"peft_type": "LORA", "r": 4, "lora_alpha": 1e400, "target_modules": "x"})", "not valid JSON"},
      {R"({"peft_type": "LORA", "r": 4, "lora_alpha": 1e308, "target_modules": "x"})", "key 'lora_alpha'"},
      {R"({"peft_type": "LORA", "r": "4", "lora_alpha": 8, "target_modules": "x"})", "key 'r': expected an integer"},
      {R"({"peft_type": "LORA", "r": 18446744073709551615, "lora_alpha": 8, "target_modules": "x"})", "key 'r'"},
      {R"({"peft_type": "LORA", "r": 4, "lora_alpha": 8})", "key 'target_modules'"},
      {R"({"peft_type": "LORA", "r": 4, "lora_alpha": 8, "target_modules": [1]})", "key 'target_modules'"},
      {R"({"peft_type": "LORA", "r": 4, "lora_alpha": 8, "target_modules": "x", "use_dora": true})", "key 'use_dora'"},
      {R"({"peft_type": "LORA", "r": 4, "lora_alpha": 8, "target_modules": "x", "lora_dropout": "0.1"})", "key 'lora_dropout'"},
      {R"({"peft_type": "IA3", "r": 4, "lora_alpha": 8, "target_modules": "x"})", "key 'peft_type'"},
      {R"([1, 2])", "expected a JSON object"},
      {"{\"peft_type\": \"LO\xff\"}", "invalid UTF-8 at line 1, column 18"},
      {std::string(1000, '[') + std::string(1000, ']'), "nested deeper than"},
  };
  for (const auto& [text, want] : cases) {
    const std::string err = error_of([&] { simu::lora::peft_config_from_json(text, "a/adapter_config.json"); });
    EXPECT_EQ(err.rfind("a/adapter_config.json", 0), 0u) << err;
    EXPECT_NE(err.find(want), std::string::npos) << text.substr(0, 80) << " -> " << err;
    EXPECT_EQ(err.find("[json.exception"), std::string::npos) << err;
  }
}

}  // namespace
