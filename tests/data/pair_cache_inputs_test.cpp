// Pair cache, inputs mode (src/data/pair_cache_inputs.cpp): round trips of the six condition inputs
// (exact float32 storage bit for bit, NaN points included; compact storage within its rounding,
// computed independently), the layout as h5py reads it, the writer's refusals (non-8-bit masks,
// out-of-range images, infinite points, a tokens record, a resume in the other mode), validation
// naming file, record and dataset, and sizes from a damaged header refused before allocating.
#include <hdf5.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>

#include "common/error.h"
#include "data/pair_cache.h"
#include "pair_cache_test_util.h"
#include "test_util.h"

namespace {

using namespace simu::data;
using simu::testing::error_of;
using simu::testing::with_h5;

constexpr int64_t S = 20, P = 12, T = 16, C = 8;

// Condition inputs of one record: images in [0, 1], a binary mask and one of 8-bit levels k/255
// (as an 8-bit mask file reads: float(k) * float(1/255)), point maps with some NaN points.
std::map<std::string, torch::Tensor> random_inputs(int seed) {
  torch::manual_seed(seed);
  const float step = static_cast<float>(1.0 / 255.0);
  auto levels = torch::randint(0, 256, {1, S, S}).to(torch::kFloat32) * step;  // float multiply, like OpenCV
  auto pm = torch::randn({3, P, P}) * 3;
  pm.index_put_({torch::indexing::Slice(), 0, torch::indexing::Slice(0, 4)}, std::nanf(""));
  return {{"image", torch::rand({3, S, S})},
          {"rgb_image", torch::rand({3, S, S})},
          {"mask", (torch::rand({1, S, S}) > 0.5).to(torch::kFloat32)},
          {"rgb_image_mask", levels},
          {"pointmap", pm},
          {"rgb_pointmap", torch::randn({1, 3, P, P})}};  // a batch dimension of 1 is accepted
}

PairRecord record(const std::string& id, int seed) {
  PairRecord r;
  r.id = id;
  r.kind = seed % 2 ? PairKind::CleanPreservation : PairKind::OcclusionCompletion;
  r.weight = default_weight(r.kind);
  r.latent_pos = torch::randn({T, C});
  r.latent_neg = torch::randn({T, C});
  r.inputs = random_inputs(seed);
  return r;
}

InputsLayout layout(const std::string& storage) { return InputsLayout::storage_named(storage, S, P); }

// Equal bit for bit, NaN where NaN.
bool same(const torch::Tensor& a, const torch::Tensor& b) {
  return a.sizes() == b.sizes() && torch::equal(torch::isnan(a), torch::isnan(b)) &&
         torch::equal(torch::nan_to_num(a, 0.0), torch::nan_to_num(b, 0.0));
}

std::string write_cache(const std::string& path, const std::string& storage, int n) {
  PairCacheWriter w(path, {T, C}, {40, 6}, torch::kFloat32, layout(storage));
  for (int i = 0; i < n; ++i) w.append(record("p" + std::to_string(i), i));
  w.finish();
  return path;
}


}  // namespace

// Exact storage: every input comes back bit for bit (NaN points as NaN), shapes [ch, S, S].
TEST(PairCacheInputs, ExactStorageRoundTrips) {
  const auto dir = simu::testing::temp_dir("pci_exact");
  const auto path = write_cache(dir + "/c.h5", "exact", 3);
  const auto reader = PairCacheReader::open(path);
  const auto& info = reader.info();
  EXPECT_EQ(info.cond_mode, "inputs");
  EXPECT_EQ(info.cond_shape, (std::vector<int64_t>{40, 6}));
  EXPECT_EQ(info.input_size, (std::vector<int64_t>{S, P}));
  EXPECT_EQ(info.image_dtype, "float32");
  EXPECT_EQ(info.pointmap_dtype, "float32");
  for (int i = 0; i < 3; ++i) {
    const auto r = reader.read(i);
    const auto want = random_inputs(i);
    EXPECT_FALSE(r.cond.defined());
    ASSERT_EQ(r.inputs.size(), 6u);
    for (const auto& [name, t] : want)
      EXPECT_TRUE(same(r.inputs.at(name), t.dim() == 4 ? t[0] : t)) << "record " << i << " " << name;
  }
  EXPECT_EQ(validate_cache(path).size, 3);
}

// Compact storage: images are round(255 x) / 255 (within half a level), point maps float16-rounded,
// masks exact; and the file is smaller.
TEST(PairCacheInputs, CompactStorageRoundsAsDocumented) {
  const auto dir = simu::testing::temp_dir("pci_compact");
  const auto path = write_cache(dir + "/c.h5", "compact", 2);
  const auto exact = write_cache(dir + "/e.h5", "exact", 2);
  const auto reader = PairCacheReader::open(path);
  EXPECT_EQ(reader.info().image_dtype, "uint8");
  EXPECT_EQ(reader.info().pointmap_dtype, "float16");
  const auto r = reader.read(1);
  const auto want = random_inputs(1);
  for (const char* name : {"image", "rgb_image"}) {
    // Half a level, plus the fp32 division q / 255 and the difference: 2 roundings of values <= 1.
    const double err = (r.inputs.at(name).to(torch::kFloat64) - want.at(name).to(torch::kFloat64)).abs().max().item<double>();
    EXPECT_LE(err, 0.5 / 255 + 2 * simu::testing::kFp32Unit) << name;
  }
  EXPECT_TRUE(same(r.inputs.at("mask"), want.at("mask")));
  EXPECT_TRUE(same(r.inputs.at("rgb_image_mask"), want.at("rgb_image_mask")));
  EXPECT_TRUE(same(r.inputs.at("pointmap"), want.at("pointmap").to(torch::kFloat16).to(torch::kFloat32)));
  EXPECT_LT(std::filesystem::file_size(path), std::filesystem::file_size(exact));
  const auto bytes = storage_bytes(path);
  EXPECT_EQ(bytes.pairs, 2);
  EXPECT_GT(bytes.condition, 0);
  EXPECT_LT(bytes.condition, storage_bytes(exact).condition);
}

// What the writer refuses, naming the file, pair and dataset.
TEST(PairCacheInputs, WriterRefusesWhatItCannotStore) {
  const auto dir = simu::testing::temp_dir("pci_refuse");
  PairCacheWriter w(dir + "/c.h5", {T, C}, {40, 6}, torch::kFloat32, layout("exact"));
  auto bad = [&](const std::string& name, const torch::Tensor& value) {
    auto r = record("x", 0);
    r.inputs[name] = value;
    return error_of([&] { w.append(r); });
  };
  EXPECT_NE(bad("mask", torch::full({1, S, S}, 0.3f)).find("'mask' holds 0.3"), std::string::npos);
  EXPECT_NE(bad("image", torch::full({3, S, S}, 255.0f)).find("'image' holds values in [255, 255]"), std::string::npos);
  auto inf = torch::zeros({3, P, P});
  inf[0][1][2] = INFINITY;
  EXPECT_NE(bad("pointmap", inf).find("'pointmap' holds +-Inf"), std::string::npos);
  EXPECT_NE(bad("image", torch::zeros({3, S, S + 1})).find("expected float [3, 20, 20]"), std::string::npos);
  auto missing = record("y", 0);
  missing.inputs.erase("rgb_pointmap");
  EXPECT_NE(error_of([&] { w.append(missing); }).find("'rgb_pointmap' is missing"), std::string::npos);
  auto tokens = record("z", 0);
  tokens.cond = torch::zeros({4, 6});
  EXPECT_NE(error_of([&] { w.append(tokens); }).find("stores condition inputs"), std::string::npos);
  EXPECT_EQ(w.size(), 0);
  w.finish();
  // A resume must keep the mode: a tokens writer cannot extend an inputs cache.
  const auto e = error_of([&] { PairCacheWriter t(dir + "/c.h5", {T, C}, {40, 6}, torch::kFloat32, true); });
  EXPECT_NE(e.find("cond_mode inputs"), std::string::npos) << e;
}

// Validation and reads name the record and dataset of a bad value written behind the writer's back.
TEST(PairCacheInputs, ValidationNamesRecordAndDataset) {
  const auto dir = simu::testing::temp_dir("pci_validate");
  const auto path = write_cache(dir + "/c.h5", "exact", 3);
  // rgb_image of record 2 gets one value 7 (channel 1, row 3, column 4).
  with_h5(path, [](hid_t f) {
    hid_t d = H5Dopen2(f, "rgb_image", H5P_DEFAULT);
    hid_t space = H5Dget_space(d);
    const hsize_t start[4] = {2, 1, 3, 4}, count[4] = {1, 1, 1, 1};
    H5Sselect_hyperslab(space, H5S_SELECT_SET, start, nullptr, count, nullptr);
    hid_t mem = H5Screate_simple(1, count, nullptr);
    const float v = 7.0f;
    EXPECT_GE(H5Dwrite(d, H5T_NATIVE_FLOAT, mem, space, H5P_DEFAULT, &v), 0);
    H5Sclose(mem), H5Sclose(space), H5Dclose(d);
  });
  const auto e = error_of([&] { validate_cache(path); });
  EXPECT_NE(e.find("record 2 (id 'p2'): dataset 'rgb_image' holds values in ["), std::string::npos) << e;
  EXPECT_NE(e.find(path), std::string::npos) << e;
  const auto reader = PairCacheReader::open(path);
  EXPECT_NO_THROW(reader.read(1));
  EXPECT_NE(error_of([&] { reader.read(2); }).find("dataset 'rgb_image'"), std::string::npos);
}

// h5py reads the layout (attributes, dtypes, shapes, chunks) and the values: masks as uint8 levels,
// images and point maps as float32 equal to what was written (dumped raw, not through our reader).
TEST(PairCacheInputs, H5pyReadsTheLayout) {
  if (std::system((std::string(SIMU_PYTHON) + " -c 'import h5py, numpy' >/dev/null 2>&1").c_str()) != 0)
    GTEST_SKIP() << "no h5py in SIMU_PYTHON=" << SIMU_PYTHON;
  const auto dir = simu::testing::temp_dir("pci_h5py");
  const auto path = write_cache(dir + "/c.h5", "exact", 2);
  const auto want = random_inputs(1);
  for (const char* name : {"image", "rgb_image_mask", "pointmap"}) {
    auto c = want.at(name).contiguous();
    std::ofstream(dir + "/" + name + ".bin", std::ios::binary).write(static_cast<const char*>(c.data_ptr()), c.numel() * 4);
  }
  const std::string script = R"PY(
import sys, h5py, numpy as np
path, d = sys.argv[1], sys.argv[2]
f = h5py.File(path, "r")
assert f.attrs["cond_mode"] == "inputs" and list(f.attrs["input_size"]) == [20, 12]
assert list(f.attrs["cond_shape"]) == [40, 6] and "cond" not in f and "cond_len" not in f
for name, dt, ch, s in [("image", np.float32, 3, 20), ("rgb_image", np.float32, 3, 20), ("mask", np.uint8, 1, 20),
                        ("rgb_image_mask", np.uint8, 1, 20), ("pointmap", np.float32, 3, 12), ("rgb_pointmap", np.float32, 3, 12)]:
    ds = f[name]
    assert ds.dtype == dt and ds.shape == (2, ch, s, s) and ds.chunks == (1, ch, s, s), (name, ds.dtype, ds.shape, ds.chunks)
    assert ds.compression == "gzip" and ds.shuffle and ds.maxshape[0] is None
img = np.fromfile(d + "/image.bin", np.float32).reshape(3, 20, 20)
assert np.array_equal(f["image"][1], img)
lv = np.fromfile(d + "/rgb_image_mask.bin", np.float32).reshape(1, 20, 20)
assert np.array_equal(f["rgb_image_mask"][1], np.round(lv * 255).astype(np.uint8))
pm = np.fromfile(d + "/pointmap.bin", np.float32).reshape(3, 12, 12)
assert np.array_equal(f["pointmap"][1], pm, equal_nan=True)
print("h5py ok")
)PY";
  std::ofstream(dir + "/check.py") << script;
  EXPECT_EQ(WEXITSTATUS(std::system((std::string(SIMU_PYTHON) + " " + dir + "/check.py " + path + " " + dir).c_str())), 0);
}

// A damaged input_size (huge sides) is refused from the header, before any record is allocated.
TEST(PairCacheInputs, HugeInputSizeIsRefusedBeforeAllocating) {
  const auto dir = simu::testing::temp_dir("pci_huge");
  const auto path = write_cache(dir + "/c.h5", "exact", 1);
  with_h5(path, [](hid_t f) {
    hid_t a = H5Aopen(f, "input_size", H5P_DEFAULT);
    const int64_t v[2] = {int64_t{1} << 30, 12};
    EXPECT_GE(H5Awrite(a, H5T_NATIVE_INT64, v), 0);
    H5Aclose(a);
  });
  const auto e = error_of([&] { PairCacheReader::open(path); });
  EXPECT_NE(e.find("attribute input_size"), std::string::npos) << e;
}
