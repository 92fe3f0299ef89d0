// Error type of the toolkit: libraries throw simu::Error with context; programs catch and exit.
#pragma once

#include <fmt/format.h>

#include <stdexcept>
#include <string>

namespace simu {

// An error with a message that names the file, key or record involved and an optional hint
// that tells the user what to do about it.
class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& message, std::string hint = "")
      : std::runtime_error(message), hint_(std::move(hint)) {}
  const std::string& hint() const { return hint_; }

 private:
  std::string hint_;
};

// Throws simu::Error with a fmt-formatted message.
template <typename... Args>
[[noreturn]] void fail(fmt::format_string<Args...> f, Args&&... args) {
  throw Error(fmt::format(f, std::forward<Args>(args)...));
}

// Throws simu::Error with a message and a hint.
template <typename... Args>
[[noreturn]] void fail_hint(const std::string& hint, fmt::format_string<Args...> f, Args&&... args) {
  throw Error(fmt::format(f, std::forward<Args>(args)...), hint);
}

}  // namespace simu

// SIMU_CHECK(cond, "fmt", args...): throws simu::Error with the formatted message when cond is false.
#define SIMU_CHECK(cond, ...)          \
  do {                                 \
    if (!(cond)) ::simu::fail(__VA_ARGS__); \
  } while (0)
