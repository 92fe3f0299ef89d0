// The pair cache's on-disk layout (internal to src/data/pair_cache*.cpp and pair_stream.cpp): the
// constants of schema 1, the open datasets of a file with its CacheInfo, the structure checks shared
// by the reader and the writer's resume, and float record decoding (pair_cache_layout.cpp).
// Both cond_modes enter here: "tokens" (cond, cond_len) and "inputs" (the six condition-input
// datasets of condition_input_names(), pair_cache_inputs.cpp).
#pragma once

#include <string>
#include <vector>

#include "data/pair_cache.h"
#include "data/pair_cache_h5.h"

namespace simu::data::layout {

constexpr const char* kFormat = "simu.pair_cache";
constexpr const char* kDefaultCreatedBy = "simuscene_resampler PairCacheWriter";
constexpr hsize_t kScalarChunk = 1024;  // rows per chunk of the per-pair scalar datasets
// Deflate expands at most ~1032:1; a dataset cannot hold more decoded bytes than this many times
// the file's size (sizes above that come from a corrupt header, and are refused before allocating).
constexpr uint64_t kMaxExpansion = 1100;

// Open datasets of a cache and its info; ids are closed under the HDF5 lock by the owner.
struct CacheHandles {
  h5::H5Id file;
  h5::H5Id latent_pos, latent_neg, cond, cond_len, kind, weight, id;  // cond, cond_len: tokens mode
  h5::H5Id inputs[6];  // inputs mode: the datasets of condition_input_names(), in that order
  CacheInfo info;
  bool half = false;  // latents/cond stored as float16
  bool multi_record = false;  // inputs chunked by several records (the stage-1 cache)

  ~CacheHandles() { close(); }
  // Every open dataset (those of the file's mode).
  std::vector<h5::H5Id*> datasets() {
    std::vector<h5::H5Id*> out{&latent_pos, &latent_neg, &kind, &weight, &id};
    if (info.inputs_mode())
      for (auto& d : inputs) out.push_back(&d);
    else
      out.insert(out.end(), {&cond, &cond_len});
    return out;
  }
  void close() {
    std::lock_guard<std::recursive_mutex> lock(hdf5_mutex());
    for (h5::H5Id* d : {&latent_pos, &latent_neg, &cond, &cond_len, &kind, &weight, &id}) d->reset();
    for (auto& d : inputs) d.reset();
    file.reset();
  }
};

// Inputs mode (pair_cache_inputs.cpp). Channels of condition input k (3 or 1) and its side (S or P).
int64_t input_channels(size_t k);
int64_t input_side(size_t k, const CacheInfo& info);
bool is_mask_input(size_t k);
bool is_pointmap_input(size_t k);
// The float32 value of mask/image level q (0..255) as the preprocessing's 8-bit reader makes it:
// float(q) * float(1/255), rounded once (OpenCV's convertTo scale). kLevels[255] == 1.0f.
float u8_level(uint8_t q);
// Opens and checks the six datasets of an inputs-mode file (N records) into h.inputs, fills
// info.image_dtype / pointmap_dtype. multi_record: chunks of several records are accepted (the
// stage-1 cache's layout; check_record_layout).
void open_input_datasets(CacheHandles& h, const std::string& path, int64_t n, bool multi_record = false);
// Rows [start, start+count) of condition input k decoded to float32 [count, ch, s, s].
torch::Tensor read_input_rows(const CacheHandles& h, size_t k, int64_t start, int64_t count);
// Creates the six empty extendible datasets of a fresh inputs-mode file, chunks of chunk_rows
// records (the pair cache: 1; chunk_rows > 1 gives each dataset a chunk cache of two chunks).
void create_input_datasets(CacheHandles& h, const InputsLayout& layout, const std::string& path,
                           hsize_t chunk_rows = 1);
// One record's input k in the dataset's storage dtype (contiguous CPU [ch, s, s]); throws naming
// the file, pair id and dataset when it has the wrong shape or values the storage cannot hold.
torch::Tensor encode_input(size_t k, const torch::Tensor& value, const CacheInfo& info, const std::string& path,
                           const std::string& id);
// HDF5 memory type of a storage dtype name ("uint8", "float16", "float32").
h5::H5Id storage_mem_type(const std::string& dtype);
// Checks a dataset's dtype name (one of dtypes) and shape; returns the dtype name.
std::string check_dataset(hid_t dset, const char* name, const std::vector<std::string>& dtypes,
                          const std::vector<int64_t>& shape, const std::string& path);
// Fails unless a compact or contiguous dataset's stored bytes hold its shape x dtype (check_dataset
// calls it; chunked datasets pass).
void check_storage(hid_t dset, const char* name, hid_t type, const std::vector<int64_t>& shape,
                   const std::string& path);
// Opens a dataset that must exist, naming the file if it does not.
h5::H5Id open_dataset(hid_t file, const char* name, const std::string& path);

// File access properties of every read-only open. Readers skip HDF5's flock: many ranks read one
// file, often on network file systems where flock fails, and writers never modify a file in place
// (they rename a finished temporary over it). All read-only opens must agree on this flag.
h5::H5Id reader_fapl();

// Opens a file (read-only or read-write) and checks attributes and every dataset.
void open_cache(CacheHandles& h, const std::string& path, bool writable);

// The small per-pair datasets, read whole (as the guarded first reads of preflight do): the reader
// serves records from these, so libhdf5 reads them only in that one way, which the guard has seen end.
struct PairColumns {
  std::vector<std::string> ids;
  std::vector<uint8_t> kinds;
  std::vector<float> weights;
  std::vector<int32_t> cond_len;  // tokens mode only
};
PairColumns read_pair_columns(const CacheHandles& h, const std::string& path);
// The structure checks of open_cache plus the per-pair datasets (read_pair_columns), in a child
// process (h5::isolated()).
void preflight(const std::string& path);

// Memory type for reading a float16/float32 dataset without conversion.
h5::H5Id float_mem_type(const std::string& dtype);

// Index of the first row (of `rows` equal rows) holding a non-finite value, or -1.
int64_t first_nonfinite_row(const torch::Tensor& t, int64_t rows);

// Reads rows [start, start+count) of a float dataset as a float32 tensor [count, ...].
torch::Tensor read_float_rows(hid_t dset, const std::string& dtype, int64_t start, int64_t count,
                              const std::string& path, const std::string& name, bool multi_record = false);

}  // namespace simu::data::layout
