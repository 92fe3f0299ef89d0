// The pair cache's on-disk layout (internal to src/data/pair_cache*.cpp and pair_stream.cpp): the
// constants of schema 1, the open datasets of a file with its CacheInfo, the structure checks shared
// by the reader and the writer's resume, and float record decoding (pair_cache_layout.cpp).
// A new cond_mode ("inputs") enters here (open_cache's checks, the datasets of CacheHandles) and in
// the writer and reader that use them.
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
  h5::H5Id latent_pos, latent_neg, cond, cond_len, kind, weight, id;
  CacheInfo info;
  bool half = false;  // latents/cond stored as float16

  ~CacheHandles() { close(); }
  void close() {
    std::lock_guard<std::recursive_mutex> lock(hdf5_mutex());
    for (h5::H5Id* d : {&latent_pos, &latent_neg, &cond, &cond_len, &kind, &weight, &id}) d->reset();
    file.reset();
  }
};

// File access properties of every read-only open. Readers skip HDF5's flock: many ranks read one
// file, often on network file systems where flock fails, and writers never modify a file in place
// (they rename a finished temporary over it). All read-only opens must agree on this flag.
h5::H5Id reader_fapl();

// Opens a file (read-only or read-write) and checks attributes and every dataset.
void open_cache(CacheHandles& h, const std::string& path, bool writable);

// The structure checks of open_cache plus every id, in a child process (h5::isolated()).
void preflight(const std::string& path);

// Memory type for reading a float16/float32 dataset without conversion.
h5::H5Id float_mem_type(const std::string& dtype);

// Index of the first row (of `rows` equal rows) holding a non-finite value, or -1.
int64_t first_nonfinite_row(const torch::Tensor& t, int64_t rows);

// Reads rows [start, start+count) of a float dataset as a float32 tensor [count, ...].
torch::Tensor read_float_rows(hid_t dset, const std::string& dtype, int64_t start, int64_t count,
                              const std::string& path, const std::string& name);

}  // namespace simu::data::layout
