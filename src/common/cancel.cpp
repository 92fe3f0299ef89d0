#include "common/cancel.h"

#include <atomic>
#include <memory>
#include <mutex>

namespace simu {
namespace {
std::mutex g_mutex;
std::shared_ptr<const std::function<void()>> g_hook;
std::atomic<bool> g_has_hook{false};
}  // namespace

void set_cancel_hook(std::function<void()> hook) {
  std::lock_guard<std::mutex> lock(g_mutex);
  g_hook = hook ? std::make_shared<const std::function<void()>>(std::move(hook)) : nullptr;
  g_has_hook = static_cast<bool>(g_hook);
}

void check_cancel() {
  if (!g_has_hook.load(std::memory_order_relaxed)) return;
  std::shared_ptr<const std::function<void()>> hook;
  {
    std::lock_guard<std::mutex> lock(g_mutex);
    hook = g_hook;
  }
  if (hook) (*hook)();  // outside the lock: the hook may take other locks (the Python GIL)
}

}  // namespace simu
