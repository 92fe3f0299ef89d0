// Config reading: typed fields, defaults, overrides, and the errors for unknown keys, wrong types,
// missing required values.
#include "common/config.h"

#include <fmt/format.h>

#include <fstream>

#include "test_files.h"

namespace {

std::string write_yaml(const std::string& name, const std::string& text) {
  const std::string dir = simu::testing::temp_dir("config");
  const std::string path = dir + "/" + name;
  std::ofstream(path) << text;
  return path;
}

struct OptimConfig {
  double lr = 1e-5;
  int warmup = 0;
  std::vector<double> betas{0.9, 0.999};
  static OptimConfig from(simu::config::Reader& r) {
    OptimConfig c;
    r.field("lr", c.lr);
    r.field("warmup", c.warmup);
    r.field("betas", c.betas);
    return c;
  }
};

using simu::testing::error_of;

TEST(Config, ReadsTypedFieldsAndDefaults) {
  const auto path = write_yaml("a.yaml", "optim:\n  lr: 2.0e-5\n  betas: [0.8, 0.95]\nname: run1\n");
  auto root = simu::config::load_file(path);
  simu::config::Reader r(root, path);
  auto child = r.child("optim");
  const auto c = OptimConfig::from(child);
  EXPECT_DOUBLE_EQ(c.lr, 2e-5);
  EXPECT_EQ(c.warmup, 0);
  ASSERT_EQ(c.betas.size(), 2u);
  EXPECT_DOUBLE_EQ(c.betas[1], 0.95);
  EXPECT_EQ(r.require<std::string>("name"), "run1");
  EXPECT_NO_THROW(r.finish());
}

TEST(Config, OverridesApplyAndParseTypes) {
  const auto path = write_yaml("b.yaml", "optim:\n  lr: 1.0e-5\n");
  auto root = simu::config::load_file(path, {"optim.lr=3e-4", "optim.warmup=7", "new.key=abc"});
  simu::config::Reader r(root, path);
  auto child = r.child("optim");
  const auto c = OptimConfig::from(child);
  EXPECT_DOUBLE_EQ(c.lr, 3e-4);
  EXPECT_EQ(c.warmup, 7);
  EXPECT_EQ(r.child("new").require<std::string>("key"), "abc");
}

TEST(Config, UnknownKeyNamesFileAndPath) {
  const auto path = write_yaml("c.yaml", "optim:\n  lr: 1.0e-5\n  lrr: 3\n");
  auto root = simu::config::load_file(path);
  simu::config::Reader r(root, path);
  auto child = r.child("optim");
  OptimConfig::from(child);
  const auto msg = error_of([&] { r.finish(); });
  EXPECT_NE(msg.find("c.yaml"), std::string::npos) << msg;
  EXPECT_NE(msg.find("unknown key 'optim.lrr'"), std::string::npos) << msg;
}

TEST(Config, WrongTypeNamesKeyAndExpectation) {
  const auto path = write_yaml("d.yaml", "optim:\n  warmup: ten\n");
  auto root = simu::config::load_file(path);
  simu::config::Reader r(root, path);
  auto child = r.child("optim");
  const auto msg = error_of([&] { OptimConfig::from(child); });
  EXPECT_NE(msg.find("key 'optim.warmup': expected an integer, got 'ten'"), std::string::npos) << msg;
}

TEST(Config, MissingRequiredNamesKey) {
  const auto path = write_yaml("e.yaml", "a: 1\n");
  auto root = simu::config::load_file(path);
  simu::config::Reader r(root, path);
  const auto msg = error_of([&] { r.child("data").require<std::string>("cache"); });
  EXPECT_NE(msg.find("missing required key 'data.cache'"), std::string::npos) << msg;
}

TEST(Config, SyntaxErrorAndMissingFile) {
  const auto path = write_yaml("f.yaml", "a: [1, 2\n");
  auto msg = error_of([&] { simu::config::load_file(path); });
  EXPECT_NE(msg.find("f.yaml: line"), std::string::npos) << msg;
  msg = error_of([&] { simu::config::load_file("/nonexistent/x.yaml"); });
  EXPECT_NE(msg.find("does not exist"), std::string::npos) << msg;
  msg = error_of([&] { simu::config::load_file(path + "x", {"=1"}); });
  EXPECT_FALSE(msg.empty());
}

TEST(Config, BadOverrideSyntax) {
  YAML::Node root(YAML::NodeType::Map);
  EXPECT_THROW(simu::config::apply_override(root, "novalue"), simu::Error);
  EXPECT_THROW(simu::config::apply_override(root, "a..b=1"), simu::Error);
}

// Untrusted bytes: a non-UTF-8 byte names file, line and column (never a bare json/yaml library
// message); absurd nesting and alias bombs are refused before yaml-cpp recurses or expands them.
TEST(Config, HostileTextGivesNamedErrors) {
  auto msg = error_of([&] { simu::config::load_file(write_yaml("u.yaml", "a: 1\nb: 'caf\xe9'\n")); });
  EXPECT_NE(msg.find("u.yaml: invalid UTF-8 at line 2, column 8 (byte 0xE9)"), std::string::npos) << msg;
  EXPECT_EQ(msg.find("json.exception"), std::string::npos) << msg;
  msg = error_of([&] { simu::config::load_file(write_yaml("d.yaml", "a: " + std::string(20000, '[') + "\n")); });
  EXPECT_NE(msg.find("d.yaml: nested deeper than 128"), std::string::npos) << msg;
  std::string block = "a:\n";
  for (int i = 0; i < 300; ++i) block += std::string(i + 1, ' ') + "- \n";
  msg = error_of([&] { simu::config::load_file(write_yaml("b.yaml", block)); });
  EXPECT_NE(msg.find("b.yaml: nested deeper"), std::string::npos) << msg;
  // Billion laughs: 10 levels of 10 aliases = 10^10 values once expanded.
  std::string bomb = "l0: &l0 [x, x, x, x, x, x, x, x, x, x]\n";
  for (int i = 1; i < 10; ++i) {
    bomb += fmt::format("l{}: &l{} [", i, i);
    for (int k = 0; k < 10; ++k) bomb += fmt::format("{}*l{}", k ? ", " : "", i - 1);
    bomb += "]\n";
  }
  msg = error_of([&] { simu::config::load_file(write_yaml("bomb.yaml", bomb)); });
  EXPECT_NE(msg.find("bomb.yaml: more than 1000000 values"), std::string::npos) << msg;
  // A --set value with a bad byte names the assignment.
  YAML::Node root(YAML::NodeType::Map);
  msg = error_of([&] { simu::config::apply_override(root, "a=\xff", "c.yaml"); });
  EXPECT_NE(msg.find("invalid UTF-8"), std::string::npos) << msg;
  // A directory given as the config.
  msg = error_of([&] { simu::config::load_file(simu::testing::temp_dir("cfgdir")); });
  EXPECT_NE(msg.find("is not a regular file"), std::string::npos) << msg;
}

// An override of a key nobody reads is an error at finish(), like a typo in the file.
TEST(Config, UnknownOverrideKeyIsAnError) {
  const auto path = write_yaml("o.yaml", "optim: {lr: 1e-5}\n");
  auto root = simu::config::load_file(path, {"optim.lrr=2e-5"});
  simu::config::Reader r(root, path);
  auto o = r.child("optim");
  OptimConfig::from(o);
  const auto msg = error_of([&] { r.finish(); });
  EXPECT_NE(msg.find("unknown key 'optim.lrr'"), std::string::npos) << msg;
}

}  // namespace
