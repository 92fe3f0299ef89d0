// Distributed plumbing with plain tensors: TCPStore rendezvous on loopback, averaging, dead-rank errors.
#include <sys/wait.h>
#include <unistd.h>

#include <cstdlib>
#include <future>
#include <thread>

#include "common/error.h"
#include "test_util.h"
#include "training/distributed.h"

using namespace simu::training;

namespace {

// Rank `rank` of a 2-rank job on loopback `port`: the job's store, connected within 20 s.
c10::intrusive_ptr<c10d::Store> rank_store(int rank, int port) {
  DistEnv env;
  env.rank = rank;
  env.world_size = 2;
  env.master_port = port;
  return connect_store(env, std::chrono::seconds(20));
}

// Rank 0's side of a lost peer: one all-reduce that rank 1 joins, then one it does not. Returns the
// second one's error (with " (too late)" when it took 10 s or more), or "no error". 10 s: the callers'
// collective timeouts (1.5 and 2 s) plus 8 s of scheduling margin on a loaded machine, half the 20 s
// store timeout a missed detection would run into.
std::string error_after_peer_left(Communicator& comm) {
  std::vector<torch::Tensor> ts{torch::ones({2})};
  comm.all_reduce_mean(ts);  // rank 1 joins this one
  const auto t0 = std::chrono::steady_clock::now();
  try {
    comm.all_reduce_mean(ts);  // rank 1 is gone
    return std::string("no error");
  } catch (const simu::Error& e) {
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return std::string(e.what()) + (s < 10 ? "" : " (too late)");
  }
}

}  // namespace

// Two ranks (threads) average their tensors; metrics sums agree.
TEST(Distributed, StoreAllReduceAveragesAcrossRanks) {
  const int port = free_port();
  auto rank_fn = [port](int rank) {
    auto comm = make_store_communicator(rank_store(rank, port), rank, 2, std::chrono::seconds(20));
    std::vector<torch::Tensor> ts{torch::full({3, 2}, 1.0f + rank), torch::full({4}, 10.0f * rank)};
    for (int round = 0; round < 4; ++round) comm->all_reduce_mean(ts);  // idempotent after the first
    auto sums = comm->all_reduce_sum({1.0 + rank, 2.0});
    comm->barrier();
    return std::make_tuple(ts[0].clone(), ts[1].clone(), sums);
  };
  auto f0 = std::async(std::launch::async, rank_fn, 0);
  auto f1 = std::async(std::launch::async, rank_fn, 1);
  auto [a0, b0, s0] = f0.get();
  auto [a1, b1, s1] = f1.get();
  EXPECT_TRUE(torch::equal(a0, torch::full({3, 2}, 1.5f)));
  EXPECT_TRUE(torch::equal(b0, torch::full({4}, 5.0f)));
  EXPECT_TRUE(torch::equal(a0, a1) && torch::equal(b0, b1));
  EXPECT_EQ(s0, (std::vector<double>{3.0, 4.0}));
  EXPECT_EQ(s0, s1);
}

// A rank that stops taking part ends the collective with an error naming it, within the timeout.
TEST(Distributed, DeadRankIsNamedWithinTimeout) {
  const int port = free_port();
  auto survivor = std::async(std::launch::async, [port] {
    auto comm = make_store_communicator(rank_store(0, port), 0, 2, std::chrono::milliseconds(1500));
    return error_after_peer_left(*comm);
  });
  {
    auto comm = make_store_communicator(rank_store(1, port), 1, 2, std::chrono::seconds(5));
    std::vector<torch::Tensor> ts{torch::ones({2})};
    comm->all_reduce_mean(ts);
  }  // rank 1 "dies"
  const std::string msg = survivor.get();
  EXPECT_NE(msg.find("waiting for rank(s) 1"), std::string::npos) << msg;
  EXPECT_EQ(msg.find("too late"), std::string::npos) << msg;
}

// Environment parsing: torchrun variables, then Slurm's.
TEST(Distributed, EnvFromTorchrunAndSlurm) {
  for (const char* k : {"RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT", "SLURM_PROCID", "SLURM_NTASKS", "SLURM_LOCALID"})
    ::unsetenv(k);
  EXPECT_EQ(DistEnv::from_environment().world_size, 1);
  ::setenv("SLURM_PROCID", "3", 1);
  ::setenv("SLURM_NTASKS", "8", 1);
  ::setenv("SLURM_LOCALID", "1", 1);
  ::setenv("MASTER_PORT", "12345", 1);
  auto e = DistEnv::from_environment();
  EXPECT_EQ(e.rank, 3);
  EXPECT_EQ(e.world_size, 8);
  EXPECT_EQ(e.local_rank, 1);
  EXPECT_EQ(e.master_port, 12345);
  ::setenv("RANK", "1", 1);
  ::setenv("WORLD_SIZE", "2", 1);
  ::setenv("LOCAL_RANK", "1", 1);
  e = DistEnv::from_environment();
  EXPECT_EQ(e.rank, 1);
  EXPECT_EQ(e.world_size, 2);
  ::setenv("RANK", "2", 1);
  EXPECT_THROW(DistEnv::from_environment(), simu::Error);
  for (const char* k : {"RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_PORT", "SLURM_PROCID", "SLURM_NTASKS", "SLURM_LOCALID"})
    ::unsetenv(k);
}

// Under Slurm without MASTER_ADDR the rendezvous host is the first node of the step's node list.
TEST(Distributed, SlurmMasterAddrIsTheFirstNode) {
  EXPECT_EQ(first_slurm_host("gpu[03-05,07],cpu1"), "gpu03");
  EXPECT_EQ(first_slurm_host("a-[2-4]-ib"), "a-2-ib");
  EXPECT_EQ(first_slurm_host("n1,n2"), "n1");
  EXPECT_EQ(first_slurm_host("node7"), "node7");
  EXPECT_EQ(first_slurm_host("r[1-2]n[08-09]"), "r1n08");
  EXPECT_THROW(first_slurm_host(""), simu::Error);
  EXPECT_THROW(first_slurm_host("gpu[1-4"), simu::Error);
  for (const char* k : {"RANK", "WORLD_SIZE", "MASTER_ADDR", "SLURM_STEP_NODELIST", "SLURM_JOB_NODELIST", "SLURM_NODELIST"})
    ::unsetenv(k);
  ::setenv("SLURM_PROCID", "0", 1);
  ::setenv("SLURM_NTASKS", "4", 1);
  ::setenv("SLURM_JOB_NODELIST", "big[10-11]", 1);
  EXPECT_EQ(DistEnv::from_environment().master_addr, "big10");
  ::setenv("SLURM_STEP_NODELIST", "step[2-3]", 1);  // the step's own nodes win over the job's
  EXPECT_EQ(DistEnv::from_environment().master_addr, "step2");
  ::setenv("MASTER_ADDR", "10.0.0.9", 1);  // an explicit address wins
  EXPECT_EQ(DistEnv::from_environment().master_addr, "10.0.0.9");
  for (const char* k : {"MASTER_ADDR", "SLURM_STEP_NODELIST", "SLURM_JOB_NODELIST", "SLURM_PROCID", "SLURM_NTASKS"})
    ::unsetenv(k);
}

namespace {
// Rank `rank` of a 2-rank CPU job on loopback port: the communicator create() would use on CPU.
std::unique_ptr<Communicator> cpu_rank(int rank, int port, std::chrono::milliseconds timeout) {
  return make_cpu_communicator(rank_store(rank, port), rank, 2, timeout);
}
// A barrier expected to fail: its error message ("no error" if it returned) and the seconds it took.
std::pair<std::string, double> failing_barrier(Communicator& comm) {
  const auto t0 = std::chrono::steady_clock::now();
  std::string msg = "no error";
  try {
    comm.barrier();
  } catch (const simu::Error& e) {
    msg = e.what();
  }
  return {msg, std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count()};
}
}  // namespace

// The CPU communicator is c10d ProcessGroupGloo: means, sums and barriers agree across two ranks.
TEST(Distributed, GlooAllReduceAveragesAcrossRanks) {
  ASSERT_TRUE(have_gloo()) << "this build has no gloo headers: install libgloo-dev and reconfigure";
  const int port = free_port();
  auto rank_fn = [port](int rank) {
    auto comm = cpu_rank(rank, port, std::chrono::seconds(20));
    std::vector<torch::Tensor> ts{torch::full({3, 2}, 1.0f + rank), torch::full({4}, 10.0f * rank),
                                  torch::full({2}, 0.25 * (rank + 1), torch::kFloat64)};
    comm->all_reduce_mean(ts);
    auto sums = comm->all_reduce_sum({1.0 + rank, 2.0, 1e-17 * rank});
    comm->barrier();
    return std::make_tuple(comm->backend(), ts, sums);
  };
  auto f0 = std::async(std::launch::async, rank_fn, 0);
  auto f1 = std::async(std::launch::async, rank_fn, 1);
  auto [be0, t0, s0] = f0.get();
  auto [be1, t1, s1] = f1.get();
  EXPECT_EQ(be0, "gloo");
  EXPECT_EQ(be1, "gloo");
  EXPECT_TRUE(torch::equal(t0[0], torch::full({3, 2}, 1.5f)));
  EXPECT_TRUE(torch::equal(t0[1], torch::full({4}, 5.0f)));
  EXPECT_TRUE(torch::equal(t0[2], torch::full({2}, 0.375, torch::kFloat64)));
  EXPECT_EQ(t0[2].scalar_type(), torch::kFloat64);
  for (int i = 0; i < 3; ++i) EXPECT_TRUE(torch::equal(t0[i], t1[i]));
  EXPECT_EQ(s0, (std::vector<double>{3.0, 4.0, 1e-17}));
  EXPECT_EQ(s0, s1);
}

// Gloo: a rank that leaves the job is named by the survivor's next collective, within the timeout.
TEST(Distributed, GlooDeadRankIsNamedWithinTimeout) {
  ASSERT_TRUE(have_gloo()) << "this build has no gloo headers";
  const int port = free_port();
  auto survivor = std::async(std::launch::async, [port] {
    auto comm = cpu_rank(0, port, std::chrono::milliseconds(2000));
    return error_after_peer_left(*comm);
  });
  {
    auto comm = cpu_rank(1, port, std::chrono::seconds(5));
    std::vector<torch::Tensor> ts{torch::ones({2})};
    comm->all_reduce_mean(ts);
  }  // rank 1 "dies": its process group closes its connections
  const std::string msg = survivor.get();
  EXPECT_NE(msg.find("gloo allreduce"), std::string::npos) << msg;
  EXPECT_NE(msg.find("waiting for rank(s) 1"), std::string::npos) << msg;
  EXPECT_EQ(msg.find("too late"), std::string::npos) << msg;
}

// Gloo: a rank that is alive but never reaches the collective (hung) is named after the timeout.
TEST(Distributed, GlooHungRankIsNamedAfterTimeout) {
  ASSERT_TRUE(have_gloo()) << "this build has no gloo headers";
  const int port = free_port();
  std::promise<void> survivor_done;
  auto done = survivor_done.get_future().share();
  auto hung = std::async(std::launch::async, [port, done] {
    auto comm = cpu_rank(1, port, std::chrono::seconds(20));
    auto sums = comm->all_reduce_sum({1.0});  // takes part once
    done.wait();                              // then hangs until rank 0 has given up
    return sums;
  });
  auto comm = cpu_rank(0, port, std::chrono::milliseconds(1500));
  comm->all_reduce_sum({1.0});
  const auto [msg, s] = failing_barrier(*comm);
  survivor_done.set_value();
  EXPECT_EQ(hung.get(), std::vector<double>{2.0});
  EXPECT_NE(msg.find("gloo barrier"), std::string::npos) << msg;
  EXPECT_NE(msg.find("waiting for rank(s) 1"), std::string::npos) << msg;
  // Not before the 1.5 s timeout (1.0: 0.5 s for the timer's granularity), and within it plus 8.5 s
  // of scheduling margin (rank 1's own timeout is 20 s).
  EXPECT_GE(s, 1.0) << "failed before the timeout: " << msg;
  EXPECT_LT(s, 10.0) << msg;
}

// Child side of GlooRankZeroDeathIsNamedPlainly: rank 0 in its own process (it hosts the store),
// one collective with rank 1, then it dies at once (_exit: no clean shutdown).
TEST(DistributedChild, RankZeroDies) {
  const char* port = std::getenv("SIMU_TEST_RANK0_PORT");
  if (!port) GTEST_SKIP() << "helper for Distributed.GlooRankZeroDeathIsNamedPlainly";
  auto comm = cpu_rank(0, std::atoi(port), std::chrono::seconds(20));
  comm->all_reduce_sum({1.0});
  ::_exit(0);
}

// When rank 0 (the store's host) dies, rank 1 says so plainly and at once: "rank 0 is gone", no C++
// backtrace, not "timeout", and it never lists itself among the ranks it waits for.
TEST(Distributed, GlooRankZeroDeathIsNamedPlainly) {
  ASSERT_TRUE(have_gloo()) << "this build has no gloo headers";
  const int port = free_port();
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    ::setenv("SIMU_TEST_RANK0_PORT", std::to_string(port).c_str(), 1);
    ::execl("/proc/self/exe", "test_training", "--gtest_filter=DistributedChild.RankZeroDies", nullptr);
    ::_exit(127);
  }
  auto comm = cpu_rank(1, port, std::chrono::seconds(20));
  comm->all_reduce_sum({1.0});
  int status = 0;
  ::waitpid(pid, &status, 0);  // rank 0 is gone now
  const auto [msg, s] = failing_barrier(*comm);
  EXPECT_NE(msg.find("rank 1: gloo barrier"), std::string::npos) << msg;
  EXPECT_NE(msg.find("rank 0 is gone"), std::string::npos) << msg;
  EXPECT_EQ(msg.find("timed out"), std::string::npos) << msg;
  EXPECT_EQ(msg.find("0, 1"), std::string::npos) << msg;
  EXPECT_EQ(msg.find("Exception raised from"), std::string::npos) << msg;  // c10's backtrace
  EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
  // At once (the connection resets), not at the 20 s timeout: 10 s is half of it.
  EXPECT_LT(s, 10.0) << msg;
}
