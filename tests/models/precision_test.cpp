// Precision names and defaults (models/precision.h): fp16 on CUDA, fp32 on the CPU; low precision on
// the CPU is an error naming the flag; Autocast(fp32) and CPU autocast requests change nothing.
#include <ATen/autocast_mode.h>

#include "common/error.h"
#include "models/precision.h"
#include "test_util.h"

namespace sm = simu::models;

TEST(Precision, NamesAndDefaults) {
  const torch::Device cpu(torch::kCPU), cuda(torch::kCUDA, 0);
  EXPECT_EQ(sm::parse_precision("auto", cuda), sm::Precision::kFp16);
  EXPECT_EQ(sm::parse_precision("auto", cpu), sm::Precision::kFp32);
  EXPECT_EQ(sm::parse_precision("bf16", cpu), sm::Precision::kBf16);
  EXPECT_EQ(sm::parse_precision("float16", cpu), sm::Precision::kFp16);
  EXPECT_EQ(sm::precision_name(sm::Precision::kBf16), "bf16");
  EXPECT_EQ(sm::precision_dtype(sm::Precision::kFp16), torch::kFloat16);
  try {
    sm::parse_precision("fp8", cpu, "--precision");
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("--precision 'fp8'"), std::string::npos) << e.what();
  }
  EXPECT_NO_THROW(sm::check_precision(sm::Precision::kFp32, cpu));
  EXPECT_NO_THROW(sm::check_precision(sm::Precision::kFp16, cuda));
  EXPECT_THROW(sm::check_precision(sm::Precision::kFp16, cpu, "--precision"), simu::Error);
  // fp32 is no autocast at all.
  {
    sm::Autocast a(sm::Precision::kFp32);
    EXPECT_FALSE(at::autocast::is_autocast_enabled(at::kCUDA));
  }
}
