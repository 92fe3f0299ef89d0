// NCCL process group headers are guarded by USE_C10D_NCCL, which the torch CMake config does not set.
#ifndef USE_C10D_NCCL
#define USE_C10D_NCCL
#endif
#include "training/distributed.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <torch/csrc/distributed/c10d/ProcessGroupNCCL.hpp>
// Gloo process group: needs the gloo headers (Debian libgloo-dev; the symbols are in libtorch_cpu).
// CMake defines USE_C10D_GLOO for this library when it finds them.
#ifdef USE_C10D_GLOO
#include <torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>
#endif
#include <torch/csrc/distributed/c10d/TCPStore.hpp>

#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <functional>
#include <thread>

#include <fmt/ranges.h>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"

namespace simu::training {

namespace {

// Integer environment variable, or fallback when unset.
int env_int(const char* name, int fallback) {
  const char* v = std::getenv(name);
  if (!v || !*v) return fallback;
  char* end = nullptr;
  const long x = std::strtol(v, &end, 10);
  if (*end != '\0') fail("environment variable {}='{}': expected an integer", name, v);
  return static_cast<int>(x);
}

// An exception's text without a C++ backtrace (c10::Error carries one) and on one line.
std::string short_what(const std::exception& e) {
  std::string msg;
  if (const auto* ce = dynamic_cast<const c10::Error*>(&e)) msg = ce->what_without_backtrace();
  else msg = e.what();
  if (const auto nl = msg.find('\n'); nl != std::string::npos) msg = msg.substr(0, nl);
  return msg;
}

// Flattens tensors into one contiguous buffer (same dtype/device as the first).
torch::Tensor flatten(const std::vector<torch::Tensor>& ts) {
  std::vector<torch::Tensor> flat;
  for (const auto& t : ts) flat.push_back(t.reshape({-1}));
  return torch::cat(flat);
}
// Copies a flat buffer back into the tensors.
void unflatten(const torch::Tensor& buf, std::vector<torch::Tensor>& ts) {
  int64_t off = 0;
  torch::NoGradGuard ng;
  for (auto& t : ts) {
    const int64_t n = t.numel();
    t.copy_(buf.narrow(0, off, n).view(t.sizes()));
    off += n;
  }
}

// Store-based collectives: each rank posts its bytes under a round key; all read in rank order.
class StoreCommunicator : public Communicator {
 public:
  StoreCommunicator(c10::intrusive_ptr<c10d::Store> store, int rank, int world, std::chrono::milliseconds timeout)
      : store_(std::move(store)), rank_(rank), world_(world), timeout_(timeout) {}
  // Leaving: every rank posts a "left" key; rank 0, which hosts the store, waits for all of them
  // (bounded by the timeout) so nobody still reading loses the server.
  ~StoreCommunicator() override {
    try {
      store_->set(fmt::format("simu/left/{}", rank_), std::vector<uint8_t>{1});
      if (rank_ == 0) {
        std::vector<std::string> keys;
        for (int r = 0; r < world_; ++r) keys.push_back(fmt::format("simu/left/{}", r));
        store_->wait(keys, timeout_);
      }
    } catch (const std::exception&) {
      // A rank that is already gone: nothing to wait for.
    }
  }
  int rank() const override { return rank_; }
  int world_size() const override { return world_; }
  std::string backend() const override { return "store"; }

  void all_reduce_mean(std::vector<torch::Tensor>& tensors) override {
    if (tensors.empty()) return;
    // [N] float64 on CPU: exact transport, sum in rank order.
    auto flat = flatten(tensors).detach().to(torch::kCPU, torch::kFloat64).contiguous();
    auto all = exchange("allreduce", bytes_of(flat));
    auto sum = torch::zeros_like(flat);
    for (auto& b : all) sum += from_bytes(b, flat.numel());
    unflatten((sum / world_).to(tensors[0].device(), tensors[0].scalar_type()), tensors);
  }

  std::vector<double> all_reduce_sum(const std::vector<double>& values) override {
    std::vector<uint8_t> mine(values.size() * sizeof(double));
    std::memcpy(mine.data(), values.data(), mine.size());
    auto all = exchange("sum", mine);
    std::vector<double> out(values.size(), 0.0);
    for (auto& b : all) {
      SIMU_CHECK(b.size() == mine.size(), "all_reduce_sum: ranks disagree on the number of values");
      const double* d = reinterpret_cast<const double*>(b.data());
      for (size_t i = 0; i < out.size(); ++i) out[i] += d[i];
    }
    return out;
  }

  void barrier() override { exchange("barrier", {1}); }

 protected:
  // Why a collective of this rank failed, in words that name the culprit: the other ranks that never
  // posted key(r), or rank 0 itself when the store it hosts cannot be reached (it is gone). This
  // rank is never listed; "after X s" says how long it waited, "timed out" only when the full
  // timeout passed.
  std::string failure_cause(const std::function<std::string(int)>& key, std::chrono::steady_clock::time_point began) {
    const double waited = std::chrono::duration<double>(std::chrono::steady_clock::now() - began).count();
    const double limit = timeout_.count() / 1000.0;
    const std::string when = waited + 0.5 >= limit ? fmt::format("timed out after {:.0f} s", waited)
                                                   : fmt::format("failed after {:.1f} s", waited);
    std::vector<int> missing;
    for (int r = 0; r < world_; ++r) {
      if (r == rank_) continue;
      try {
        if (!store_->check({key(r)})) missing.push_back(r);
      } catch (const std::exception&) {
        if (rank_ == 0) return fmt::format("{}: the rendezvous store stopped answering", when);
        return fmt::format("{}: rank 0 is gone (it hosts the rendezvous store, which no longer answers); see rank 0's log",
                           when);
      }
    }
    if (missing.empty()) return fmt::format("{}: every other rank reached it (a peer's connection broke)", when);
    return fmt::format("{} waiting for rank(s) {} (dead or hung)", when, fmt::join(missing, ", "));
  }

  c10::intrusive_ptr<c10d::Store> store_;
  int rank_, world_;
  std::chrono::milliseconds timeout_;

 private:
  static std::vector<uint8_t> bytes_of(const torch::Tensor& t) {
    std::vector<uint8_t> b(t.numel() * sizeof(double));
    std::memcpy(b.data(), t.data_ptr<double>(), b.size());
    return b;
  }
  static torch::Tensor from_bytes(const std::vector<uint8_t>& b, int64_t n) {
    SIMU_CHECK(static_cast<int64_t>(b.size()) == n * 8, "all_reduce_mean: ranks disagree on the gradient size ({} vs {} bytes)",
               b.size(), n * 8);
    auto t = torch::empty({n}, torch::kFloat64);
    std::memcpy(t.data_ptr<double>(), b.data(), b.size());
    return t;
  }
  // Posts mine for this round, waits for every rank's (naming the missing ones), returns them in rank order.
  std::vector<std::vector<uint8_t>> exchange(const std::string& what, const std::vector<uint8_t>& mine) {
    const int64_t round = round_++;
    auto key = [&](int64_t rd, int r) { return fmt::format("simu/{}/{}", rd, r); };
    try {
      store_->set(key(round, rank_), mine);
    } catch (const std::exception&) {
      fail("rank {}: {} #{}: rank 0 is gone (it hosts the rendezvous store, which no longer answers); see rank 0's log",
           rank_, what, round);
    }
    std::vector<std::string> keys;
    for (int r = 0; r < world_; ++r) keys.push_back(key(round, r));
    const auto began = std::chrono::steady_clock::now();
    std::vector<std::vector<uint8_t>> out;
    try {
      store_->wait(keys, timeout_);
      for (auto& k : keys) out.push_back(store_->get(k));
    } catch (const std::exception&) {
      fail_hint("check the log of the named rank(s); raise dist.timeout_s if they are only slow", "rank {}: {} #{} {}",
                rank_, what, round, failure_cause([&](int r) { return keys[r]; }, began));
    }
    // Every rank has read round-2 by the time any rank posts this round's key: drop my old one.
    if (round >= 2) store_->deleteKey(key(round - 2, rank_));
    return out;
  }

  int64_t round_ = 0;
};

// NCCL for tensors, the store for small host-side exchanges.
class NcclCommunicator : public StoreCommunicator {
 public:
  NcclCommunicator(c10::intrusive_ptr<c10d::Store> store, int rank, int world, std::chrono::milliseconds timeout)
      : StoreCommunicator(store, rank, world, timeout) {
    auto opts = c10d::ProcessGroupNCCL::Options::create();
    opts->timeout = timeout;
    pg_ = c10::make_intrusive<c10d::ProcessGroupNCCL>(c10::make_intrusive<c10d::PrefixStore>("nccl", store), rank,
                                                      world, opts);
  }
  void all_reduce_mean(std::vector<torch::Tensor>& tensors) override {
    if (tensors.empty()) return;
    std::vector<at::Tensor> buf{flatten(tensors).detach().to(torch::kFloat32).contiguous()};
    c10d::AllreduceOptions o;
    o.reduceOp = c10d::ReduceOp::SUM;
    auto work = pg_->allreduce(buf, o);
    // The NCCL watchdog aborts the process when the collective exceeds opts->timeout.
    work->wait();
    unflatten((buf[0] / world_size()).to(tensors[0].scalar_type()), tensors);
  }
  std::string backend() const override { return "nccl"; }

 private:
  c10::intrusive_ptr<c10d::ProcessGroupNCCL> pg_;
};

#ifdef USE_C10D_GLOO
// c10d ProcessGroupGloo for tensors and metrics. Each collective is announced in the store first
// (simu/gloo/<round>/<rank>) so that a failure -- a peer's connection closed, or Gloo's timeout --
// can name the ranks that never reached it.
class GlooCommunicator : public StoreCommunicator {
 public:
  GlooCommunicator(c10::intrusive_ptr<c10d::Store> store, int rank, int world, std::chrono::milliseconds timeout)
      : StoreCommunicator(store, rank, world, timeout) {
    // A write to a dead peer's socket must be an error, not a SIGPIPE that kills this rank.
    ::signal(SIGPIPE, SIG_IGN);
    auto opts = c10d::ProcessGroupGloo::Options::create(timeout);
    // GLOO_SOCKET_IFNAME picks the interface (as in torch.distributed); else this host's address.
    const char* ifname = std::getenv("GLOO_SOCKET_IFNAME");
    opts->devices.push_back(ifname && *ifname ? c10d::ProcessGroupGloo::createDeviceForInterface(ifname)
                                              : c10d::ProcessGroupGloo::createDefaultDevice());
    try {
      pg_ = c10::make_intrusive<c10d::ProcessGroupGloo>(c10::make_intrusive<c10d::PrefixStore>("gloo", store), rank,
                                                        world, opts);
    } catch (const std::exception& e) {
      fail_hint("check that every rank started and can reach the others (GLOO_SOCKET_IFNAME selects the interface)",
                "rank {}: Gloo process group setup failed (world size {}, timeout {} s): {}", rank, world,
                timeout.count() / 1000.0, short_what(e));
    }
  }
  std::string backend() const override { return "gloo"; }

  void all_reduce_mean(std::vector<torch::Tensor>& tensors) override {
    if (tensors.empty()) return;
    // [N] in the tensors' dtype, on CPU (Gloo here is CPU-only).
    std::vector<at::Tensor> buf{flatten(tensors).detach().to(torch::kCPU).contiguous()};
    run("allreduce", [&] { return pg_->allreduce(buf, sum_options()); });
    unflatten((buf[0] / world_size()).to(tensors[0].device(), tensors[0].scalar_type()), tensors);
  }

  std::vector<double> all_reduce_sum(const std::vector<double>& values) override {
    std::vector<at::Tensor> buf{torch::tensor(values, torch::kFloat64)};
    if (!values.empty()) run("sum", [&] { return pg_->allreduce(buf, sum_options()); });
    auto t = buf[0].contiguous();
    return std::vector<double>(t.data_ptr<double>(), t.data_ptr<double>() + t.numel());
  }

  void barrier() override {
    run("barrier", [&] { return pg_->barrier(); });
  }

 private:
  static c10d::AllreduceOptions sum_options() {
    c10d::AllreduceOptions o;
    o.reduceOp = c10d::ReduceOp::SUM;
    return o;
  }
  std::string key(int64_t round, int r) const { return fmt::format("simu/gloo/{}/{}", round, r); }
  // Announces collective #round, runs it, waits for it; on failure names the ranks that never arrived.
  void run(const char* what, const std::function<c10::intrusive_ptr<c10d::Work>()>& op) {
    const int64_t round = round_++;
    try {
      store_->set(key(round, rank_), std::vector<uint8_t>{1});
    } catch (const std::exception& e) {
      fail("rank {}: gloo {} #{}: rank 0 is gone (it hosts the rendezvous store, which no longer answers); see rank 0's log",
           rank_, what, round);
    }
    const auto began = std::chrono::steady_clock::now();
    try {
      // Gloo ends the operation itself after the options' timeout; the margin lets its error win.
      op()->wait(timeout_ + std::chrono::seconds(5));
    } catch (const std::exception& e) {
      fail_hint("check the log of the named rank(s); raise dist.timeout_s if they are only slow",
                "rank {}: gloo {} #{} {} (gloo: {})", rank_, what, round,
                failure_cause([&](int r) { return key(round, r); }, began), short_what(e));
    }
    // Every rank entered this round, so all are done with the previous one: drop my old key.
    if (round >= 1) store_->deleteKey(key(round - 1, rank_));
  }

  c10::intrusive_ptr<c10d::ProcessGroupGloo> pg_;
  int64_t round_ = 0;
};
#endif

// World of one: nothing to do.
class SoloCommunicator : public Communicator {
 public:
  int rank() const override { return 0; }
  int world_size() const override { return 1; }
  std::string backend() const override { return "single"; }
  void all_reduce_mean(std::vector<torch::Tensor>&) override {}
  std::vector<double> all_reduce_sum(const std::vector<double>& v) override { return v; }
  void barrier() override {}
};

}  // namespace

std::unique_ptr<Communicator> make_solo_communicator() { return std::make_unique<SoloCommunicator>(); }

std::string first_slurm_host(const std::string& nodelist) {
  // The first entry ends at the first comma outside brackets.
  size_t end = 0;
  int depth = 0;
  for (; end < nodelist.size(); ++end) {
    if (nodelist[end] == '[') ++depth;
    else if (nodelist[end] == ']') --depth;
    else if (nodelist[end] == ',' && depth == 0) break;
  }
  const std::string first = nodelist.substr(0, end);
  SIMU_CHECK(!first.empty(), "Slurm node list '{}': no host in it (set MASTER_ADDR)", nodelist);
  const size_t open = first.find('[');
  if (open == std::string::npos) return first;
  const size_t close = first.find(']', open);
  SIMU_CHECK(close != std::string::npos, "Slurm node list '{}': '[' without ']' (set MASTER_ADDR)", nodelist);
  // Within the brackets, the first range or number: "03-05,07" -> "03" (zero padding kept).
  const std::string inside = first.substr(open + 1, close - open - 1);
  const std::string lead = inside.substr(0, inside.find_first_of(",-"));
  SIMU_CHECK(!lead.empty(), "Slurm node list '{}': empty brackets (set MASTER_ADDR)", nodelist);
  const std::string rest = first.substr(close + 1);  // may hold another bracket: "a[1-2]b[3-4]"
  return first.substr(0, open) + lead + (rest.empty() ? "" : first_slurm_host(rest));
}

DistEnv DistEnv::from_environment() {
  DistEnv e;
  if (std::getenv("RANK") || std::getenv("WORLD_SIZE")) {
    e.rank = env_int("RANK", 0);
    e.world_size = env_int("WORLD_SIZE", 1);
    e.local_rank = env_int("LOCAL_RANK", e.rank);
  } else if (std::getenv("SLURM_PROCID")) {
    e.rank = env_int("SLURM_PROCID", 0);
    e.world_size = env_int("SLURM_NTASKS", 1);
    e.local_rank = env_int("SLURM_LOCALID", 0);
  }
  if (const char* a = std::getenv("MASTER_ADDR"); a && *a) {
    e.master_addr = a;
  } else if (std::getenv("SLURM_PROCID") && !std::getenv("RANK")) {
    for (const char* k : {"SLURM_STEP_NODELIST", "SLURM_JOB_NODELIST", "SLURM_NODELIST"})
      if (const char* l = std::getenv(k); l && *l) {
        e.master_addr = first_slurm_host(l);
        break;
      }
  }
  e.master_port = env_int("MASTER_PORT", e.master_port);
  SIMU_CHECK(e.world_size >= 1 && e.rank >= 0 && e.rank < e.world_size,
             "distributed environment: RANK {} is not in [0, WORLD_SIZE={})", e.rank, e.world_size);
  return e;
}

c10::intrusive_ptr<c10d::Store> connect_store(const DistEnv& env, std::chrono::milliseconds timeout) {
  c10d::TCPStoreOptions o;
  o.port = static_cast<uint16_t>(env.master_port);
  o.isServer = env.rank == 0;
  o.numWorkers = env.world_size;
  o.waitWorkers = true;
  o.timeout = timeout;
  try {
    return c10::make_intrusive<c10d::TCPStore>(env.master_addr, o);
  } catch (const std::exception& e) {
    fail_hint("check MASTER_ADDR/MASTER_PORT and that every rank started",
              "rank {}: rendezvous at {}:{} failed (world size {}, timeout {} s): {}", env.rank, env.master_addr,
              env.master_port, env.world_size, timeout.count() / 1000.0, short_what(e));
  }
}

std::unique_ptr<Communicator> make_store_communicator(c10::intrusive_ptr<c10d::Store> store, int rank, int world_size,
                                                      std::chrono::milliseconds timeout) {
  return std::make_unique<StoreCommunicator>(std::move(store), rank, world_size, timeout);
}

bool have_gloo() {
#ifdef USE_C10D_GLOO
  return true;
#else
  return false;
#endif
}

std::unique_ptr<Communicator> make_cpu_communicator(c10::intrusive_ptr<c10d::Store> store, int rank, int world_size,
                                                    std::chrono::milliseconds timeout) {
#ifdef USE_C10D_GLOO
  return std::make_unique<GlooCommunicator>(std::move(store), rank, world_size, timeout);
#else
  static bool warned = false;
  if (!warned && rank == 0)
    simu::log::warn("this build has no gloo headers (install libgloo-dev and reconfigure): CPU ranks average "
                    "through the TCPStore instead of c10d ProcessGroupGloo");
  warned = true;
  return std::make_unique<StoreCommunicator>(std::move(store), rank, world_size, timeout);
#endif
}

std::unique_ptr<Communicator> Communicator::create(const DistEnv& env, const torch::Device& device,
                                                   std::chrono::milliseconds timeout) {
  if (env.world_size == 1) return std::make_unique<SoloCommunicator>();
  auto store = connect_store(env, timeout);
  if (device.is_cuda()) return std::make_unique<NcclCommunicator>(store, env.rank, env.world_size, timeout);
  return make_cpu_communicator(store, env.rank, env.world_size, timeout);
}

int free_port() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  SIMU_CHECK(fd >= 0, "free_port: socket(): {}", std::strerror(errno));
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  a.sin_port = 0;
  socklen_t len = sizeof(a);
  if (::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof(a)) != 0 ||
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) != 0) {
    ::close(fd);
    fail("free_port: cannot bind a loopback port: {}", std::strerror(errno));
  }
  const int port = ntohs(a.sin_port);
  ::close(fd);
  return port;
}

}  // namespace simu::training
