// safetensors: round trips of every dtype, metadata, the shared fixtures read back, malformed files.
#include "data/safetensors.h"

#include <fstream>

#include "common/error.h"
#include "test_util.h"

namespace {
using simu::data::load_safetensors;
using simu::data::SafeTensorsFile;
using simu::data::save_safetensors;

using simu::testing::error_of;

void write_raw(const std::string& path, const std::string& header, const std::string& data, int64_t len_override = -1) {
  std::ofstream out(path, std::ios::binary);
  uint64_t n = len_override >= 0 ? static_cast<uint64_t>(len_override) : header.size();
  for (int i = 0; i < 8; ++i) out.put(static_cast<char>((n >> (8 * i)) & 0xff));
  out << header << data;
}

TEST(SafeTensors, RoundTripEveryDtypeAndMetadata) {
  const auto dir = simu::testing::temp_dir("st_rt");
  torch::manual_seed(0);
  std::vector<std::pair<std::string, torch::Tensor>> ts = {
      {"f32", torch::randn({3, 5})},
      {"f64", torch::randn({2, 2}, torch::kFloat64)},
      {"f16", torch::randn({7}).to(torch::kFloat16)},
      {"bf16", torch::randn({4, 3}).to(torch::kBFloat16)},
      {"i64", torch::randint(-1000, 1000, {5}, torch::kInt64)},
      {"i32", torch::randint(-1000, 1000, {2, 3}, torch::kInt32)},
      {"i16", torch::randint(-1000, 1000, {3}, torch::kInt16)},
      {"i8", torch::randint(-100, 100, {9}, torch::kInt8)},
      {"u8", torch::randint(0, 255, {1, 1, 3}, torch::kUInt8)},
      {"bool", torch::randint(0, 2, {6}).to(torch::kBool)},
      {"scalar", torch::tensor(3.5)},
      {"empty", torch::zeros({0, 4})},
      {"noncontig", torch::randn({4, 6}).t()},
  };
  const std::string path = dir + "/a.safetensors";
  save_safetensors(path, ts, {{"format", "pt"}, {"note", "x"}});
  auto f = SafeTensorsFile::open(path);
  EXPECT_EQ(f.metadata().at("format"), "pt");
  EXPECT_EQ(f.keys().size(), ts.size());
  for (const auto& [name, t] : ts) {
    auto got = f.get(name);
    EXPECT_EQ(got.scalar_type(), t.scalar_type()) << name;
    EXPECT_EQ(got.sizes(), t.sizes()) << name;
    EXPECT_TRUE(torch::equal(got, t)) << name;
  }
  // Writing to a loaded tensor never changes the file (copy-on-write mapping).
  auto v = f.get("f32");
  v.fill_(42.0f);
  EXPECT_TRUE(torch::equal(load_safetensors(path).at("f32"), ts[0].second));
}

TEST(SafeTensors, ReadsEverySharedFixture) {
  const auto dir = simu::testing::fixture("");
  ASSERT_TRUE(std::filesystem::exists(dir)) << "fixtures not found at " << dir << " (set SIMU_SHARED_DIR)";
  int files = 0;
  for (const auto& e : std::filesystem::recursive_directory_iterator(dir)) {
    if (e.path().extension() != ".safetensors") continue;
    auto f = SafeTensorsFile::open(e.path().string());
    EXPECT_FALSE(f.keys().empty()) << e.path();
    for (const auto& k : f.keys()) {
      auto t = f.get(k);
      EXPECT_EQ(t.sizes().vec(), f.info(k).shape) << k;
    }
    ++files;
  }
  EXPECT_GE(files, 8);
  // A known entry: the decoder fixture's input [2, 8, 4, 4, 4].
  auto io = SafeTensorsFile::open(simu::testing::fixture("ss_decoder_small.safetensors"));
  EXPECT_FALSE(io.keys().empty());
}

TEST(SafeTensors, MalformedFilesGiveClearErrors) {
  const auto dir = simu::testing::temp_dir("st_bad");
  const std::string p = dir + "/bad.safetensors";
  // Shorter than the length prefix.
  std::ofstream(p, std::ios::binary) << "abc";
  EXPECT_NE(error_of([&] { SafeTensorsFile::open(p); }).find("truncated"), std::string::npos);
  // Header longer than the file.
  write_raw(p, "{}", "", 1000);
  EXPECT_NE(error_of([&] { SafeTensorsFile::open(p); }).find("truncated"), std::string::npos);
  // Bad JSON.
  write_raw(p, "{not json", "");
  EXPECT_NE(error_of([&] { SafeTensorsFile::open(p); }).find("not valid JSON"), std::string::npos);
  // Unknown dtype.
  write_raw(p, R"({"a":{"dtype":"Q7","shape":[1],"data_offsets":[0,4]}})", std::string(4, '\0'));
  EXPECT_NE(error_of([&] { SafeTensorsFile::open(p); }).find("unknown dtype 'Q7'"), std::string::npos);
  // Out-of-range offsets (data cut off).
  write_raw(p, R"({"a":{"dtype":"F32","shape":[4],"data_offsets":[0,16]}})", std::string(8, '\0'));
  auto msg = error_of([&] { SafeTensorsFile::open(p); });
  EXPECT_NE(msg.find("outside the data buffer"), std::string::npos) << msg;
  EXPECT_NE(msg.find("'a'"), std::string::npos) << msg;
  // Overlapping tensors.
  write_raw(p, R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},"b":{"dtype":"F32","shape":[2],"data_offsets":[4,12]}})",
            std::string(12, '\0'));
  EXPECT_NE(error_of([&] { SafeTensorsFile::open(p); }).find("overlap"), std::string::npos);
  // Byte count not matching the shape.
  write_raw(p, R"({"a":{"dtype":"F32","shape":[3],"data_offsets":[0,8]}})", std::string(8, '\0'));
  EXPECT_NE(error_of([&] { SafeTensorsFile::open(p); }).find("expected"), std::string::npos);
  // Missing file.
  EXPECT_NE(error_of([&] { SafeTensorsFile::open(dir + "/none.safetensors"); }).find("cannot open"), std::string::npos);
  // Unknown key.
  save_safetensors(p, std::vector<std::pair<std::string, torch::Tensor>>{{"x", torch::ones({1})}});
  EXPECT_NE(error_of([&] { SafeTensorsFile::open(p).get("y"); }).find("no tensor named 'y'"), std::string::npos);
}

TEST(SafeTensors, TruncatingAValidFileIsDetected) {
  const auto dir = simu::testing::temp_dir("st_trunc");
  const std::string p = dir + "/t.safetensors";
  save_safetensors(p, std::vector<std::pair<std::string, torch::Tensor>>{{"x", torch::randn({100})}});
  const auto size = std::filesystem::file_size(p);
  std::filesystem::resize_file(p, size - 10);
  EXPECT_NE(error_of([&] { SafeTensorsFile::open(p); }).find("outside the data buffer"), std::string::npos);
}

// Sizes from the header are checked before anything is allocated: an element count whose byte size
// overflows 64 bits, a header length past the format's limit, a directory, offsets that are not
// integers -- each a named error (never std::bad_alloc).
TEST(SafeTensors, HostileHeadersAreNamedErrorsBeforeAllocation) {
  const auto dir = simu::testing::temp_dir("st_hostile");
  const std::string p = dir + "/h.safetensors";
  write_raw(p, R"({"big":{"dtype":"F32","shape":[4294967296,4294967296],"data_offsets":[0,0]}})", "");
  auto msg = error_of([&] { SafeTensorsFile::open(p); });
  EXPECT_NE(msg.find("tensor 'big': shape [4294967296,4294967296] of F32 overflows"), std::string::npos) << msg;
  write_raw(p, R"({"z":{"dtype":"F32","shape":[0,4611686018427387904],"data_offsets":[0,0]}})", "");
  EXPECT_NO_THROW(SafeTensorsFile::open(p));  // zero elements: valid, nothing allocated
  write_raw(p, R"({"n":{"dtype":"F32","shape":[-1],"data_offsets":[0,4]}})", std::string(4, '\0'));
  msg = error_of([&] { SafeTensorsFile::open(p); });
  EXPECT_NE(msg.find("tensor 'n': shape is [-1], expected non-negative integers"), std::string::npos) << msg;
  write_raw(p, R"({"o":{"dtype":"F32","shape":[1],"data_offsets":[0,"4"]}})", std::string(4, '\0'));
  msg = error_of([&] { SafeTensorsFile::open(p); });
  EXPECT_NE(msg.find("tensor 'o': data_offsets is [0,\"4\"]"), std::string::npos) << msg;
  write_raw(p, "{\"\xff\":1}", "");
  msg = error_of([&] { SafeTensorsFile::open(p); });
  EXPECT_NE(msg.find("invalid UTF-8"), std::string::npos) << msg;
  EXPECT_EQ(msg.find("json.exception"), std::string::npos) << msg;
  write_raw(p, std::string(5000, '[') + std::string(5000, ']'), "");
  msg = error_of([&] { SafeTensorsFile::open(p); });
  EXPECT_NE(msg.find("nested deeper"), std::string::npos) << msg;
  msg = error_of([&] { SafeTensorsFile::open(dir); });
  EXPECT_NE(msg.find("is not a regular file"), std::string::npos) << msg;
}

}  // namespace
