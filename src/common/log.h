// Logging with fmt: levels, an optional rank prefix, one line per call to stderr.
#pragma once

#include <fmt/format.h>

#include <functional>
#include <string>

namespace simu::log {

enum class Level { Debug = 0, Info = 1, Warn = 2, Error = 3, Off = 4 };

// Sets the minimum level printed (default Info; SIMU_LOG_LEVEL=debug|info|warn|error|off overrides).
void set_level(Level level);
Level level();
// Parses "debug", "info", "warn", "error" or "off"; throws simu::Error otherwise.
Level parse_level(const std::string& name);
// Sets the rank shown in each line ("[rank 1]"); -1 (default) shows none.
void set_rank(int rank);
// Writes one already formatted line at the given level.
void write(Level level, const std::string& line);
// Where lines go instead of stderr (the Python module forwards them to Python's logging); nullptr
// restores stderr. The sink is called outside the log's lock, from whichever thread logs, with the
// line without level or rank prefix. Thread-safe.
using Sink = std::function<void(Level level, const std::string& line)>;
void set_sink(Sink sink);
// Whether a sink is installed (progress displays then log their plain lines instead of drawing on stderr).
bool has_sink();

template <typename... Args>
void debug(fmt::format_string<Args...> f, Args&&... a) {
  if (level() <= Level::Debug) write(Level::Debug, fmt::format(f, std::forward<Args>(a)...));
}
template <typename... Args>
void info(fmt::format_string<Args...> f, Args&&... a) {
  if (level() <= Level::Info) write(Level::Info, fmt::format(f, std::forward<Args>(a)...));
}
template <typename... Args>
void warn(fmt::format_string<Args...> f, Args&&... a) {
  if (level() <= Level::Warn) write(Level::Warn, fmt::format(f, std::forward<Args>(a)...));
}
template <typename... Args>
void error(fmt::format_string<Args...> f, Args&&... a) {
  if (level() <= Level::Error) write(Level::Error, fmt::format(f, std::forward<Args>(a)...));
}

}  // namespace simu::log
