// The local launcher: a rank that dies or hangs ends the whole job with an error naming it.
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <string>
#include <thread>

#include "common/error.h"
#include "test_util.h"
#include "training/distributed.h"

using namespace simu::training;

// Child side: behaviour chosen by SIMU_TEST_LAUNCH_MODE ("die": rank 1 exits 3; "hang": rank 1
// stops sending heartbeats; "ok": every rank exits 0). Rank 0 keeps beating for up to 30 s.
TEST(LauncherChild, Rank) {
  const char* mode = std::getenv("SIMU_TEST_LAUNCH_MODE");
  if (!mode || !std::getenv("RANK")) GTEST_SKIP() << "helper for Launcher.*";
  const int rank = std::atoi(std::getenv("RANK"));
  const std::string m = mode;
  if (m == "ok") ::_exit(0);
  if (rank == 1 && m == "die") ::_exit(3);
  for (int i = 0; i < 300; ++i) {
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
