// Crash isolation of the pair cache's first reads: a forked child reads, the caller learns whether
// libhdf5 survived (pair_cache_h5.h).
#include <poll.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>

#include "common/error.h"
#include "data/pair_cache_h5.h"

namespace simu::data::h5 {

void isolated(const std::string& path, const char* what,
              const std::function<void(const std::function<void(int64_t, int64_t)>&)>& fn,
              const std::function<void(int64_t, int64_t)>& progress) {
  const char* env = std::getenv("SIMU_HDF5_ISOLATE");
  if (env && std::string(env) == "0") {
    fn(progress ? progress : [](int64_t, int64_t) {});
    return;
  }
  int fds[2];
  if (::pipe(fds) != 0) fail("pair cache '{}': pipe(): {}", path, std::strerror(errno));
  pid_t pid;
  {
    // No other thread may be inside HDF5 while the child is forked (its state is copied).
    std::lock_guard<std::recursive_mutex> lock(hdf5_mutex());
    std::fflush(nullptr);
    pid = ::fork();
    if (pid == 0) {
      // Child: the only thread. The HDF5 mutex was copied locked by a thread id this process does not
      // have: make it a fresh one.
      new (&hdf5_mutex()) std::recursive_mutex();
      ::close(fds[0]);
      auto send = [&](const std::string& msg) {
        size_t done = 0;
        while (done < msg.size()) {
          const ssize_t k = ::write(fds[1], msg.data() + done, msg.size() - done);
          if (k <= 0) {
            if (k < 0 && errno == EINTR) continue;
            break;
          }
          done += static_cast<size_t>(k);
        }
      };
      int code = 0;
      try {
        fn([&](int64_t done, int64_t total) { send(fmt::format("P {} {}\n", done, total)); });
      } catch (const Error& e) {
        send(std::string("E") + e.what() + '\0' + e.hint());
        code = 3;
      } catch (const std::exception& e) {
        send(std::string("E") + "pair cache '" + path + "': " + e.what() + '\0');
        code = 3;
      }
      ::close(fds[1]);
      ::_exit(code);
    }
  }
  ::close(fds[1]);
  if (pid < 0) {
    ::close(fds[0]);
    fail("pair cache '{}': fork(): {}", path, std::strerror(errno));
  }
  // Progress lines ("P done total\n"), then possibly one error ("E<message>\0<hint>").
  std::string buf, error;
  bool in_error = false, hung = false;
  char chunk[4096];
  // Watchdog: libhdf5 1.10 also loops forever on some corrupt heaps; a child silent for longer than
  // SIMU_HDF5_TIMEOUT_S (default 120 s; progress lines reset it) is killed.
  const char* tenv = std::getenv("SIMU_HDF5_TIMEOUT_S");
  const int timeout_ms = 1000 * std::max(1, tenv ? std::atoi(tenv) : 120);
  while (true) {
    pollfd pfd{fds[0], POLLIN, 0};
    const int ready = ::poll(&pfd, 1, timeout_ms);
    if (ready < 0 && errno == EINTR) continue;
    if (ready == 0) {
      hung = true;
      ::kill(pid, SIGKILL);
      break;
    }
    const ssize_t k = ::read(fds[0], chunk, sizeof chunk);
    if (k < 0 && errno == EINTR) continue;
    if (k <= 0) break;
    buf.append(chunk, static_cast<size_t>(k));
    while (!in_error && !buf.empty()) {
      if (buf[0] == 'E') {
        in_error = true;
        break;
      }
      const auto nl = buf.find('\n');
      if (nl == std::string::npos) break;
      long long done = 0, total = 0;
      if (std::sscanf(buf.c_str(), "P %lld %lld", &done, &total) == 2 && progress) progress(done, total);
      buf.erase(0, nl + 1);
    }
  }
  ::close(fds[0]);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (WIFEXITED(status) && WEXITSTATUS(status) == 0) return;
  if (WIFEXITED(status) && WEXITSTATUS(status) == 3 && in_error) {
    const auto zero = buf.find('\0');
    throw Error(buf.substr(1, zero == std::string::npos ? std::string::npos : zero - 1),
                zero == std::string::npos ? "" : buf.substr(zero + 1));
  }
  if (hung)
    fail_hint("the file is damaged: restore a copy or rebuild it (SIMU_HDF5_TIMEOUT_S raises the limit for huge files)",
              "pair cache '{}' is corrupt: reading its {} made libhdf5 1.10 loop for more than {} s (stopped; it ran in "
              "a separate process)",
              path, what, timeout_ms / 1000);
  const std::string how = WIFSIGNALED(status) ? fmt::format("signal {} ({})", WTERMSIG(status), strsignal(WTERMSIG(status)))
                                              : fmt::format("exit status {}", WEXITSTATUS(status));
  fail_hint("the file is damaged: restore a copy or rebuild it (h5py on HDF5 >= 1.14 may say which object is corrupt)",
            "pair cache '{}' is corrupt: reading its {} crashed libhdf5 1.10 ({}, in a separate process)", path, what,
            how);
}

}  // namespace simu::data::h5
