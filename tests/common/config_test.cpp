// Config reading: typed fields, defaults, overrides, and the errors for unknown keys, wrong types,
// missing required values.
#include "common/config.h"

#include <fstream>

#include "test_util.h"

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

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const simu::Error& e) {
    return e.what();
  }
  return "";
}

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

}  // namespace
