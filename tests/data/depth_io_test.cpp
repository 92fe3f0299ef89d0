// Tests data/depth_io: .npy reading against files numpy itself wrote (dtypes, byte orders, Fortran
// order), malformed .npy files (truncated, wrong dtype, huge declared shape), depth maps (npy,
// 16-bit PNG, EXR), point maps, intrinsics JSON layouts, unprojection and the intrinsics fit.
#include <gtest/gtest.h>
#include <torch/torch.h>

#include <cstdlib>
#include <fstream>

#include "common/error.h"
#include "common/fs.h"
#include "data/depth_io.h"
#include "test_util.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

namespace sd = simu::data;

namespace {

// Runs a Python snippet with numpy (SIMU_PYTHON); returns false when it fails.
bool python(const std::string& code, const std::string& dir) {
  const std::string py = dir + "/snippet.py";
  std::ofstream(py) << code;
  return std::system((std::string(SIMU_PYTHON) + " " + py).c_str()) == 0;
}

// Expects fn to throw a simu::Error whose message contains every one of `parts`.
template <typename F>
void expect_error(F&& fn, const std::vector<std::string>& parts) {
  try {
    fn();
    ADD_FAILURE() << "no error";
  } catch (const simu::Error& e) {
    const std::string msg = e.what();
    for (const auto& p : parts) EXPECT_NE(msg.find(p), std::string::npos) << "'" << p << "' not in: " << msg;
  }
}

// Raw .npy bytes with a given header dict and data size.
void write_raw_npy(const std::string& path, const std::string& dict, size_t data_bytes) {
  std::string header = dict;
  const size_t total = 10 + header.size() + 1;
  header.append((64 - total % 64) % 64, ' ');
  header.push_back('\n');
  std::string b = "\x93NUMPY";
  b.push_back('\x01');
  b.push_back('\x00');
  b.push_back(static_cast<char>(header.size() & 0xFF));
  b.push_back(static_cast<char>(header.size() >> 8));
  b += header;
  b.append(data_bytes, '\0');
  std::ofstream(path, std::ios::binary) << b;
}

}  // namespace

// Arrays numpy wrote (float32/64, uint16, int64, bool, big-endian, Fortran order) read back exactly.
TEST(DepthIo, ReadsWhatNumpyWrites) {
  const auto dir = simu::testing::temp_dir("npy_numpy");
  ASSERT_TRUE(python(R"(import numpy as np
d = ')" + dir + R"('
a = np.arange(24, dtype=np.float64).reshape(2, 3, 4) * 0.5 - 3
np.save(d + '/f8.npy', a)
np.save(d + '/f4.npy', a.astype(np.float32))
np.save(d + '/f4be.npy', a.astype('>f4'))
np.save(d + '/f4fortran.npy', np.asfortranarray(a.astype(np.float32)))
np.save(d + '/u2.npy', (np.arange(12, dtype=np.uint16) * 6000).reshape(3, 4))
np.save(d + '/i8be.npy', np.arange(-3, 3).astype('>i8'))
np.save(d + '/b1.npy', np.array([[True, False], [False, True]]))
np.save(d + '/scalar.npy', np.float32(7.5))
)", dir));
  const auto want = torch::arange(24, torch::kFloat64).reshape({2, 3, 4}) * 0.5 - 3;
  for (const char* name : {"f8", "f4", "f4be", "f4fortran"}) {
    const auto t = sd::read_npy(dir + "/" + name + ".npy");
    EXPECT_EQ(t.sizes(), want.sizes()) << name;
    EXPECT_TRUE(t.is_contiguous()) << name;
    EXPECT_TRUE(torch::equal(t.to(torch::kFloat64), want)) << name;
  }
  EXPECT_EQ(sd::read_npy(dir + "/f4.npy").scalar_type(), torch::kFloat32);
  // uint16 above 32767 survives (read as int32); numpy's uint16 product wraps at 65536.
  const auto u2 = sd::read_npy(dir + "/u2.npy");
  EXPECT_EQ(u2.scalar_type(), torch::kInt32);
  EXPECT_TRUE(torch::equal(u2, ((torch::arange(12, torch::kInt32) * 6000) % 65536).reshape({3, 4}))) << u2;
  EXPECT_GT(u2.max().item<int32_t>(), 32767);
  EXPECT_TRUE(torch::equal(sd::read_npy(dir + "/i8be.npy"), torch::arange(-3, 3, torch::kInt64)));
  EXPECT_TRUE(torch::equal(sd::read_npy(dir + "/b1.npy"), torch::eye(2).to(torch::kBool)));
  const auto s = sd::read_npy(dir + "/scalar.npy");
  EXPECT_EQ(s.dim(), 0);
  EXPECT_EQ(s.item<float>(), 7.5f);
  simu::fs::remove_tree(dir);
}

// write_npy output is what numpy.load reads (dtype, shape, values).
TEST(DepthIo, NumpyReadsWhatWeWrite) {
  const auto dir = simu::testing::temp_dir("npy_write");
  sd::write_npy(dir + "/occ.npy", (torch::arange(27) % 2).to(torch::kUInt8).reshape({3, 3, 3}));
  sd::write_npy(dir + "/v.npy", torch::tensor({1.5f, -2.0f, 3.25f}));
  ASSERT_TRUE(python(R"(import numpy as np
d = ')" + dir + R"('
o = np.load(d + '/occ.npy'); v = np.load(d + '/v.npy')
assert o.dtype == np.uint8 and o.shape == (3, 3, 3) and (o.ravel() == np.arange(27) % 2).all(), (o.dtype, o.shape)
assert v.dtype == np.float32 and v.shape == (3,) and (v == np.array([1.5, -2, 3.25], np.float32)).all(), v
)", dir));
  EXPECT_TRUE(torch::equal(sd::read_npy(dir + "/v.npy"), torch::tensor({1.5f, -2.0f, 3.25f})));
  simu::fs::remove_tree(dir);
}

// Malformed files fail with an error naming the file and what was expected.
TEST(DepthIo, MalformedNpyNamesFileAndExpectation) {
  const auto dir = simu::testing::temp_dir("npy_bad");
  // Truncated: 2x3 float32 declares 24 data bytes; keep 10.
  write_raw_npy(dir + "/trunc.npy", "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }", 10);
  expect_error([&] { sd::read_npy(dir + "/trunc.npy"); }, {dir + "/trunc.npy", "24 data bytes", "10 bytes", "truncated"});
  // Trailing bytes.
  write_raw_npy(dir + "/trail.npy", "{'descr': '<f4', 'fortran_order': False, 'shape': (2,), }", 12);
  expect_error([&] { sd::read_npy(dir + "/trail.npy"); }, {dir + "/trail.npy", "trailing"});
  // Unsupported dtypes: complex, unicode, structured.
  write_raw_npy(dir + "/complex.npy", "{'descr': '<c8', 'fortran_order': False, 'shape': (2,), }", 16);
  expect_error([&] { sd::read_npy(dir + "/complex.npy"); }, {dir + "/complex.npy", "'<c8'", "expected one of"});
  write_raw_npy(dir + "/struct.npy", "{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (2,), }", 8);
  expect_error([&] { sd::read_npy(dir + "/struct.npy"); }, {dir + "/struct.npy", "structured"});
  // A huge declared shape is refused before any allocation (file has 0 data bytes).
  write_raw_npy(dir + "/huge.npy", "{'descr': '<f8', 'fortran_order': False, 'shape': (100000000, 100000000, 100000), }", 0);
  expect_error([&] { sd::read_npy(dir + "/huge.npy"); }, {dir + "/huge.npy", "too large"});
  write_raw_npy(dir + "/big.npy", "{'descr': '<f4', 'fortran_order': False, 'shape': (1000000, 1000000), }", 0);
  expect_error([&] { sd::read_npy(dir + "/big.npy"); }, {dir + "/big.npy", "4000000000000 data bytes", "truncated"});
  // Not an npy at all; a header cut short; a bad dict.
  std::ofstream(dir + "/text.npy") << "hello world, not numpy";
  expect_error([&] { sd::read_npy(dir + "/text.npy"); }, {dir + "/text.npy", "\\x93NUMPY"});
  {
    std::string b = "\x93NUMPY\x01";
    b.push_back('\x00');
    b += "\x76\x00{'descr'";
    std::ofstream(dir + "/cut.npy", std::ios::binary) << b;
  }
  expect_error([&] { sd::read_npy(dir + "/cut.npy"); }, {dir + "/cut.npy", "truncated"});
  write_raw_npy(dir + "/nokey.npy", "{'descr': '<f4', 'shape': (2,), }", 8);
  expect_error([&] { sd::read_npy(dir + "/nokey.npy"); }, {dir + "/nokey.npy", "fortran_order"});
  expect_error([&] { sd::read_npy(dir + "/missing.npy"); }, {dir + "/missing.npy"});
  // A depth file of the wrong shape / dtype.
  sd::write_npy(dir + "/pm.npy", torch::zeros({4, 5, 3}));
  expect_error([&] { sd::read_depth(dir + "/pm.npy"); }, {dir + "/pm.npy", "[H, W]", "--pointmap"});
  sd::write_npy(dir + "/depth_i8.npy", torch::zeros({4, 5}, torch::kInt8));
  expect_error([&] { sd::read_depth(dir + "/depth_i8.npy"); }, {dir + "/depth_i8.npy", "uint16"});
  sd::write_npy(dir + "/pm_wrong.npy", torch::zeros({3, 4, 5}));
  expect_error([&] { sd::read_pointmap(dir + "/pm_wrong.npy"); }, {dir + "/pm_wrong.npy", "[H, W, 3]"});
  simu::fs::remove_tree(dir);
}

// Depth in every format gives metres with NaN for invalid pixels; a point map keeps +inf / NaN.
TEST(DepthIo, DepthFormats) {
  const auto dir = simu::testing::temp_dir("depth_formats");
  // Metres with an invalid pixel (0) and a far one.
  const auto metres = torch::tensor({{1.0f, 2.5f, 0.0f}, {0.75f, 10.0f, 3.125f}});
  auto expect_depth = [&](const torch::Tensor& got, const std::string& what) {
    ASSERT_EQ(got.sizes(), metres.sizes()) << what;
    EXPECT_TRUE(std::isnan(got[0][2].item<float>())) << what;
    const auto valid = metres > 0;
    // At most two fp32 roundings (a unit's scale, a division) of depths up to 10 m, absolute.
    EXPECT_LT((got.masked_select(valid) - metres.masked_select(valid)).abs().max().item<float>(),
              10.0 * simu::testing::gamma(2))
        << what;
  };
  sd::write_npy(dir + "/d.npy", metres);
  expect_depth(sd::read_depth(dir + "/d.npy"), "npy float32");
  sd::write_npy(dir + "/d64.npy", metres.to(torch::kFloat64).unsqueeze(0));
  expect_depth(sd::read_depth(dir + "/d64.npy"), "npy float64 [1, H, W]");
  ASSERT_TRUE(python("import numpy as np\nnp.save('" + dir +
                         "/mm.npy', np.array([[1000, 2500, 0], [750, 10000, 3125]], np.uint16))\n",
                     dir));
  expect_depth(sd::read_depth(dir + "/mm.npy"), "npy uint16 mm");
#ifdef SIMU_HAVE_OPENCV
  cv::Mat mm(2, 3, CV_16UC1);
  const uint16_t v[6] = {1000, 2500, 0, 750, 10000, 3125};
  for (int k = 0; k < 6; ++k) mm.at<uint16_t>(k / 3, k % 3) = v[k];
  ASSERT_TRUE(cv::imwrite(dir + "/d.png", mm));
  expect_depth(sd::read_depth(dir + "/d.png"), "16-bit PNG mm");
  // EXR (float metres): OpenCV writes it only with OPENCV_IO_ENABLE_OPENEXR, which read_depth sets itself.
  ::setenv("OPENCV_IO_ENABLE_OPENEXR", "1", 0);
  cv::Mat m(2, 3, CV_32FC1, const_cast<float*>(metres.contiguous().data_ptr<float>()));
  bool exr_written = false;
  try {
    exr_written = cv::imwrite(dir + "/d.exr", m);
  } catch (const cv::Exception&) {
  }
  if (exr_written)
    expect_depth(sd::read_depth(dir + "/d.exr"), "EXR float metres");
  else
    std::printf("note: this OpenCV cannot write EXR; EXR read not exercised\n");
  // An 8-bit PNG holds no depth.
  cv::Mat eight(2, 3, CV_8UC1, cv::Scalar(5));
  ASSERT_TRUE(cv::imwrite(dir + "/d8.png", eight));
  expect_error([&] { sd::read_depth(dir + "/d8.png"); }, {dir + "/d8.png", "16-bit"});
  // Not an image.
  std::ofstream(dir + "/junk.png") << "not a png";
  expect_error([&] { sd::read_depth(dir + "/junk.png"); }, {dir + "/junk.png", "cannot read"});
#endif
  expect_error([&] { sd::read_depth(dir + "/nope.png"); }, {dir + "/nope.png", "not found"});
  expect_error([&] { sd::read_depth(dir + "/d.txt"); }, {dir + "/d.txt", "extension"});
  // MoGe-style point map: float32 [H, W, 3] with +inf invalid points, read as it is.
  auto pm = torch::randn({4, 5, 3});
  pm[1][2] = torch::full({3}, INFINITY);
  pm[3][0][1] = NAN;
  sd::write_npy(dir + "/pm.npy", pm);
  const auto got = sd::read_pointmap(dir + "/pm.npy");
  EXPECT_TRUE(torch::isinf(got[1][2]).all().item<bool>());
  EXPECT_TRUE(std::isnan(got[3][0][1].item<float>()));
  EXPECT_TRUE(torch::equal(torch::nan_to_num(got, 0, 0, 0), torch::nan_to_num(pm, 0, 0, 0)));
  simu::fs::remove_tree(dir);
}

// The three K layouts; malformed ones name the file and the layout expected.
TEST(DepthIo, IntrinsicsJson) {
  const auto dir = simu::testing::temp_dir("intrinsics");
  std::ofstream(dir + "/a.json") << R"({"fx": 500, "fy": 510, "cx": 320.5, "cy": 240, "width": 640})";
  std::ofstream(dir + "/b.json") << R"({"K": [[500, 0, 320.5], [0, 510, 240], [0, 0, 1]]})";
  std::ofstream(dir + "/c.json") << R"([500, 0, 320.5, 0, 510, 240, 0, 0, 1])";
  for (const char* n : {"a", "b", "c"}) {
    const auto K = sd::read_intrinsics_json(dir + "/" + n + ".json");
    EXPECT_EQ(K.fx, 500);
    EXPECT_EQ(K.fy, 510);
    EXPECT_EQ(K.cx, 320.5);
    EXPECT_EQ(K.cy, 240);
  }
  std::ofstream(dir + "/skew.json") << R"([[500, 3, 320], [0, 500, 240], [0, 0, 1]])";
  expect_error([&] { sd::read_intrinsics_json(dir + "/skew.json"); }, {dir + "/skew.json", "no skew"});
  std::ofstream(dir + "/part.json") << R"({"fx": 500, "fy": 500, "cx": 320})";
  expect_error([&] { sd::read_intrinsics_json(dir + "/part.json"); }, {dir + "/part.json", "'cy'"});
  std::ofstream(dir + "/neg.json") << R"({"fx": -5, "fy": 500, "cx": 320, "cy": 2})";
  expect_error([&] { sd::read_intrinsics_json(dir + "/neg.json"); }, {dir + "/neg.json", "fx, fy > 0"});
  std::ofstream(dir + "/bad.json") << "{fx: 1";
  expect_error([&] { sd::read_intrinsics_json(dir + "/bad.json"); }, {dir + "/bad.json", "JSON"});
  simu::fs::remove_tree(dir);
}

// Unprojection inverts the pinhole projection; the intrinsics fit recovers K from the points.
TEST(DepthIo, UnprojectAndFitIntrinsics) {
  const sd::Intrinsics K{520.0, 515.0, 33.5, 21.0};
  auto z = torch::rand({40, 60}, torch::kFloat64) * 3 + 0.5;
  z[5][7] = 0.0;  // invalid
  const auto p = sd::unproject_depth(z.to(torch::kFloat32), K);  // [H, W, 3]
  ASSERT_EQ(p.sizes(), (std::vector<int64_t>{40, 60, 3}));
  EXPECT_TRUE(torch::isnan(p[5][7]).all().item<bool>());
  // Re-project a few pixels by hand.
  for (auto [r, c] : std::vector<std::pair<int, int>>{{0, 0}, {13, 59}, {39, 21}}) {
    const double x = p[r][c][0].item<double>(), y = p[r][c][1].item<double>(), zz = p[r][c][2].item<double>();
    // x = (c - cx) z / fx in fp32 (z rounded, 3 operations): 4 roundings of (c - cx), in pixels.
    EXPECT_NEAR(K.fx * x / zz + K.cx, c, (60 + K.cx) * simu::testing::gamma(4));
    EXPECT_NEAR(K.fy * y / zz + K.cy, r, (40 + K.cy) * simu::testing::gamma(4));
    EXPECT_NEAR(zz, z[r][c].item<double>(), 3.5 * simu::testing::kFp32Unit);  // z <= 3.5 rounded to fp32
  }
  const auto fit = sd::estimate_intrinsics(p, "test");
  // Least squares of the pixel against r = x/z, each r within gamma(4) of |r| <= 60 / fx in fp32: the
  // slope moves by at most f max|dr| / std(r) ~ 520 x 2.8e-8 / 0.033 = 4.4e-4, the intercept by that
  // times mean(r) plus f max|dr|: 1e-2 (px) is 20 times the bound.
  EXPECT_NEAR(fit.fx, K.fx, 1e-2);
  EXPECT_NEAR(fit.fy, K.fy, 1e-2);
  EXPECT_NEAR(fit.cx, K.cx, 1e-2);
  EXPECT_NEAR(fit.cy, K.cy, 1e-2);
  expect_error([&] { sd::estimate_intrinsics(torch::full({4, 4, 3}, NAN), "pm.npy"); }, {"pm.npy", "valid points"});
}
