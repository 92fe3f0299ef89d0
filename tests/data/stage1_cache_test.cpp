// The stage-1 sample cache: records written and read back (exact and compact storage), bulk rows,
// refused records, and the documented layout as h5py reads it (docs/stage1_cache.md).
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "data/stage1_cache.h"
#include "test_util.h"

using namespace simu::data;

namespace {

constexpr int64_t S = 14, P = 8, R = 4;

// A record with seeded random content: images in [0, 1] (multiples of 1/255 so compact storage is
// exact too), binary masks, point maps with one NaN, occupancy 0/1, pose latents.
Stage1Record make_record(int i) {
  torch::manual_seed(100 + i);
  Stage1Record r;
  r.id = "scene_" + std::to_string(i / 2) + "/obj" + std::to_string(i % 2);
  for (const char* n : {"image", "rgb_image"}) r.inputs[n] = torch::randint(0, 256, {3, S, S}).to(torch::kFloat32) / 255.0f;
  for (const char* n : {"mask", "rgb_image_mask"}) r.inputs[n] = (torch::rand({1, S, S}) < 0.5).to(torch::kFloat32);
  for (const char* n : {"pointmap", "rgb_pointmap"}) {
    auto p = torch::randn({3, P, P});
    p[0][1][2] = NAN;
    r.inputs[n] = p;
  }
  r.occupancy = (torch::rand({R, R, R}) < 0.3).to(torch::kByte);
  for (const auto& [name, k] : stage1_pose_latents()) r.pose[name] = torch::randn({k});
  r.pointmap_scale = torch::rand({3}) + 0.5;
  r.pointmap_shift = torch::randn({3});
  r.family = i % 3 == 0 ? "mug" : "box";
  r.split = static_cast<SampleSplit>(i % 3);
  r.visible_fraction = 0.25f * static_cast<float>(i % 5);
  return r;
}

// Float equality with NaN == NaN.
bool same(const torch::Tensor& a, const torch::Tensor& b) {
  return a.sizes() == b.sizes() && torch::equal(torch::nan_to_num(a.to(torch::kFloat32), 7.0), torch::nan_to_num(b.to(torch::kFloat32), 7.0)) &&
         torch::equal(torch::isnan(a), torch::isnan(b));
}

std::string write_cache(const std::string& dir, const std::string& storage, int n) {
  const auto path = dir + "/s1_" + storage + ".h5";
  Stage1CacheWriter w(path, InputsLayout::storage_named(storage, S, P), R, "ScaleShiftInvariant");
  w.set_created_by("unit test");
  for (int i = 0; i < n; ++i) w.append(make_record(i));
  w.finish();
  return path;
}

}  // namespace

// Every field comes back as written (exact storage: bit for bit; compact: the images are 8-bit levels,
// decoded as the documented product, and the point maps float16-rounded), with the info and counts.
// 37 records: the bulk datasets' chunks of 16 records (docs/stage1_cache.md) end in a partial chunk,
// and reads start and end inside chunks.
TEST(Stage1Cache, RoundTrip) {
  const auto dir = simu::testing::temp_dir("s1cache_rt");
  constexpr int N = 37;
  for (const std::string storage : {"exact", "compact"}) {
    const auto path = write_cache(dir, storage, N);
    const auto reader = Stage1CacheReader::open(path);
    const auto& info = reader.info();
    EXPECT_EQ(info.size, N);
    EXPECT_EQ(info.occupancy_resolution, R);
    EXPECT_EQ(info.input_size, (std::vector<int64_t>{S, P}));
    EXPECT_EQ(info.pose_convention, "ScaleShiftInvariant");
    EXPECT_EQ(info.created_by, "unit test");
    EXPECT_EQ(info.image_dtype, storage == "exact" ? "float32" : "uint8");
    EXPECT_EQ(info.counts[0] + info.counts[1] + info.counts[2], N);
    EXPECT_EQ(info.counts[0], 13);  // records 0, 3, ..., 36
    for (int i = 0; i < N; ++i) {
      const auto want = make_record(i);
      const auto got = reader.read(i);
      EXPECT_EQ(got.id, want.id);
      EXPECT_EQ(got.family, want.family);
      EXPECT_EQ(got.split, want.split);
      EXPECT_EQ(got.visible_fraction, want.visible_fraction);
      EXPECT_TRUE(torch::equal(got.occupancy, want.occupancy));
      for (const auto& [name, v] : want.pose) EXPECT_TRUE(torch::equal(got.pose.at(name), v)) << name;
      EXPECT_TRUE(torch::equal(got.pointmap_scale, want.pointmap_scale));
      EXPECT_TRUE(torch::equal(got.pointmap_shift, want.pointmap_shift));
      for (const auto& [name, v] : want.inputs) {
        const bool point = name.find("pointmap") != std::string::npos, image = name == "image" || name == "rgb_image";
        // compact: point maps rounded to float16; images stored as levels k, read as float(k) * float(1/255)
        // (one float32 product, not the k / 255 division the record was made with).
        auto expect = v;
        if (storage == "compact" && point) expect = v.to(torch::kFloat16).to(torch::kFloat32);
        if (storage == "compact" && image) expect = (v * 255).round() * static_cast<float>(1.0 / 255.0);
        EXPECT_TRUE(same(got.inputs.at(name), expect)) << storage << " " << name << " record " << i;
      }
    }
    // Bulk rows: storage dtypes, the same values.
    const auto rows = reader.read_rows(1, 3);
    EXPECT_EQ(rows.index, (std::vector<int64_t>{1, 2, 3}));
    EXPECT_EQ(rows.inputs.at("mask").scalar_type(), torch::kByte);
    EXPECT_EQ(rows.inputs.at("image").scalar_type(), storage == "exact" ? torch::kFloat32 : torch::kByte);
    EXPECT_TRUE(torch::equal(rows.occupancy[1], make_record(2).occupancy));
    EXPECT_TRUE(torch::equal(rows.pose.at("scale")[2], make_record(3).pose.at("scale")));
    // Across chunk boundaries (records 13..34: chunks 0, 1 and 2), and one whole chunk.
    for (const auto& [start, count] : std::vector<std::pair<int64_t, int64_t>>{{13, 22}, {16, 16}, {36, 1}}) {
      const auto span = reader.read_rows(start, count);
      ASSERT_EQ(span.occupancy.size(0), count);
      for (int64_t j = 0; j < count; ++j) {
        const auto want = make_record(static_cast<int>(start + j));
        EXPECT_TRUE(torch::equal(span.occupancy[j], want.occupancy)) << "record " << start + j;
        // Masks are stored as the 8-bit levels 0 / 255.
        EXPECT_TRUE(torch::equal(span.inputs.at("mask")[j], (want.inputs.at("mask") * 255).to(torch::kByte)))
            << "record " << start + j;
      }
    }
  }
}

// Records the cache cannot hold are refused before anything is written, naming the file and id;
// the writer stays usable; an unfinished writer leaves no file.
TEST(Stage1Cache, RefusesBadRecords) {
  const auto dir = simu::testing::temp_dir("s1cache_bad");
  const auto path = dir + "/bad.h5";
  {
    Stage1CacheWriter w(path, InputsLayout::storage_named("exact", S, P), R, "ScaleShiftInvariant");
    auto expect_refused = [&](Stage1Record r, const std::string& needle) {
      try {
        w.append(r);
        ADD_FAILURE() << "accepted: " << needle;
      } catch (const RecordRefused& e) {
        EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find(path), std::string::npos) << e.what();
      }
    };
    w.append(make_record(0));
    auto r = make_record(1);
    expect_refused(make_record(0), "already in the cache");
    r.occupancy = torch::full({R, R, R}, 2, torch::kByte);
    expect_refused(r, "occupancy holds values other than 0 and 1");
    r = make_record(1);
    r.occupancy = torch::zeros({R, R, R + 1}, torch::kByte);
    expect_refused(r, "occupancy must be [4, 4, 4]");
    r = make_record(1);
    r.pose.erase("scale");
    expect_refused(r, "pose latent 'scale' is missing");
    r = make_record(1);
    r.pose["translation"][0] = NAN;
    expect_refused(r, "pose latent 'translation' holds NaN or Inf");
    r = make_record(1);
    r.inputs["image"][0][0][0] = 3.0f;
    expect_refused(r, "'image'");
    r = make_record(1);
    r.visible_fraction = 1.5f;
    expect_refused(r, "visible fraction 1.5");
    r = make_record(1);
    r.family.clear();
    expect_refused(r, "empty family");
    w.append(make_record(1));
    EXPECT_EQ(w.size(), 2);
  }
  EXPECT_FALSE(std::filesystem::exists(path)) << "an unfinished writer left its cache";
  // A pair cache is another format: named as such.
  try {
    Stage1CacheReader::open(dir + "/missing.h5");
    ADD_FAILURE();
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("stage-1 cache"), std::string::npos) << e.what();
  }
}

// The layout as h5py sees it: attributes, dtypes, shapes, chunking and values.
TEST(Stage1Cache, H5pyReadsTheLayout) {
  const std::string py = simu::testing::python_exe();
  if (std::system((py + " -c 'import h5py, numpy' >/dev/null 2>&1").c_str()) != 0) GTEST_SKIP() << "no h5py";
  const auto dir = simu::testing::temp_dir("s1cache_h5py");
  const auto path = write_cache(dir, "compact", 3);
  const auto rec = make_record(2);
  const auto dump = [&](const torch::Tensor& t, const std::string& name) {
    auto c = t.to(torch::kFloat32).contiguous();
    std::ofstream(dir + "/" + name, std::ios::binary).write(static_cast<const char*>(c.data_ptr()), c.numel() * 4);
  };
  dump(rec.occupancy, "occ.bin");
  dump(rec.pose.at("6drotation_normalized"), "rot.bin");
  dump(rec.inputs.at("image"), "image.bin");
  const std::string script = R"PY(
import sys, h5py, numpy as np
path, d = sys.argv[1], sys.argv[2]
f = h5py.File(path, "r")
a = f.attrs
assert a["format"] == "simu.stage1_cache" and int(a["schema_version"]) == 1
assert list(a["input_size"]) == [14, 8] and int(a["occupancy_resolution"]) == 4
assert a["pose_convention"] == "ScaleShiftInvariant"
assert f["image"].dtype == np.uint8 and f["image"].shape == (3, 3, 14, 14) and f["image"].chunks == (16, 3, 14, 14)
assert f["mask"].dtype == np.uint8 and f["pointmap"].dtype == np.float16 and f["pointmap"].shape == (3, 3, 8, 8)
occ = f["occupancy"]
assert occ.dtype == np.uint8 and occ.shape == (3, 4, 4, 4) and occ.chunks == (16, 4, 4, 4) and occ.compression == "gzip"
assert np.array_equal(occ[2].astype(np.float32), np.fromfile(d + "/occ.bin", np.float32).reshape(4, 4, 4))
for name, k in (("6drotation_normalized", 6), ("scale", 3), ("translation", 3), ("translation_scale", 1)):
    assert f["pose_" + name].dtype == np.float32 and f["pose_" + name].shape == (3, k), name
assert np.array_equal(f["pose_6drotation_normalized"][2], np.fromfile(d + "/rot.bin", np.float32))
img = np.fromfile(d + "/image.bin", np.float32).reshape(3, 14, 14)
assert np.array_equal(f["image"][2].astype(np.float32), np.round(img * 255))
assert f["pointmap_scale"].shape == (3, 3) and f["pointmap_shift"].dtype == np.float32
assert f["split"].dtype == np.uint8 and list(f["split"][:]) == [0, 1, 2]
assert f["visible_fraction"].dtype == np.float32 and np.allclose(f["visible_fraction"][:], [0, 0.25, 0.5])
assert list(f["family"].asstr()[:]) == ["mug", "box", "box"]
assert list(f["id"].asstr()[:]) == ["scene_0/obj0", "scene_0/obj1", "scene_1/obj0"]
print("h5py ok")
)PY";
  std::ofstream(dir + "/check.py") << script;
  EXPECT_EQ(WEXITSTATUS(std::system((py + " " + dir + "/check.py " + path + " " + dir).c_str())), 0);
}
