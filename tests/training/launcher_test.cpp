// The local launcher: a rank that dies or hangs ends the whole job with an error naming it.
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <string>
#include <thread>

#include "common/error.h"
#include "test_util.h"
#include "training/distributed.h"
#include "training/launcher.h"

using namespace simu::training;

// Child side: behaviour chosen by SIMU_TEST_LAUNCH_MODE ("die": rank 1 exits 3; "hang": rank 1
// stops sending heartbeats; "ok": every rank exits 0). Rank 0 keeps beating for up to 30 s.
TEST(LauncherChild, Rank) {
  const char* mode = std::getenv("SIMU_TEST_LAUNCH_MODE");
  if (!mode || !std::getenv("RANK")) GTEST_SKIP() << "helper for Launcher.*";
  const int rank = std::atoi(std::getenv("RANK"));
  const std::string m = mode;
  if (m == "ok") ::_exit(0);
  // "threads": the launcher shares the cores between the ranks through OMP_NUM_THREADS, which sizes
  // torch's intra-op pool at start-up (this test binary's main then sets its own count).
  if (m == "threads") {
    const int want = std::max(1, static_cast<int>(std::thread::hardware_concurrency()) / 2);
    const char* omp = std::getenv("OMP_NUM_THREADS");
    ::_exit(omp && std::atoi(omp) == want ? 0 : 4);
  }
  if (rank == 1 && m == "die") ::_exit(3);
  // "stop": rank 1 stops itself (SIGSTOP: it cannot act on SIGTERM). "stop-wait": the same, and rank 0
  // gives up after 2 s as a collective timing out on it would (exit 5).
  if (rank == 1 && (m == "stop" || m == "stop-wait")) {
    heartbeat();
    ::raise(SIGSTOP);
  }
  for (int i = 0; i < 300; ++i) {
    if (rank == 0 && m == "stop-wait" && i == 20) ::_exit(5);
    if (rank == 0) heartbeat();
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  ::_exit(0);
}

namespace {
std::string launch(const char* mode, int hang_s, double& seconds) {
  ::setenv("SIMU_TEST_LAUNCH_MODE", mode, 1);
  const auto t0 = std::chrono::steady_clock::now();
  std::string err;
  try {
    launch_local_ranks(2, {"--gtest_filter=LauncherChild.Rank"}, std::chrono::seconds(hang_s));
  } catch (const simu::Error& e) {
    err = e.what();
  }
  seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  ::unsetenv("SIMU_TEST_LAUNCH_MODE");
  return err;
}
}  // namespace

TEST(Launcher, AllRanksSucceed) {
  double s = 0;
  EXPECT_EQ(launch("ok", 20, s), "");
}

TEST(Launcher, RanksShareTheCores) {
  const char* before = std::getenv("OMP_NUM_THREADS");
  const std::string saved = before ? before : "";
  ::unsetenv("OMP_NUM_THREADS");
  double s = 0;
  // A rank whose OMP_NUM_THREADS is not cores / 2 exits with status 4.
  EXPECT_EQ(launch("threads", 20, s), "");
  if (before) ::setenv("OMP_NUM_THREADS", saved.c_str(), 1);
}

TEST(Launcher, DeadRankEndsJobNamingIt) {
  double s = 0;
  const auto err = launch("die", 20, s);
  EXPECT_NE(err.find("rank 1 exited with status 3"), std::string::npos) << err;
  EXPECT_LT(s, 20.0);
}

TEST(Launcher, HungRankEndsJobNamingIt) {
  double s = 0;
  const auto err = launch("hang", 6, s);
  EXPECT_NE(err.find("rank 1 made no progress for 6 s"), std::string::npos) << err;
  EXPECT_LT(s, 20.0);
}

// A stopped rank (SIGSTOP) ends the job within the hang limit: SIGKILL at once, no 5 s SIGTERM wait.
TEST(Launcher, StoppedRankIsKilledWithinTheLimit) {
  double s = 0;
  const auto err = launch("stop", 4, s);
  EXPECT_NE(err.find("rank 1 made no progress for 4 s (stopped by a signal)"), std::string::npos) << err;
  EXPECT_LT(s, 4 + 3.0) << err;  // was limit + 5 s (SIGTERM ignored by a stopped process)
}

// A rank that fails waiting for a stopped one: the stopped rank is named as the cause.
TEST(Launcher, FailureCausedByAStoppedRankNamesIt) {
  double s = 0;
  const auto err = launch("stop-wait", 20, s);
  EXPECT_NE(err.find("rank(s) 1 stopped (hung) and rank 0 exited with status 5 waiting for it"), std::string::npos)
      << err;
  EXPECT_LT(s, 10.0) << err;
}
