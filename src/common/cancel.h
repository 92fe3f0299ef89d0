// Cooperative cancellation of long library calls (the Python module's Ctrl-C): the long loops call
// check_cancel() at safe points (a sampling step, a probe object, a training step); a hook installed by
// the embedding program decides whether to stop and then throws Cancelled. Without a hook (the
// command-line programs) check_cancel() is one atomic load.
//
//   simu::set_cancel_hook([] { if (interrupted()) throw simu::Cancelled("interrupted"); });
#pragma once

#include <functional>
#include <string>

#include "common/error.h"

namespace simu {

// Thrown by a cancel hook: the call stops, unwinding what it built (nothing is half-written: the
// library's outputs go through atomic renames).
class Cancelled : public Error {
 public:
  explicit Cancelled(const std::string& message) : Error(message) {}
};

// Installs the hook check_cancel() calls (nullptr removes it). Thread-safe.
void set_cancel_hook(std::function<void()> hook);
// Calls the hook when one is installed; the hook throws Cancelled to stop the calling loop.
void check_cancel();

}  // namespace simu
