// Stage-1 sample cache: an HDF5 file of per-object samples for Stage-1 pretraining (train_stage1):
// the condition embedder's six inputs after the released preprocessing, the ground-truth filled
// occupancy, the ground-truth pose latents in SAM 3D's convention, and what the world knows about the
// object (family, split, visible fraction). build_stage1_data writes it from world scenes.
//
// Layout (schema_version 1; docs/stage1_cache.md, readable with h5py):
//   root attributes: format="simu.stage1_cache", schema_version=1, input_size=[S, P],
//                    occupancy_resolution=R, pose_convention="...", created_by="..."
//   /image, /rgb_image, /mask, /rgb_image_mask, /pointmap, /rgb_pointmap
//                    the pair cache's inputs mode exactly (docs/pair_cache.md: shapes, storages, checks)
//   /occupancy       [N, R, R, R]  uint8 0/1, index (x, y, z)     chunk [1, R, R, R], shuffle + gzip
//   /pose_<latent>   [N, k]        float32, one per pose latent (stage1_pose_latents())
//   /pointmap_scale, /pointmap_shift  [N, 3] float32: the preprocessing's ObjectCentricSSI scale / shift
//   /visible_fraction [N] float32 in [0, 1];  /split [N] uint8 (0 train, 1 val, 2 test)
//   /family, /id     [N] variable-length UTF-8 strings (ids unique)
// Errors are simu::Error naming the file and the dataset or record. Every HDF5 call runs under
// data::hdf5_mutex() (pair_cache.h).
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "data/pair_cache.h"

namespace simu::data {

// The schema version this code writes and reads.
constexpr int kStage1CacheSchemaVersion = 1;

// The pose latents a sample holds, in the flow model's order, with their widths: SAM 3D's
// 6drotation_normalized (6), scale (3), translation (3), translation_scale (1) (models/pose.h).
const std::vector<std::pair<std::string, int64_t>>& stage1_pose_latents();

// Splits as stored (the world's Train / Val / Test).
enum class SampleSplit : uint8_t { Train = 0, Val = 1, Test = 2 };
// "train" / "val" / "test"; parse_sample_split throws naming `what` for anything else.
const char* split_name(SampleSplit s);
SampleSplit parse_sample_split(const std::string& name, const std::string& what = "split");

// One object sample.
struct Stage1Record {
  std::string id;                               // unique, e.g. "train_000123/obj2_mug"
  std::map<std::string, torch::Tensor> inputs;  // condition_input_names() -> [ch, S, S] float32
  torch::Tensor occupancy;                      // [R, R, R] uint8 0/1
  std::map<std::string, torch::Tensor> pose;    // stage1_pose_latents() -> [k] float32
  torch::Tensor pointmap_scale, pointmap_shift;  // [3] float32
  std::string family;
  SampleSplit split = SampleSplit::Train;
  float visible_fraction = 1.0f;
  int64_t index = -1;                           // record index in the file (set by the reader)
};

// What a cache holds.
struct Stage1CacheInfo {
  int schema_version = 0;
  int64_t size = 0;                       // records N
  int64_t occupancy_resolution = 0;       // R
  std::vector<int64_t> input_size;        // [S, P]
  std::string image_dtype, pointmap_dtype;  // "uint8" / "float16" / "float32"
  std::string pose_convention;            // models::PoseDecodeOptions::convention of the pose latents
  std::string created_by, path;
  int64_t counts[3] = {0, 0, 0};          // records per split
};

// Rows of every per-record dataset in its storage dtype (the trainer's bulk load).
struct Stage1Rows {
  std::map<std::string, torch::Tensor> inputs;  // [n, ch, s, s] uint8 / float16 / float32
  torch::Tensor occupancy;                      // [n, R, R, R] uint8
  std::map<std::string, torch::Tensor> pose;    // [n, k] float32
  std::vector<int64_t> index;                   // record indices
};

// Writes a cache atomically (path.tmp-<pid>, renamed over path by finish(); a writer destroyed
// unfinished removes its temporary file and leaves path as it was).
class Stage1CacheWriter {
 public:
  // layout: the six inputs' sizes and storage (InputsLayout::storage_named); R: occupancy side;
  // pose_convention: how the pose latents were encoded (recorded for the decoder).
  Stage1CacheWriter(const std::string& path, const InputsLayout& layout, int64_t occupancy_resolution,
                    const std::string& pose_convention);
  Stage1CacheWriter(const Stage1CacheWriter&) = delete;
  Stage1CacheWriter& operator=(const Stage1CacheWriter&) = delete;
  ~Stage1CacheWriter();
  // Appends one sample. Refused (RecordRefused, naming the file and id, nothing written): an empty or
  // repeated id, inputs of the wrong shape or values (check_condition_input), occupancy not [R, R, R]
  // of 0/1, a pose latent missing, of the wrong width or not finite, scale/shift not finite [3], a
  // visible fraction outside [0, 1], an empty family.
  void append(const Stage1Record& record);
  int64_t size() const;
  void set_created_by(const std::string& text);
  // Flushes, closes, fsyncs and renames the temporary file over path. Further appends throw.
  void finish();
  const std::string& path() const { return path_; }

 private:
  struct Impl;
  std::string path_, tmp_path_;
  std::unique_ptr<Impl> impl_;
};

// Reads a cache: open() checks the attributes, the schema version and every dataset's dtype and shape
// (in a forked child first, as the pair cache's reader does: libhdf5 1.10 can crash on corrupt
// files), and reads the small per-record datasets whole. Reads are thread-safe (their HDF5 calls
// take hdf5_mutex()).
class Stage1CacheReader {
 public:
  static Stage1CacheReader open(const std::string& path);
  const Stage1CacheInfo& info() const;
  int64_t size() const;
  // Record i, inputs decoded to float32 and checked (errors name the file, record, id and dataset).
  Stage1Record read(int64_t i) const;
  // Records [start, start + count) of the big datasets in their storage dtypes, checked in bulk
  // (occupancy 0/1, pose finite, images in range, point maps without +-Inf). Several threads may call
  // it at once: only locating the chunks holds the HDF5 lock, reading and inflating them does not.
  Stage1Rows read_rows(int64_t start, int64_t count) const;
  const std::vector<std::string>& ids() const;
  const std::vector<std::string>& families() const;
  const std::vector<uint8_t>& splits() const;
  const std::vector<float>& visible_fractions() const;

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

}  // namespace simu::data
