// simu::cli::run with the common options (common/cli.h): it registers --set and --log-level, applies
// the log level after parsing and before the body, and turns parse errors and a thrown simu::Error
// into exit codes without running (or finishing) the body.
#include "common/cli.h"

#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "common/error.h"
#include "common/log.h"

namespace {
// Runs a fresh app with the common options on args; ran tells whether the body ran.
int run_with(std::vector<std::string> args, simu::cli::CommonOptions& common, bool& ran,
             simu::log::Level* seen = nullptr, bool throw_in_body = false) {
  CLI::App app{"cli test"};
  args.insert(args.begin(), "prog");
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  ran = false;
  return simu::cli::run(app, static_cast<int>(argv.size()), argv.data(), common, [&] {
    ran = true;
    if (seen) *seen = simu::log::level();
    SIMU_CHECK(!throw_in_body, "the body failed on purpose");
    return 7;
  });
}
}  // namespace

// The options are registered and parsed, the level is in force inside the body, the body's code returns.
TEST(Cli, RunWithCommonOptionsAppliesThemBeforeTheBody) {
  const auto before = simu::log::level();
  simu::cli::CommonOptions common;
  bool ran = false;
  simu::log::Level seen = simu::log::Level::Info;
  EXPECT_EQ(run_with({"--log-level", "error", "--set", "a.b=1", "--set", "c=2"}, common, ran, &seen), 7);
  EXPECT_TRUE(ran);
  EXPECT_EQ(seen, simu::log::Level::Error);
  EXPECT_EQ(common.sets, (std::vector<std::string>{"a.b=1", "c=2"}));
  simu::log::set_level(before);
}

// A bad level is an error (exit 1) before the body runs; an unknown option is a usage error; a
// simu::Error thrown by the body is exit 1.
TEST(Cli, RunWithCommonOptionsReportsErrors) {
  const auto before = simu::log::level();
  bool ran = true;
  {
    simu::cli::CommonOptions common;
    EXPECT_EQ(run_with({"--log-level", "loud"}, common, ran), 1);
    EXPECT_FALSE(ran);
  }
  {
    simu::cli::CommonOptions common;
    EXPECT_NE(run_with({"--no-such-option"}, common, ran), 0);
    EXPECT_FALSE(ran);
  }
  {
    simu::cli::CommonOptions common;
    EXPECT_EQ(run_with({}, common, ran, nullptr, true), 1);
    EXPECT_TRUE(ran);
  }
  simu::log::set_level(before);
}
