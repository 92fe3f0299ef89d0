#include "common/cli.h"

#include <cstdio>
#include <cstring>
#include <exception>
#include <string>
#include <typeinfo>

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
  } catch (const std::exception& e) {
    // torch's c10::Error (and its subclasses, namespace c10) appends a C++ backtrace to what(),
    // after "\nException raised from"; print the message only (its what_without_backtrace()). The
    // type is recognised by its mangled name so that common needs no torch.
    const std::string what = e.what();
    if (std::strncmp(typeid(e).name(), "N3c10", 5) == 0) {
      const auto cut = what.find("\nException raised from ");
      std::fprintf(stderr, "error (torch): %s\n", what.substr(0, cut).c_str());
      return 1;
    }
    std::fprintf(stderr, "error: %s\n", e.what());
    return 1;
  }
}

int run(CLI::App& app, int argc, char** argv, CommonOptions& common, const std::function<int()>& body) {
  add_common_options(app, common);
  return run(app, argc, argv, [&] {
    apply_common_options(common);
    return body();
  });
}

}  // namespace simu::cli
