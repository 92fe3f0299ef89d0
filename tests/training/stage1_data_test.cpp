// Stage-1 samples in memory (training/stage1_data.h): one split of a cache, in record order, decoded
// on the device exactly as the cache reader decodes it.
#include "stage1_fixture.h"
#include "training/stage1_data.h"

using namespace simu::training;

// A compact cache of 7 records (splits 0, 1, 2, 0, ...): the train split's 3 rows come back in order
// with their record indices, and decode_inputs gives the reader's float32 values bit for bit.
TEST(Stage1Data, LoadsOneSplitAsTheReaderDecodesIt) {
  const auto dir = simu::testing::temp_dir("s1data");
  const auto path = dir + "/c.h5";
  auto src = simu::testing::tiny_samples(7, 21);
  {
    simu::data::Stage1CacheWriter w(path, simu::data::InputsLayout::storage_named("compact", simu::testing::kTinyImage,
                                                                                 simu::testing::kTinyPoint),
                                    simu::testing::kTinyR, "ScaleShiftInvariant");
    for (int64_t i = 0; i < 7; ++i) {
      simu::data::Stage1Record r;
      r.id = "rec" + std::to_string(i);
      for (const auto& [name, v] : decode_inputs(src->inputs)) r.inputs[name] = v[i];
      r.occupancy = src->occupancy[i];
      for (const auto& [name, v] : src->pose) r.pose[name] = v[i];
      r.pointmap_scale = torch::ones({3});
      r.pointmap_shift = torch::zeros({3});
      r.family = "box";
      r.split = static_cast<simu::data::SampleSplit>(i % 3);
      w.append(r);
    }
    w.finish();
  }
  const auto samples = load_stage1_samples(path, simu::data::SampleSplit::Train, false, /*chunk=*/2);
  EXPECT_EQ(samples->ids, (std::vector<int64_t>{0, 3, 6}));
  EXPECT_EQ(samples->occupancy_resolution(), simu::testing::kTinyR);
  const auto reader = simu::data::Stage1CacheReader::open(path);
  for (int64_t row = 0; row < 3; ++row) {
    const auto rec = reader.read(samples->ids[row]);
    std::map<std::string, torch::Tensor> one;
    for (const auto& [name, v] : samples->inputs) one[name] = v.narrow(0, row, 1);
    for (const auto& [name, v] : decode_inputs(one)) {
      const auto& want = rec.inputs.at(name);
      EXPECT_TRUE(torch::equal(torch::isnan(v[0]), torch::isnan(want)) &&
                  torch::equal(torch::nan_to_num(v[0], 0.0), torch::nan_to_num(want, 0.0)))
          << name << " row " << row;
    }
    EXPECT_TRUE(torch::equal(samples->occupancy[row], rec.occupancy));
    for (const auto& [name, v] : samples->pose) EXPECT_TRUE(torch::equal(v[row], rec.pose.at(name))) << name;
  }
  try {
    simu::data::Stage1CacheWriter w(dir + "/val_only.h5", simu::data::InputsLayout::storage_named("exact", 28, 8), 4, "x");
    w.finish();
    load_stage1_samples(dir + "/val_only.h5", simu::data::SampleSplit::Train);
    ADD_FAILURE() << "an empty split was accepted";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("has no train samples"), std::string::npos) << e.what();
  }
}
