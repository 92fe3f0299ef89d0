// Pair cache: an HDF5 file of FM-DPO latent preference pairs (preferred / rejected shape latents, the
// pair kind and weight, the condition tokens), its writer, reader, validator and a sharded,
// epoch-shuffled, resumable prefetching stream for training.
//
// Layout (schema_version 1; full description in docs/pair_cache.md, readable with h5py):
//   root attributes: format="simu.pair_cache", schema_version=1, latent_shape=[T, C],
//                    cond_mode="tokens", cond_shape=[L, Cc], created_by="..."
//   /latent_pos  [N, T, C]  float16|float32   chunk [1, T, C], shuffle + gzip
//   /latent_neg  [N, T, C]  same dtype        chunk [1, T, C], shuffle + gzip
//   /cond        [N, L, Cc] same dtype        chunk [1, L, Cc], shuffle + gzip (rows >= cond_len are 0)
//   /cond_len    [N]        int32             valid condition rows of each pair (1..L)
//   /kind        [N]        uint8             0 occlusion-completion, 1 clean-preservation
//   /weight      [N]        float32           per-pair loss weight (default 1.0 / 0.1 by kind)
//   /id          [N]        variable-length UTF-8 string, unique
// cond_mode="inputs" stores the condition embedder's inputs instead of /cond and /cond_len (the six
// official kwargs, see condition_input_names(); root attribute input_size=[S, P]):
//   /image, /rgb_image            [N, 3, S, S]  float32 | float16 | uint8 (k/255)   chunk [1, 3, S, S]
//   /mask, /rgb_image_mask        [N, 1, S, S]  uint8 (k/255, exact for 8-bit masks)
//   /pointmap, /rgb_pointmap      [N, 3, P, P]  float32 | float16 (NaN = invalid point)
//
// Every HDF5 call of the toolkit runs under one process-wide mutex (hdf5_mutex()): Debian's libhdf5
// is not built thread-safe. Errors are simu::Error naming the file and the dataset or record.
#pragma once

#include <torch/torch.h>

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <exception>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "common/error.h"

namespace simu::data {

// The schema version this code writes and reads.
constexpr int kPairCacheSchemaVersion = 1;

// The condition inputs an inputs-mode cache stores, in dataset order: the condition embedder's
// kwargs (models/cond_embedder.h) as data/preprocess.h prepare_condition_inputs makes them.
const std::vector<std::string>& condition_input_names();

// Storage of an inputs-mode cache. float32 keeps every value bit-exact (training on it equals
// training on the tokens the same embedder made at build time); uint8 images (round(255 x), k/255
// on read) and float16 point maps are about 2.5x smaller but not exact (images after the
// preprocessing's bilinear resize are not multiples of 1/255). Masks are always uint8: exact for
// masks read from 8-bit files (their values are k/255) and for binary ones.
struct InputsLayout {
  int64_t image_size = 518;     // S: image, rgb_image [3, S, S], mask, rgb_image_mask [1, S, S]
  int64_t pointmap_size = 518;  // P: pointmap, rgb_pointmap [3, P, P]
  torch::ScalarType image_dtype = torch::kFloat32;     // kFloat32, kFloat16 or kByte
  torch::ScalarType pointmap_dtype = torch::kFloat32;  // kFloat32 or kFloat16
  // "exact" = float32 images and point maps; "compact" = uint8 images, float16 point maps.
  static InputsLayout storage_named(const std::string& name, int64_t image_size, int64_t pointmap_size);
};

enum class PairKind : uint8_t { OcclusionCompletion = 0, CleanPreservation = 1 };
// "occlusion_completion" / "clean_preservation".
std::string kind_name(PairKind kind);
// Default loss weight of a kind: 1.0 for occlusion-completion, 0.1 for clean-preservation.
float default_weight(PairKind kind);

// One preference pair.
struct PairRecord {
  std::string id;
  PairKind kind = PairKind::OcclusionCompletion;
  float weight = 1.0f;
  torch::Tensor latent_pos, latent_neg;  // [T, C] float32 CPU (preferred, rejected)
  torch::Tensor cond;                    // [l, Cc] float32 CPU (tokens mode), l = this pair's cond_len <= L
  // Inputs mode: kwarg -> [ch, S, S] float32 CPU (condition_input_names(); [1, ch, S, S] accepted
  // by the writer). Empty in tokens mode (and cond undefined in inputs mode).
  std::map<std::string, torch::Tensor> inputs;
  int64_t index = -1;                    // record index in the file (set by the reader)
};

// What a cache holds (from its attributes and dataset shapes).
struct CacheInfo {
  int schema_version = 0;
  std::vector<int64_t> latent_shape, cond_shape;  // [T, C], [L, Cc] (inputs mode: the embedder's tokens)
  std::string cond_mode;                          // "tokens" or "inputs"
  std::string latent_dtype;                       // "float16" or "float32" (cond has the same dtype)
  int64_t size = 0;                               // number of pairs N
  int64_t counts[2] = {0, 0};                     // pairs per kind (index = PairKind value)
  std::string path;
  std::string created_by;
  std::string cond_dtype;                         // "float16" or "float32" (tokens mode)
  // Inputs mode: input_size [S, P] and the storage dtypes ("uint8", "float16", "float32").
  std::vector<int64_t> input_size;
  std::string image_dtype, pointmap_dtype;
  bool inputs_mode() const { return cond_mode == "inputs"; }
};

// Storage description of one dataset (for `pairs inspect`).
struct DatasetInfo {
  std::string name;
  std::string dtype;             // "float16", "float32", "uint8", "int32", "string", ...
  std::vector<int64_t> shape;
  std::vector<int64_t> chunk;    // empty when contiguous
  std::vector<std::string> filters;  // e.g. {"shuffle", "gzip(4)"}
};

// The process-wide lock every HDF5 call of the toolkit takes (libhdf5 is not thread-safe here).
std::recursive_mutex& hdf5_mutex();

// Thrown by PairCacheWriter::append when the record itself is refused (shape, values, id, kind,
// weight, a condition of the other mode); nothing was written, the writer stays usable.
class RecordRefused : public Error {
 public:
  using Error::Error;
};

// Writes a cache atomically: everything goes to `path.tmp-<pid>`; finish() flushes, closes, fsyncs
// and renames it over `path`. A writer destroyed without finish() (exception, crash) removes its
// temporary file and leaves `path` as it was (absent, or the previous complete cache); a process
// killed outright leaves only the stray `path.tmp-<pid>`, never a half-written `path`.
// resume=true with an existing `path`: the cache is copied to the temporary file and appended to;
// contains(id) tells which pairs it already has so the caller can skip them. Its latent/cond shapes
// and dtype must match the arguments. resume=false replaces any existing `path` on finish().
class PairCacheWriter {
 public:
  // latent_shape [T, C], cond_shape [L, Cc] (tokens mode; L is the maximum condition length),
  // dtype torch::kFloat16 or torch::kFloat32 (storage of latents and cond).
  PairCacheWriter(const std::string& path, std::vector<int64_t> latent_shape, std::vector<int64_t> cond_shape,
                  torch::ScalarType dtype, bool resume = false);
  // Inputs mode: the condition is stored as the embedder's inputs (layout); cond_shape [L, Cc] is
  // what the embedder makes of them (kept as an attribute so training can check its embedder);
  // dtype is the latents' storage. Resuming needs the same shapes and storage.
  PairCacheWriter(const std::string& path, std::vector<int64_t> latent_shape, std::vector<int64_t> cond_shape,
                  torch::ScalarType dtype, const InputsLayout& layout, bool resume = false);
  PairCacheWriter(const PairCacheWriter&) = delete;
  PairCacheWriter& operator=(const PairCacheWriter&) = delete;
  ~PairCacheWriter();

  // Whether a pair with this id is already in the cache (resumed or appended).
  bool contains(const std::string& id) const;
  // Appends one pair: latent_pos/neg [T, C], cond [l, Cc] with 1 <= l <= L (padded with zeros to L),
  // any float dtype, finite values, a non-empty id not yet present, weight finite and >= 0.
  // Inputs mode: record.inputs instead of cond, each kwarg of condition_input_names() with its shape
  // ([ch, S, S]); images and masks in [0, 1] (see check_condition_input), point maps without +-Inf.
  // Throws RecordRefused (a simu::Error) naming the file and the id otherwise, before writing anything.
  void append(const PairRecord& record);
  // Number of pairs written so far (including resumed ones).
  int64_t size() const;
  // Sets the created_by root attribute (default "simuscene_resampler PairCacheWriter").
  void set_created_by(const std::string& text);
  // Flushes, closes, fsyncs and renames the temporary file over path. Further appends throw.
  void finish();
  const std::string& path() const { return path_; }
  const std::string& temp_path() const { return tmp_path_; }

 private:
  PairCacheWriter(const std::string& path, std::vector<int64_t> latent_shape, std::vector<int64_t> cond_shape,
                  torch::ScalarType dtype, const InputsLayout* layout, bool resume);
  void resume_from(const std::string& path);
  void create_fresh();
  struct Impl;
  std::string path_, tmp_path_;
  std::unique_ptr<Impl> impl_;
};

// Reads a cache. open() checks the root attributes, the schema version, every dataset's presence,
// dtype and shape, and that the file is not truncated; read(i) throws naming the file, record and
// dataset when a record cannot be decoded or holds NaN/Inf. Copies share one open file; reads are
// thread-safe (serialized by hdf5_mutex()).
class PairCacheReader {
 public:
  static PairCacheReader open(const std::string& path);
  const CacheInfo& info() const;
  int64_t size() const;
  // Record i (0 <= i < size()), tensors float32 CPU, index = i.
  PairRecord read(int64_t i) const;
  // All ids in file order.
  std::vector<std::string> ids() const;
  // kind of every pair [N] uint8 and weight of every pair [N] float32 (cheap: small datasets).
  torch::Tensor kinds() const;
  torch::Tensor weights() const;
  const std::string& path() const;

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

// Storage of every dataset in the file (name order).
std::vector<DatasetInfo> describe_datasets(const std::string& path);
// Bytes the datasets of a cache take on disk (after compression), per pair: the latents, the
// condition (tokens or inputs) and the rest; file_bytes is the whole file's size.
struct StorageBytes {
  int64_t pairs = 0;
  double latents = 0, condition = 0, other = 0, file_bytes = 0;
};
StorageBytes storage_bytes(const std::string& path);

// Why one condition input [ch, S, S] (float32) is not acceptable, or "" when it is: images within
// [-0.25, 1.25] (values in [0, 1] plus the resize's overshoot) and finite, masks in [0, 1], point
// maps without +-Inf (NaN marks invalid points).
std::string check_condition_input(const std::string& name, const torch::Tensor& value);

// Full scan: structure as in open(), then every record decoded and checked: latents and cond finite,
// cond_len in 1..L (inputs mode: every condition input decoded and checked by check_condition_input), kind 0 or 1, weight finite and >= 0, ids non-empty and unique. Returns the info;
// throws simu::Error naming the file and the record index (and dataset) at the first problem.
// progress(done, total) is called now and then when given.
CacheInfo validate_cache(const std::string& path,
                         const std::function<void(int64_t, int64_t)>& progress = nullptr);

// Writes a synthetic cache of n pairs with deterministic content from seed (torch CPU generator, not
// the global RNG): latent_pos ~ smooth random fields, latent_neg a corrupted version of it (strongly
// for occlusion-completion, mildly for clean-preservation), cond ~ N(0, 1) with lengths varying in
// [cond_len_min, L] (L/2 when cond_len_min <= 0; = L gives one length, as a fixed embedder does),
// kinds mixed (about 2/3 occlusion-completion, at least one of each when n >= 2), default weights,
// ids "syn-000000"...
void make_synthetic_cache(const std::string& path, int64_t n, std::vector<int64_t> latent_shape,
                          std::vector<int64_t> cond_shape, uint64_t seed, torch::ScalarType dtype,
                          const std::function<void(int64_t, int64_t)>& progress = nullptr,
                          int64_t cond_len_min = 0);

// Inputs-mode synthetic cache: latents and kinds as make_synthetic_cache; the condition inputs are
// examples[i % examples.size()] (kwarg -> [ch, S, S] or [1, ch, S, S], e.g. preprocessed images) or,
// without examples, smooth random images in [0, 1], box masks and a plane-like point map.
void make_synthetic_inputs_cache(const std::string& path, int64_t n, std::vector<int64_t> latent_shape,
                                 std::vector<int64_t> cond_shape, const InputsLayout& layout, uint64_t seed,
                                 torch::ScalarType dtype,
                                 const std::vector<std::map<std::string, torch::Tensor>>& examples = {},
                                 const std::function<void(int64_t, int64_t)>& progress = nullptr);

// Position of a stream: the next global batch to produce is batch `step` of epoch `epoch`.
struct StreamPosition {
  int64_t epoch = 0;
  int64_t step = 0;  // global batches consumed within the epoch
};

// The permutation of 0..n-1 for an epoch: Fisher-Yates driven by std::mt19937_64 seeded from
// (seed, epoch) with an exactly specified bounded draw, so every rank and every platform agrees.
std::vector<int64_t> epoch_permutation(int64_t n, uint64_t seed, int64_t epoch);

// Training stream over a cache. Each epoch is a fresh permutation (epoch_permutation(N, seed, epoch));
// global batch g of an epoch is perm[g*G, (g+1)*G) with G = global_batch, and rank r receives the
// slice [r*G/world, (r+1)*G/world) of it (G must be a multiple of world; the trainer splits its share
// into micro-batches: G = micro x accum x world). An epoch has floor(N/G) global batches (the N mod G
// pairs left over are different ones every epoch); after the last one the stream rolls over to the
// next epoch. Ranks are disjoint and together cover every global batch. A background thread reads up
// to `prefetch` batches ahead. position() is where the next batch comes from, so a stream built with
// start = position() continues exactly (a step past the epoch's end rolls over into later epochs).
class PairStream {
 public:
  PairStream(std::string path, int rank, int world, int64_t global_batch, uint64_t seed,
             StreamPosition start = {}, int prefetch = 4);
  PairStream(const PairStream&) = delete;
  PairStream& operator=(const PairStream&) = delete;
  ~PairStream();

  // This rank's share of the next global batch (global_batch / world records, file order of the
  // permutation). Rethrows a read error of the background thread (naming file and record).
  std::vector<PairRecord> next_batch();
  // Position after the batches returned so far.
  StreamPosition position() const;
  int64_t steps_per_epoch() const { return steps_per_epoch_; }
  int64_t local_batch() const { return local_batch_; }
  const CacheInfo& info() const { return reader_.info(); }

 private:
  struct Item {
    std::vector<PairRecord> batch;
    StreamPosition after;
    std::exception_ptr error;
  };
  void produce(StreamPosition pos);

  PairCacheReader reader_;
  int rank_, world_;
  int64_t global_batch_, local_batch_, steps_per_epoch_;
  uint64_t seed_;
  size_t prefetch_;
  StreamPosition position_;
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<Item> queue_;
  bool stop_ = false;
  std::thread thread_;
};

// A batch of records stacked for the model.
struct PairBatch {
  torch::Tensor latent_pos, latent_neg;  // [B, T, C] float32
  torch::Tensor cond;                    // [B, Lmax, Cc] float32, zero padded
  torch::Tensor cond_mask;               // [B, Lmax] bool, true on valid condition rows
  torch::Tensor weight;                  // [B] float32
  torch::Tensor kind;                    // [B] uint8
  std::vector<std::string> ids;
};
// Stacks records (Lmax = the longest cond among them). Throws on an empty list or mismatched shapes,
// and for inputs-mode records (their condition is made by the embedder at training time).
PairBatch collate(const std::vector<PairRecord>& records);

}  // namespace simu::data
