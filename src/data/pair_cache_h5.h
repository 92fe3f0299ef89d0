// HDF5 plumbing of the pair cache (internal to src/data/pair_cache*.cpp and pair_stream.cpp; users
// include data/pair_cache.h): the global lock, error text, RAII ids, row and attribute access
// (pair_cache_h5.cpp) and the crash isolation of a file's first reads (pair_cache_isolation.cpp).
// Every error names the file as "pair cache '<file>'".
#pragma once

#include <hdf5.h>
#include <torch/torch.h>

#include <cstdint>
#include <functional>
#include <mutex>
#include <string>
#include <vector>

#include "data/pair_cache.h"

namespace simu::data::h5 {

// Locks the global HDF5 mutex and silences HDF5's own error printing (we report errors ourselves).
struct H5Lock {
  std::lock_guard<std::recursive_mutex> lock{hdf5_mutex()};
  H5Lock() { H5Eset_auto2(H5E_DEFAULT, nullptr, nullptr); }
};

// The innermost description of the current HDF5 error stack (then clears it).
std::string h5_error();

// Owns one HDF5 id and closes it with the function of its type.
class H5Id {
 public:
  H5Id() = default;
  explicit H5Id(hid_t id) : id_(id) {}
  H5Id(const H5Id&) = delete;
  H5Id& operator=(const H5Id&) = delete;
  H5Id(H5Id&& o) noexcept : id_(o.id_) { o.id_ = -1; }
  H5Id& operator=(H5Id&& o) noexcept {
    if (this != &o) {
      reset();
      id_ = o.id_;
      o.id_ = -1;
    }
    return *this;
  }
  ~H5Id() { reset(); }
  hid_t get() const { return id_; }
  bool valid() const { return id_ >= 0; }
  // Closes the id; returns false when the close failed.
  bool reset() {
    if (id_ < 0) return true;
    herr_t r = 0;
    switch (H5Iget_type(id_)) {
      case H5I_FILE: r = H5Fclose(id_); break;
      case H5I_DATASET: r = H5Dclose(id_); break;
      case H5I_DATASPACE: r = H5Sclose(id_); break;
      case H5I_DATATYPE: r = H5Tclose(id_); break;
      case H5I_ATTR: r = H5Aclose(id_); break;
      case H5I_GROUP: r = H5Gclose(id_); break;
      case H5I_GENPROP_LST: r = H5Pclose(id_); break;
      default: r = H5Idec_ref(id_) < 0 ? -1 : 0; break;
    }
    id_ = -1;
    return r >= 0;
  }

 private:
  hid_t id_ = -1;
};

// Checks an HDF5 return value / id; on failure throws naming the file and what was being done.
hid_t check_id(hid_t id, const std::string& file, const std::string& what);
void check_ok(herr_t r, const std::string& file, const std::string& what);
// IEEE half precision little-endian (the same definition h5py uses for numpy float16).
H5Id make_f16_type();
// Variable-length UTF-8 string type.
H5Id make_vlen_string_type();
// "float16" / "float32" for a storage dtype of the cache.
std::string dtype_str(torch::ScalarType t);
// A readable name of an HDF5 datatype ("float16", "uint8", "string", ...).
std::string type_name(hid_t type);
std::vector<int64_t> space_dims(hid_t space);
std::vector<int64_t> dataset_dims(hid_t dset);
// Selects rows [start, start+count) of dimension 0 (all of the other dimensions) and reads them
// into buf (memory type mtype). Throws naming file, dataset and the record range.
void read_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, void* buf, const std::string& file,
               const std::string& name);
// The filter pipeline of a per-record dataset: shuffle and/or gzip, at their pipeline positions.
struct RecordPipeline {
  int shuffle = -1, deflate = -1;  // position in the pipeline, -1 when absent
  int64_t rows = 1;                // records per chunk
};
// Fails unless a per-record dataset is stored as docs/pair_cache.md says (chunks of one record
// [1, ...], filters shuffle and/or gzip only), naming the file and dataset; returns its pipeline.
// With multi_record, chunks of k >= 1 whole records ([k, ...]: the stage-1 cache's bulk datasets,
// docs/stage1_cache.md) are accepted too.
RecordPipeline check_record_layout(hid_t dset, const std::string& file, const std::string& name,
                                   bool multi_record = false);
// Rows [start, start+count) of a per-record dataset (latents, condition, inputs), read chunk by chunk
// through the raw chunk API with every size checked before it is used (libhdf5 1.10's own read path
// copies out of bounds on some corrupted chunk indexes). The dataset must be stored as
// docs/pair_cache.md says: chunks of one record ([1, ...]), filters shuffle and/or gzip only; the
// stored type is converted to mtype. Throws naming the file, record and dataset.
void read_record_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, void* buf, const std::string& file,
                      const std::string& name, bool multi_record = false);
// read_record_rows in two steps, so that many records' bytes can be decoded on several threads:
// locate_record_chunks (HDF5 calls: under the HDF5 lock) finds where each record's chunk is stored and
// checks it against the file (the layout as read_record_rows requires); decode_record_chunks reads
// those bytes (pread), inflates and unshuffles them into buf in the stored type (count * per * fsize
// bytes; no HDF5 call: any thread, without the lock). Errors name the file, record and dataset.
// Chunks of k records (multi_record) are located once per chunk: libhdf5 1.10 finds a chunk by
// walking its index from the first chunk (H5Dget_chunk_info_by_coord), so the cost of a lookup grows
// with the chunk's position and a whole-file load of one-record chunks is quadratic in the records.
struct RecordChunks {
  std::string file, name;
  RecordPipeline pipe;
  size_t per = 0, fsize = 0;             // elements per record, bytes per stored element
  int64_t start = 0, count = 0;          // the records wanted
  int64_t first_chunk = 0;               // the chunk holding record `start` (= start / pipe.rows)
  std::vector<uint64_t> offset, nbytes;  // each chunk's file offset and stored bytes, from first_chunk on
  std::vector<uint32_t> mask;            // its filter mask
};
RecordChunks locate_record_chunks(hid_t dset, int64_t start, int64_t count, const std::string& file,
                                  const std::string& name, bool multi_record = false);
void decode_record_chunks(const RecordChunks& chunks, void* buf);
// Writes rows [start, start+count) of dimension 0 from buf.
void write_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, const void* buf, const std::string& file,
                const std::string& name);
// Grows dimension 0 of a dataset to n rows.
void extend_rows(hid_t dset, int64_t n, const std::string& file, const std::string& name);
// Creates an extendible dataset [0, row...] with chunks [chunk_rows, row...], optionally shuffle+gzip.
// chunk_cache_bytes > 0 sizes the dataset's raw chunk cache (a writer appending one record at a time
// to chunks of several records keeps the open chunk there, so each chunk is compressed once).
H5Id create_rows_dataset(hid_t file, const std::string& name, hid_t ftype, const std::vector<int64_t>& row,
                         hsize_t chunk_rows, bool compress, const std::string& path, size_t chunk_cache_bytes = 0);
// Attribute writers (scalar int64, int64 vector, variable-length UTF-8 string); replace existing ones.
void write_attr_int(hid_t obj, const char* name, int64_t v, const std::string& path);
void write_attr_ints(hid_t obj, const char* name, const std::vector<int64_t>& v, const std::string& path);
void write_attr_str(hid_t obj, const char* name, const std::string& v, const std::string& path);
// Attribute readers; a missing or ill-typed attribute throws naming the file and attribute.
H5Id open_attr(hid_t obj, const char* name, const std::string& path);
std::vector<int64_t> read_attr_ints(hid_t obj, const char* name, const std::string& path);
std::string read_attr_str(hid_t obj, const char* name, const std::string& path);
// Reads n string elements of a dataset starting at start (variable-length or fixed-length strings).
std::vector<std::string> read_strings(hid_t dset, int64_t start, int64_t n, const std::string& path,
                                      const std::string& name);
// Fsyncs a file by path.
void fsync_path(const std::string& path);

// ---------------------------------------------------------------------------------------------
// Crash isolation. libhdf5 1.10 (Debian 12) trusts several on-disk structures: a corrupted global
// heap (where variable-length strings such as the 'format' attribute and the ids live) makes
// H5Aread/H5Dread read out of bounds and crash (H5HG_read). HDF5 1.14 reports such files cleanly, 1.10
// cannot be fixed from outside. So the first reads of a file -- attributes, dataset headers, every
// id, and `pairs validate`'s full scan -- run in a forked child process: if libhdf5 crashes there,
// the caller gets a simu::Error naming the file; if the child succeeds, the same reads in this
// process touch exactly the bytes that were just read safely. SIMU_HDF5_ISOLATE=0 turns it off
// (debugging).
//
// Runs fn in a forked child. fn may report progress through the callback it gets. Returns when fn
// succeeded; rethrows its simu::Error (same message and hint); throws a simu::Error naming the file
// when the child died (signal, sanitizer abort) or stayed silent longer than SIMU_HDF5_TIMEOUT_S.
void isolated(const std::string& path, const char* what,
              const std::function<void(const std::function<void(int64_t, int64_t)>&)>& fn,
              const std::function<void(int64_t, int64_t)>& progress = nullptr);

}  // namespace simu::data::h5
