#include "common/cli.h"

#include <cstdio>
#include <exception>

#include "common/error.h"
#include "common/log.h"

namespace simu::cli {

void add_common_options(CLI::App& app, CommonOptions& opts) {
  app.add_option("--set", opts.sets, "Override a config value, e.g. --set optim.lr=2e-5 (repeatable)");
  app.add_option("--log-level", opts.log_level, "debug, info, warn, error or off")->capture_default_str();
}

void apply_common_options(const CommonOptions& opts) { log::set_level(log::parse_level(opts.log_level)); }

int run(CLI::App& app, int argc, char** argv, const std::function<int()>& body) {
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  }
  try {
    return body();
  } catch (const simu::Error& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    if (!e.hint().empty()) std::fprintf(stderr, "hint: %s\n", e.hint().c_str());
    return 1;
  } catch (const c10::Error& e) {
    std::fprintf(stderr, "error (torch): %s\n", e.what_without_backtrace());
    return 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}

}  // namespace simu::cli
