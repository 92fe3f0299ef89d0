// Checkpoint directories: round trip, keep-last-N, resolve, and kill -9 in the middle of a write.
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <thread>

#include "common/error.h"
#include "test_util.h"
#include "training/checkpoint.h"

using namespace simu::training;

namespace {
CheckpointData sample(int64_t step, int64_t n = 16) {
  CheckpointData d;
  d.step = step;
  d.adapter["base_model.model.x.lora_A.weight"] = torch::full({n, 4}, static_cast<float>(step));
  d.optimizer["base_model.model.x.lora_A.weight.exp_avg"] = torch::full({n, 4}, 0.5f * step);
  d.optimizer["rng.torch_cpu"] = at::detail::getDefaultCPUGenerator().get_state();
  d.state["data_position"] = {{"epoch", 0}, {"step", step}};
  return d;
}
}  // namespace

TEST(Checkpoint, RoundTripKeepLastAndLatest) {
  const std::string root = simu::testing::temp_dir("ckpt");
  for (int s = 1; s <= 4; ++s) save_checkpoint(root, sample(s * 10), 2);
  auto all = list_checkpoints(root);
  ASSERT_EQ(all.size(), 2u);
  EXPECT_EQ(std::filesystem::path(all[0]).filename(), "step_00000030");
  EXPECT_EQ(resolve_resume(root, "latest"), root + "/step_00000040");
  auto d = load_checkpoint(all.back());
  EXPECT_EQ(d.step, 40);
  EXPECT_TRUE(torch::equal(d.adapter.at("base_model.model.x.lora_A.weight"), torch::full({16, 4}, 40.0f)));
  EXPECT_EQ(d.state["data_position"]["step"], 40);
  EXPECT_TRUE(torch::equal(d.optimizer.at("rng.torch_cpu"), at::detail::getDefaultCPUGenerator().get_state()));
  // Rewriting the same step replaces it.
  auto again = sample(40);
  again.adapter["base_model.model.x.lora_A.weight"].fill_(7);
  save_checkpoint(root, again, 2);
  EXPECT_EQ(load_checkpoint(root + "/step_00000040").adapter.at("base_model.model.x.lora_A.weight")[0][0].item<float>(), 7);
}

TEST(Checkpoint, ClearErrors) {
  const std::string root = simu::testing::temp_dir("ckpt_err");
  try {
    resolve_resume(root, "latest");
    FAIL();
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("no checkpoint under"), std::string::npos) << e.what();
  }
  std::filesystem::create_directories(root + "/step_00000001");
  try {
    load_checkpoint(root + "/step_00000001");
    FAIL();
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("missing adapter.safetensors"), std::string::npos) << e.what();
  }
}

// Child side of the kill test: writes checkpoints forever (slowly, SIMU_CHECKPOINT_STALL_MS).
TEST(CheckpointChild, WriteForever) {
  const char* root = std::getenv("SIMU_TEST_CKPT_ROOT");
  if (!root) GTEST_SKIP() << "helper for Checkpoint.KillDuringWriteLeavesPreviousLoadable";
  for (int64_t s = std::atoll(std::getenv("SIMU_TEST_CKPT_START"));; ++s) save_checkpoint(root, sample(s, 1 << 16), 2);
}

// kill -9 at each phase of a write (the writer raises SIGKILL there): what is visible afterwards
// loads and holds what was written for its step, an interrupted prune or replacement leaves no
// half-deleted step and loses no step, and the next writer clears the temporaries.
TEST(Checkpoint, KillAtEveryWritePhaseLeavesCheckpointsLoadable) {
  struct Case {
    const char* phase;
    int64_t start;   // first step the child writes (1 exists already: the replace branch)
    int64_t newest;  // newest visible step after the kill
    bool exchange;   // replace by an atomic swap (false: the move-aside fallback)
  };
  for (const Case c : {Case{"adapter", 2, 1, true}, Case{"optimizer", 2, 1, true}, Case{"state", 2, 1, true},
                       Case{"replace", 1, 1, true}, Case{"replace", 1, 1, false}, Case{"prune", 2, 2, true}}) {
    SCOPED_TRACE(std::string(c.phase) + (c.exchange ? "" : " (move-aside fallback)"));
    const std::string root =
        simu::testing::temp_dir(std::string("ckpt_phase_") + c.phase + (c.exchange ? "" : "_fallback"));
    save_checkpoint(root, sample(0, 64), 2);
    save_checkpoint(root, sample(1, 64), 2);
    const pid_t pid = ::fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
      ::setenv("SIMU_TEST_CKPT_ROOT", root.c_str(), 1);
      ::setenv("SIMU_TEST_CKPT_START", std::to_string(c.start).c_str(), 1);
      ::setenv("SIMU_CHECKPOINT_KILL_AT", c.phase, 1);
      if (!c.exchange) ::setenv("SIMU_CHECKPOINT_RENAME_EXCHANGE", "0", 1);
      ::execl("/proc/self/exe", "test_training", "--gtest_filter=CheckpointChild.WriteForever", nullptr);
      ::_exit(127);
    }
    // The child must die at the phase within 30 s; otherwise the phase was never reached.
    int status = 0;
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(30);
    while (::waitpid(pid, &status, WNOHANG) == 0) {
      if (std::chrono::steady_clock::now() > until) {
        ::kill(pid, SIGKILL);
        ::waitpid(pid, &status, 0);
        FAIL() << "the writer never reached phase " << c.phase;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    ASSERT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << "status " << status;
    auto all = list_checkpoints(root);
    ASSERT_FALSE(all.empty());
    EXPECT_EQ(load_checkpoint(all.back()).step, c.newest);
    for (const auto& dir : all) {
      auto d = load_checkpoint(dir);
      EXPECT_EQ(d.adapter.at("base_model.model.x.lora_A.weight")[0][0].item<float>(), static_cast<float>(d.step)) << dir;
      EXPECT_EQ(d.optimizer.at("base_model.model.x.lora_A.weight.exp_avg")[5][1].item<float>(), 0.5f * d.step) << dir;
    }
    // The next writer puts a moved-aside step back in place and clears every temporary.
    save_checkpoint(root, sample(1000, 4), 0);
    EXPECT_TRUE(std::filesystem::is_directory(root + "/step_00000001")) << "step 1 lost";
    EXPECT_EQ(load_checkpoint(root + "/step_00000001").step, 1);
    for (const auto& e : std::filesystem::directory_iterator(root))
      EXPECT_NE(e.path().filename().string().rfind(".tmp-", 0), 0u) << e.path();
  }
}

// kill -9 at several moments during writes (the writer pauses 20 ms between its files): every
// visible checkpoint loads and holds what was written for its step.
TEST(Checkpoint, KillDuringWriteLeavesPreviousLoadable) {
  const std::string root = simu::testing::temp_dir("ckpt_kill");
  save_checkpoint(root, sample(0, 1 << 16), 2);
  auto newest = [&] { return load_checkpoint(*latest_checkpoint(root)).step; };
  for (int delay_ms : {5, 25, 45, 65, 85}) {
    const int64_t before = newest();
    const pid_t pid = ::fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
      ::setenv("SIMU_TEST_CKPT_ROOT", root.c_str(), 1);
      ::setenv("SIMU_TEST_CKPT_START", std::to_string(before + 1).c_str(), 1);
      ::setenv("SIMU_CHECKPOINT_STALL_MS", "20", 1);
      ::execl("/proc/self/exe", "test_training", "--gtest_filter=CheckpointChild.WriteForever", nullptr);
      ::_exit(127);
    }
    // Wait until the child has completed one checkpoint, then kill it `delay_ms` into the next.
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(30);
    while (std::chrono::steady_clock::now() < until) {
      auto l = latest_checkpoint(root);
      if (l && std::filesystem::path(*l).filename().string() > fmt::format("step_{:08d}", before)) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms));
    ::kill(pid, SIGKILL);
    int status = 0;
    ::waitpid(pid, &status, 0);
    ASSERT_TRUE(WIFSIGNALED(status)) << "child ended by itself (status " << status << ")";
    auto all = list_checkpoints(root);
    ASSERT_FALSE(all.empty());
    EXPECT_GT(newest(), before);
    for (const auto& dir : all) {
      auto d = load_checkpoint(dir);
      EXPECT_EQ(d.adapter.at("base_model.model.x.lora_A.weight")[0][0].item<float>(), static_cast<float>(d.step)) << dir;
      EXPECT_EQ(d.optimizer.at("base_model.model.x.lora_A.weight.exp_avg")[5][1].item<float>(), 0.5f * d.step) << dir;
    }
  }
  // The next writer clears the killed writer's temporary directory.
  save_checkpoint(root, sample(1000, 4), 2);
  for (const auto& e : std::filesystem::directory_iterator(root))
    EXPECT_NE(e.path().filename().string().rfind(".tmp-", 0), 0u) << e.path();
}
