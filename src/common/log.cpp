#include "common/log.h"

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <mutex>

#include "common/error.h"

namespace simu::log {
namespace {

Level initial_level() {
  const char* env = std::getenv("SIMU_LOG_LEVEL");
  if (env == nullptr) return Level::Info;
  try {
    return parse_level(env);
  } catch (const Error&) {
    return Level::Info;
  }
}

std::atomic<int> g_level{static_cast<int>(initial_level())};
std::atomic<int> g_rank{-1};
std::mutex g_mutex;
std::shared_ptr<const Sink> g_sink;  // null: stderr

}  // namespace

void set_level(Level l) { g_level = static_cast<int>(l); }
Level level() { return static_cast<Level>(g_level.load()); }
void set_rank(int rank) { g_rank = rank; }

Level parse_level(const std::string& name) {
  if (name == "debug") return Level::Debug;
  if (name == "info") return Level::Info;
  if (name == "warn" || name == "warning") return Level::Warn;
  if (name == "error") return Level::Error;
  if (name == "off") return Level::Off;
  fail("unknown log level '{}': expected debug, info, warn, error or off", name);
}

void set_sink(Sink sink) {
  std::lock_guard<std::mutex> lock(g_mutex);
  g_sink = sink ? std::make_shared<const Sink>(std::move(sink)) : nullptr;
}

bool has_sink() {
  std::lock_guard<std::mutex> lock(g_mutex);
  return static_cast<bool>(g_sink);
}

void write(Level l, const std::string& line) {
  static const char* names[] = {"debug", "info", "warn", "error", "off"};
  std::shared_ptr<const Sink> sink;
  {
    std::lock_guard<std::mutex> lock(g_mutex);
    sink = g_sink;
  }
  if (sink) {
    (*sink)(l, line);  // outside the lock: the sink may take other locks (the Python GIL)
    return;
  }
  std::lock_guard<std::mutex> lock(g_mutex);
  const int rank = g_rank.load();
  if (rank >= 0) {
    std::fprintf(stderr, "[%s][rank %d] %s\n", names[static_cast<int>(l)], rank, line.c_str());
  } else {
    std::fprintf(stderr, "[%s] %s\n", names[static_cast<int>(l)], line.c_str());
  }
  std::fflush(stderr);
}

}  // namespace simu::log
