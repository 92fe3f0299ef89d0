#include "training/launcher.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <thread>

#include <c10/cuda/CUDAFunctions.h>
#include <fmt/format.h>
#include <fmt/ranges.h>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "training/distributed.h"

namespace simu::training {

std::vector<std::string> relaunch_args(int argc, char** argv) {
  std::vector<std::string> args;
  for (int i = 1; i < argc; ++i) {
    if (std::strcmp(argv[i], "--nproc-per-node") == 0) {
      ++i;
      continue;
    }
    if (std::strncmp(argv[i], "--nproc-per-node=", 17) == 0) continue;
    args.push_back(argv[i]);
  }
  return args;
}

torch::Device rank_device(const std::string& device, int local_rank) {
  if (device != "cuda") return torch::Device(torch::kCPU);
  if (!torch::cuda::is_available())
    fail_hint("set train.device: cpu (slow) or run on a GPU machine", "train.device is cuda but no CUDA device is visible");
  SIMU_CHECK(local_rank < static_cast<int>(torch::cuda::device_count()), "LOCAL_RANK {} but only {} CUDA devices are visible",
             local_rank, torch::cuda::device_count());
  c10::cuda::set_device(static_cast<c10::DeviceIndex>(local_rank));
  return torch::Device(torch::kCUDA, static_cast<c10::DeviceIndex>(local_rank));
}

void heartbeat() {
  static const char* path = std::getenv("SIMU_HEARTBEAT_FILE");
  if (path && *path) ::utimensat(AT_FDCWD, path, nullptr, 0);
}

namespace {
volatile sig_atomic_t g_forward_signal = 0;
void on_signal(int sig) { g_forward_signal = sig; }

// True when the process is stopped by a signal (state T in /proc/<pid>/stat) or traced (t).
bool process_stopped(pid_t pid) {
  const std::string path = fmt::format("/proc/{}/stat", pid);
  const int fd = ::open(path.c_str(), O_RDONLY);
  if (fd < 0) return false;
  char buf[512];
  const ssize_t n = ::read(fd, buf, sizeof(buf) - 1);
  ::close(fd);
  if (n <= 0) return false;
  buf[n] = '\0';
  // "pid (comm) S ...": the state follows the last ')'.
  const char* close = std::strrchr(buf, ')');
  return close && close[1] == ' ' && (close[2] == 'T' || close[2] == 't');
}
}  // namespace

namespace {

// The local ranks of one launch: their pids (-1 once reaped) and heartbeat files.
struct LocalRanks {
  int nproc = 0;
  std::string beat_dir;
  std::vector<pid_t> pids;
  std::vector<std::string> beats;
};

// Forks and execs rank r of this program with torchrun's environment and its heartbeat file.
pid_t start_rank(int r, const LocalRanks& lr, int port, const char* exe, const std::vector<std::string>& args) {
  const int threads_per_rank = static_cast<int>(std::thread::hardware_concurrency()) / lr.nproc;
  {
    const int fd = ::open(lr.beats[r].c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd >= 0) ::close(fd);
  }
  const pid_t pid = ::fork();
  SIMU_CHECK(pid >= 0, "fork failed: {}", std::strerror(errno));
  if (pid != 0) return pid;
  ::setenv("RANK", std::to_string(r).c_str(), 1);
  ::setenv("LOCAL_RANK", std::to_string(r).c_str(), 1);
  ::setenv("WORLD_SIZE", std::to_string(lr.nproc).c_str(), 1);
  ::setenv("LOCAL_WORLD_SIZE", std::to_string(lr.nproc).c_str(), 1);
  ::setenv("MASTER_ADDR", "127.0.0.1", 1);
  ::setenv("MASTER_PORT", std::to_string(port).c_str(), 1);
  ::setenv("NCCL_NVLS_ENABLE", "0", 1);
  // Share the cores between the ranks (torchrun sets 1): N ranks each spinning up an intra-op pool
  // as wide as the machine starve each other's launch threads.
  if (!std::getenv("OMP_NUM_THREADS"))
    ::setenv("OMP_NUM_THREADS", std::to_string(std::max(1, threads_per_rank)).c_str(), 1);
  ::setenv("SIMU_HEARTBEAT_FILE", lr.beats[r].c_str(), 1);
  std::vector<char*> argv;
  argv.push_back(const_cast<char*>(exe));
  for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
  argv.push_back(nullptr);
  ::execv(exe, argv.data());
  std::fprintf(stderr, "error: rank %d: exec %s failed: %s\n", r, exe, std::strerror(errno));
  ::_exit(127);
}

// Ends every rank still running: a stopped (SIGSTOPped, suspended) rank cannot act on SIGTERM, so it
// gets SIGKILL at once; the others `sig`, then SIGKILL after 5 s.
void stop_all(LocalRanks& lr, int sig) {
  for (auto p : lr.pids)
    if (p > 0) ::kill(p, process_stopped(p) ? SIGKILL : sig);
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (std::chrono::steady_clock::now() < until) {
    bool any = false;
    for (auto& p : lr.pids) {
      if (p <= 0) continue;
      if (::waitpid(p, nullptr, WNOHANG) == p) p = -1; else any = true;
    }
    if (!any) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  for (auto& p : lr.pids)
    if (p > 0) {
      ::kill(p, SIGKILL);
      ::waitpid(p, nullptr, 0);
      p = -1;
    }
  simu::fs::remove_tree(lr.beat_dir);
}

// The ranks (other than `except`) that are stopped by a signal right now: they, not the rank that
// reported a timeout waiting for them, are the cause.
std::vector<int> stopped_ranks(const LocalRanks& lr, int except) {
  std::vector<int> out;
  for (int r = 0; r < lr.nproc; ++r)
    if (r != except && lr.pids[r] > 0 && process_stopped(lr.pids[r])) out.push_back(r);
  return out;
}

// Reaps the ranks that exited; returns how many. A failed rank stops all and throws naming it (or the
// stopped rank it was waiting for).
int reap_exited(LocalRanks& lr) {
  int reaped = 0;
  for (int r = 0; r < lr.nproc; ++r) {
    if (lr.pids[r] <= 0) continue;
    int status = 0;
    if (::waitpid(lr.pids[r], &status, WNOHANG) != lr.pids[r]) continue;
    lr.pids[r] = -1;
    ++reaped;
    if (WIFEXITED(status) && WEXITSTATUS(status) == 0) continue;
    const std::string how = WIFSIGNALED(status) ? fmt::format("was killed by signal {} ({})", WTERMSIG(status), strsignal(WTERMSIG(status)))
                                                : fmt::format("exited with status {}", WEXITSTATUS(status));
    // A rank that failed waiting for a stopped one: name the stopped rank as the cause.
    const auto stopped = stopped_ranks(lr, r);
    stop_all(lr, SIGTERM);
    if (!stopped.empty())
      fail_hint("a stopped process (SIGSTOP, Ctrl-Z, a debugger) cannot take part in collectives",
                "rank(s) {} stopped (hung) and rank {} {} waiting for it; all ranks stopped",
                fmt::join(stopped, ", "), r, how);
    fail("rank {} {}; the other ranks were stopped", r, how);
  }
  return reaped;
}

// A rank whose heartbeat file is older than hang_timeout: stop all and throw naming it.
void check_heartbeats(LocalRanks& lr, std::chrono::seconds hang_timeout) {
  const auto now = std::filesystem::file_time_type::clock::now();
  for (int r = 0; r < lr.nproc; ++r) {
    if (lr.pids[r] <= 0) continue;
    std::error_code ec;
    const auto t = std::filesystem::last_write_time(lr.beats[r], ec);
    if (!ec && now - t > hang_timeout) {
      const bool stopped = process_stopped(lr.pids[r]);
      stop_all(lr, SIGTERM);
      fail_hint("raise dist.hang_timeout_s if a step (or start-up) is legitimately this slow",
                "rank {} made no progress for {} s ({}); all ranks stopped", r, hang_timeout.count(),
                stopped ? "stopped by a signal" : "hung");
    }
  }
}

}  // namespace

void launch_local_ranks(int nproc, const std::vector<std::string>& args, std::chrono::seconds hang_timeout) {
  SIMU_CHECK(nproc >= 1, "--nproc-per-node must be >= 1, got {}", nproc);
  const int port = free_port();
  LocalRanks lr;
  lr.nproc = nproc;
  lr.beat_dir = fmt::format("{}/simu_launch_{}", std::filesystem::temp_directory_path().string(), ::getpid());
  std::filesystem::create_directories(lr.beat_dir);
  char exe[4096];
  const ssize_t n = ::readlink("/proc/self/exe", exe, sizeof(exe) - 1);
  SIMU_CHECK(n > 0, "cannot find this program's path (/proc/self/exe)");
  exe[n] = '\0';
  lr.pids.assign(nproc, -1);
  lr.beats.resize(nproc);
  // Start the ranks.
  for (int r = 0; r < nproc; ++r) {
    lr.beats[r] = fmt::format("{}/rank{}", lr.beat_dir, r);
    lr.pids[r] = start_rank(r, lr, port, exe, args);
  }
  simu::log::info("launched {} local ranks (MASTER_PORT {}, hang timeout {} s)", nproc, port, hang_timeout.count());
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  ::sigaction(SIGINT, &sa, nullptr);
  ::sigaction(SIGTERM, &sa, nullptr);
  // Watch: exits, signals, heartbeats.
  int running = nproc;
  while (running > 0) {
    if (g_forward_signal) {
      const int sig = g_forward_signal;
      stop_all(lr, SIGTERM);
      fail("interrupted by signal {}; all ranks stopped", sig);
    }
    running -= reap_exited(lr);
    check_heartbeats(lr, hang_timeout);
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  simu::fs::remove_tree(lr.beat_dir);
}

}  // namespace simu::training
