// TensorBoard event files (CRC32C, framing, read back by TensorBoard itself), metrics lines, progress.
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "common/fs.h"
#include "common/error.h"
#include "test_util.h"
#include "training/observe.h"

using namespace simu::training;

// CRC-32C check value of "123456789" (RFC 3720 / iSCSI) and a 32-byte-zero vector.
TEST(TensorBoard, Crc32cKnownValues) {
  EXPECT_EQ(crc32c("123456789", 9), 0xE3069283u);
  const std::string zeros(32, '\0');
  EXPECT_EQ(crc32c(zeros.data(), zeros.size()), 0x8A9136AAu);
}

namespace {
// Runs `body` (Python; `ea` is a loaded EventAccumulator of dir) under SIMU_PYTHON and returns what it
// printed; "" with *skip set when that Python has no tensorboard module.
std::string read_with_tensorboard(const std::string& dir, const std::string& body, bool* skip) {
  const std::string py = simu::testing::python_exe();
  *skip = std::system((py + " -c 'import tensorboard' >/dev/null 2>&1").c_str()) != 0;
  if (*skip) return "";
  const std::string script = dir + "/read.py", out = dir + "/out.txt";
  std::ofstream(script) << "import sys\n"
                           "from tensorboard.backend.event_processing.event_accumulator import EventAccumulator\n"
                           "ea = EventAccumulator(sys.argv[1]); ea.Reload()\n"
                        << body;
  EXPECT_EQ(std::system((py + " " + script + " " + dir + " > " + out + " 2>/dev/null").c_str()), 0) << script;
  return simu::fs::read_file(out);
}
}  // namespace

// The file opens in TensorBoard's EventAccumulator with the scalars we wrote.
TEST(TensorBoard, ReadBackByTensorBoard) {
  const std::string dir = simu::testing::temp_dir("tb");
  {
    TensorBoardWriter w(dir);
    w.add_scalars(1, {{"loss", 0.5}, {"accuracy", 0.25}});
    w.add_scalars(2, {{"loss", 0.375}, {"accuracy", 0.75}});
  }
  bool skip = false;
  const std::string got = read_with_tensorboard(dir,
                                                "for tag in sorted(ea.Tags()['scalars']):\n"
                                                "    for e in ea.Scalars(tag): print(tag, e.step, repr(e.value))\n",
                                                &skip);
  if (skip) GTEST_SKIP() << simu::testing::python_exe() << " has no tensorboard module";
  EXPECT_EQ(got, "accuracy 1 0.25\naccuracy 2 0.75\nloss 1 0.5\nloss 2 0.375\n");
}

// A resumed run's event file starts with a SessionLog START at its first new step: TensorBoard shows
// the points the killed run logged after its checkpoint (steps 5, 6) no more, only the new ones.
TEST(TensorBoard, ResumedRunReplacesStepsAfterTheCheckpoint) {
  const std::string dir = simu::testing::temp_dir("tb_resume");
  {
    TensorBoardWriter killed(dir);
    for (int s = 1; s <= 6; ++s) killed.add_scalars(s, {{"loss", s}});
  }
  {
    TensorBoardWriter resumed(dir);
    resumed.session_start(5);
    for (int s = 5; s <= 6; ++s) resumed.add_scalars(s, {{"loss", 10 * s}});
  }
  bool skip = false;
  const std::string got =
      read_with_tensorboard(dir, "print(' '.join('%d:%g' % (e.step, e.value) for e in ea.Scalars('loss')))\n", &skip);
  if (skip) GTEST_SKIP() << simu::testing::python_exe() << " has no tensorboard module";
  EXPECT_EQ(got, "1:1 2:2 3:3 4:4 5:50 6:60\n");
}

// A resumed run drops metric lines past its checkpoint step and appends.
TEST(Metrics, ResumeTruncatesLaterLines) {
  const std::string dir = simu::testing::temp_dir("metrics");
  const std::string path = dir + "/metrics.jsonl";
  {
    MetricsWriter w(path);
    for (int s = 1; s <= 4; ++s) w.write(s, {{"loss", s * 0.5}});
  }
  {
    MetricsWriter w(path, 2);
    w.write(3, {{"loss", 9.0}});
  }
  EXPECT_EQ(simu::fs::read_file(path), "{\"loss\":0.5,\"step\":1}\n{\"loss\":1.0,\"step\":2}\n{\"loss\":9.0,\"step\":3}\n");
  EXPECT_EQ(format_duration(3725), "1h02m05s");
}

// The progress display: on a terminal one redrawn line (carriage return, bar, step/total, loss,
// accuracy, lr, pairs/s, ETA); elsewhere a plain line every `every` steps and at the last one.
TEST(Progress, BarOnATerminalPlainLinesOtherwise) {
  testing::internal::CaptureStderr();
  {
    simu::training::Progress bar(10, 0, /*tty=*/true);
    bar.update(5, 0.6931, 0.75, 1e-5, 12.5);
    bar.finish();
  }
  const std::string tty = testing::internal::GetCapturedStderr();
  EXPECT_EQ(tty.rfind("\r[###############...............] 5/10 loss 0.6931 acc 0.750 lr 1.00e-05 12.5 pairs/s ETA ", 0), 0u)
      << tty;
  EXPECT_EQ(tty.back(), '\n');
  testing::internal::CaptureStderr();
  {
    simu::training::Progress plain(5, 0, /*tty=*/false, /*every=*/2);
    for (int s = 1; s <= 5; ++s) plain.update(s, 0.5, 1.0, 2e-5, 3.0);
    plain.finish();
  }
  const std::string lines = testing::internal::GetCapturedStderr();
  EXPECT_EQ(lines.find('\r'), std::string::npos) << lines;
  std::vector<std::string> got;
  std::istringstream in(lines);
  for (std::string l; std::getline(in, l);) got.push_back(l.substr(0, l.find(" loss")));
  EXPECT_EQ(got, (std::vector<std::string>{"step 2/5", "step 4/5", "step 5/5"})) << lines;
  EXPECT_NE(lines.find("loss 0.5000 acc 1.000 lr 2.00e-05 3.0 pairs/s ETA "), std::string::npos) << lines;
  EXPECT_EQ(simu::training::format_duration(3723), "1h02m03s");
  EXPECT_EQ(simu::training::format_duration(123), "2m03s");
}
