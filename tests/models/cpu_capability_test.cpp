// The CPU kernel set the torch suites run on: torch's own report (at::get_cpu_capability()), checked
// against the request in ATEN_CPU_CAPABILITY when one is set, and the intra-op threads.
// scripts/capability_pass.sh and scripts/capability_report.sh read the printed line to say which
// capabilities a test run exercised.
#include <ATen/Parallel.h>
#include <ATen/Version.h>

#include <algorithm>
#include <cctype>
#include <cstdlib>
#include <string>

#include "test_util.h"

namespace {
std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return s;
}
}  // namespace

TEST(CpuCapability, RunsOnTheRequestedKernelSet) {
  const std::string got = at::get_cpu_capability();
  const char* want = std::getenv("ATEN_CPU_CAPABILITY");
  std::printf("[cpu capability] %s (ATEN_CPU_CAPABILITY=%s), %d intra-op threads\n", got.c_str(),
              want ? want : "unset", at::get_num_threads());
  EXPECT_FALSE(got.empty());
  // A request torch could not honour (a kernel set this CPU lacks, a misspelt name) falls back to
  // another set silently: a pass meant to exercise it would not.
  if (want && *want) EXPECT_EQ(lower(got), lower(want)) << "ATEN_CPU_CAPABILITY=" << want << " was not honoured";
}
