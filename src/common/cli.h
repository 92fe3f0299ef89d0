// Shared command-line plumbing for the thin programs: common options and the catch-and-exit wrapper.
#pragma once

#include <CLI/CLI.hpp>

#include <functional>
#include <string>
#include <vector>

namespace simu::cli {

// Options every program has: --set key.path=value (repeatable) and --log-level.
struct CommonOptions {
  std::vector<std::string> sets;
  std::string log_level = "info";
};
void add_common_options(CLI::App& app, CommonOptions& opts);
// Applies --log-level.
void apply_common_options(const CommonOptions& opts);

// Parses argv into app and runs body; prints simu::Error (with its hint) and other exceptions as one
// "error: ..." line and returns the exit code (0 success, 1 error, CLI11's own for usage errors).
int run(CLI::App& app, int argc, char** argv, const std::function<int()>& body);
// The same for a program with the common options: registers them on app (add_common_options), and
// applies them (apply_common_options) after parsing, before body.
int run(CLI::App& app, int argc, char** argv, CommonOptions& common, const std::function<int()>& body);

}  // namespace simu::cli
