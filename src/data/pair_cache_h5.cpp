// HDF5 plumbing of the pair cache: error text, ids, rows, attributes (pair_cache_h5.h).
#include "data/pair_cache_h5.h"

#include <fcntl.h>
#include <unistd.h>

#include <fmt/ranges.h>
#include <zlib.h>

#include <algorithm>
#include <cerrno>
#include <cstring>

#include "common/error.h"

namespace simu::data {

std::recursive_mutex& hdf5_mutex() {
  static std::recursive_mutex m;
  return m;
}

namespace h5 {

namespace {
constexpr int kGzipLevel = 4;
constexpr hssize_t kMaxAttrValues = 64;   // values of an integer root attribute (shapes, version)
constexpr size_t kMaxAttrString = 1 << 16;  // bytes of a fixed-length string root attribute
}  // namespace

// The innermost description of the current HDF5 error stack (then clears it).
std::string h5_error() {
  std::string text;
  H5Ewalk2(
      H5E_DEFAULT, H5E_WALK_UPWARD,  // upward: entry 0 is the innermost (most specific) error
      [](unsigned n, const H5E_error2_t* e, void* data) -> herr_t {
        auto* s = static_cast<std::string*>(data);
        if (n == 0 && e->desc) *s = e->desc;
        return 0;
      },
      &text);
  H5Eclear2(H5E_DEFAULT);
  return text.empty() ? std::string("unknown HDF5 error") : text;
}

// Checks an HDF5 return value / id; on failure throws naming the file and what was being done.
hid_t check_id(hid_t id, const std::string& file, const std::string& what) {
  if (id < 0) fail("pair cache '{}': {}: {}", file, what, h5_error());
  return id;
}
void check_ok(herr_t r, const std::string& file, const std::string& what) {
  if (r < 0) fail("pair cache '{}': {}: {}", file, what, h5_error());
}

// IEEE half precision little-endian (the same definition h5py uses for numpy float16).
H5Id make_f16_type() {
  H5Id t(H5Tcopy(H5T_IEEE_F32LE));
  H5Tset_fields(t.get(), 15, 10, 5, 0, 10);
  H5Tset_size(t.get(), 2);
  H5Tset_ebias(t.get(), 15);
  return t;
}

// Variable-length UTF-8 string type.
H5Id make_vlen_string_type() {
  H5Id t(H5Tcopy(H5T_C_S1));
  H5Tset_size(t.get(), H5T_VARIABLE);
  H5Tset_cset(t.get(), H5T_CSET_UTF8);
  return t;
}

std::string dtype_str(torch::ScalarType t) {
  if (t == torch::kFloat16) return "float16";
  if (t == torch::kFloat32) return "float32";
  fail("pair cache dtype must be float16 or float32, got {}", c10::toString(t));
}

// A readable name of an HDF5 datatype ("float16", "uint8", "string", ...).
std::string type_name(hid_t type) {
  const auto cls = H5Tget_class(type);
  const size_t size = H5Tget_size(type);
  switch (cls) {
    case H5T_FLOAT: return fmt::format("float{}", size * 8);
    case H5T_INTEGER:
      return fmt::format("{}int{}", H5Tget_sign(type) == H5T_SGN_NONE ? "u" : "", size * 8);
    case H5T_STRING: return H5Tis_variable_str(type) > 0 ? "string" : fmt::format("string{}", size);
    default: return fmt::format("hdf5-class-{}", static_cast<int>(cls));
  }
}

std::vector<int64_t> space_dims(hid_t space) {
  const int rank = H5Sget_simple_extent_ndims(space);
  std::vector<hsize_t> d(std::max(rank, 0));
  if (rank > 0) H5Sget_simple_extent_dims(space, d.data(), nullptr);
  return std::vector<int64_t>(d.begin(), d.end());
}

std::vector<int64_t> dataset_dims(hid_t dset) {
  H5Id space(H5Dget_space(dset));
  return space_dims(space.get());
}

namespace {
// The file space of a dataset with rows [start, start+count) of dimension 0 selected (all of the other
// dimensions), and the matching memory space.
struct RowSelection {
  H5Id file_space, mem_space;
};
RowSelection select_rows(hid_t dset, int64_t start, int64_t count, const std::string& file, const std::string& what) {
  RowSelection sel;
  sel.file_space = H5Id(H5Dget_space(dset));
  auto dims = space_dims(sel.file_space.get());
  std::vector<hsize_t> off(dims.size(), 0), cnt(dims.begin(), dims.end());
  off[0] = static_cast<hsize_t>(start);
  cnt[0] = static_cast<hsize_t>(count);
  check_ok(H5Sselect_hyperslab(sel.file_space.get(), H5S_SELECT_SET, off.data(), nullptr, cnt.data(), nullptr), file,
           what);
  sel.mem_space = H5Id(H5Screate_simple(static_cast<int>(cnt.size()), cnt.data(), nullptr));
  return sel;
}
}  // namespace

void read_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, void* buf, const std::string& file,
               const std::string& name) {
  const RowSelection sel = select_rows(dset, start, count, file,
                                       fmt::format("dataset '{}': select records {}..{}", name, start, start + count - 1));
  if (H5Dread(dset, mtype, sel.mem_space.get(), sel.file_space.get(), H5P_DEFAULT, buf) < 0) {
    const auto why = h5_error();
    if (count == 1) fail("pair cache '{}': record {}: cannot read dataset '{}': {}", file, start, name, why);
    fail("pair cache '{}': records {}..{}: cannot read dataset '{}': {}", file, start, start + count - 1, name, why);
  }
}

namespace {
RecordPipeline record_pipeline(hid_t dcpl, const std::string& file, const std::string& name) {
  RecordPipeline p;
  const int nf = H5Pget_nfilters(dcpl);
  for (int k = 0; k < nf; ++k) {
    unsigned flags = 0, cd[8];
    size_t ncd = 8;
    const H5Z_filter_t id = H5Pget_filter2(dcpl, k, &flags, &ncd, cd, 0, nullptr, nullptr);
    if (id == H5Z_FILTER_SHUFFLE && p.shuffle < 0 && p.deflate < 0)
      p.shuffle = k;
    else if (id == H5Z_FILTER_DEFLATE && p.deflate < 0)
      p.deflate = k;
    else
      fail_hint("docs/pair_cache.md: per-record datasets use shuffle + gzip",
                "pair cache '{}': dataset '{}': filter {} (id {}) at position {}, expected shuffle then gzip", file, name,
                k, static_cast<int>(id), k);
  }
  return p;
}

// Undoes HDF5's shuffle filter: byte b of element i was stored at b * n + i.
void unshuffle(const uint8_t* in, uint8_t* out, size_t n, size_t elem) {
  for (size_t i = 0; i < n; ++i)
    for (size_t b = 0; b < elem; ++b) out[i * elem + b] = in[b * n + i];
}
}  // namespace

RecordPipeline check_record_layout(hid_t dset, const std::string& file, const std::string& name, bool multi_record) {
  const auto dims = dataset_dims(dset);
  H5Id dcpl(H5Dget_create_plist(dset));
  // Chunks of one record: [1, dims[1], ...] (multi_record: [k, dims[1], ...], k >= 1).
  std::vector<hsize_t> chunk(dims.size(), 0);
  const bool chunked = H5Pget_layout(dcpl.get()) == H5D_CHUNKED &&
                       H5Pget_chunk(dcpl.get(), static_cast<int>(chunk.size()), chunk.data()) == static_cast<int>(dims.size());
  std::vector<int64_t> want(dims.begin(), dims.end());
  if (!want.empty()) want[0] = multi_record && chunked && chunk[0] >= 1 ? static_cast<int64_t>(chunk[0]) : 1;
  if (!chunked || std::vector<int64_t>(chunk.begin(), chunk.end()) != want || (!want.empty() && want[0] > (1 << 20)))
    fail_hint("docs/pair_cache.md: per-record datasets are chunked one record at a time; rewrite the cache",
              "pair cache '{}': dataset '{}' is stored {}, expected chunks of {} [{}]", file, name,
              chunked ? fmt::format("in chunks [{}]", fmt::join(chunk, ", ")) : std::string("unchunked"),
              multi_record ? "whole records" : "one record", fmt::join(want, ", "));
  auto p = record_pipeline(dcpl.get(), file, name);
  p.rows = want.empty() ? 1 : want[0];
  return p;
}

namespace {
// The file a dataset's raw chunks are read from, with our own descriptor: offsets and lengths are
// checked against the file's length here (libhdf5 1.10's H5Dread_chunk trusts its index for the
// length it writes into the caller's buffer; it wrote past one found by fuzz_pair_cache).
struct ChunkFile {
  int fd = -1;
  uint64_t length = 0, base = 0;  // file length; base address (user block) of HDF5 addresses
  ChunkFile(hid_t dset, const std::string& file) {
    fd = ::open(file.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) fail("pair cache '{}': cannot open for reading: {}", file, std::strerror(errno));
    const off_t end = ::lseek(fd, 0, SEEK_END);
    length = end > 0 ? static_cast<uint64_t>(end) : 0;
    H5Id fid(H5Iget_file_id(dset));
    H5Id fcpl(H5Fget_create_plist(fid.get()));
    hsize_t ub = 0;
    if (fcpl.valid() && H5Pget_userblock(fcpl.get(), &ub) >= 0) base = ub;
  }
  ~ChunkFile() {
    if (fd >= 0) ::close(fd);
  }
  ChunkFile(const ChunkFile&) = delete;
  ChunkFile& operator=(const ChunkFile&) = delete;
};
}  // namespace

RecordChunks locate_record_chunks(hid_t dset, int64_t start, int64_t count, const std::string& file,
                                  const std::string& name, bool multi_record) {
  RecordChunks c;
  c.file = file;
  c.name = name;
  c.start = start;
  c.count = count;
  c.pipe = check_record_layout(dset, file, name, multi_record);
  const auto dims = dataset_dims(dset);
  H5Id ftype(H5Dget_type(dset));
  c.fsize = H5Tget_size(ftype.get());
  c.per = 1;  // elements per record
  for (size_t k = 1; k < dims.size(); ++k) c.per *= static_cast<size_t>(dims[k]);
  const int64_t rows = c.pipe.rows;
  const size_t chunk_bytes = c.per * c.fsize * static_cast<size_t>(rows);
  if (c.per == 0 || count <= 0) return c;
  const ChunkFile cf(dset, file);
  // A chunk's stored size is bounded by what its records can take (gzip adds at most ~0.1% + 12 bytes).
  const uint64_t limit = c.pipe.deflate >= 0 ? chunk_bytes + chunk_bytes / 100 + 1024 : chunk_bytes;
  std::vector<hsize_t> off(dims.size(), 0);
  c.first_chunk = start / rows;
  const int64_t last_chunk = (start + count - 1) / rows;
  for (int64_t ch = c.first_chunk; ch <= last_chunk; ++ch) {
    const int64_t r = ch * rows;  // the chunk's first record (named in errors)
    off[0] = static_cast<hsize_t>(r);
    unsigned mask = 0;
    haddr_t addr = HADDR_UNDEF;
    hsize_t nbytes = 0;
    if (H5Dget_chunk_info_by_coord(dset, off.data(), &mask, &addr, &nbytes) < 0)
      fail("pair cache '{}': record {}: cannot locate the chunk of dataset '{}': {}", file, r, name, h5_error());
    // Inside the file and no larger than its records may take.
    if (addr == HADDR_UNDEF || nbytes == 0)
      fail("pair cache '{}': record {}: dataset '{}' has no stored chunk (never written)", file, r, name);
    if (nbytes > limit || addr > cf.length || cf.base + addr > cf.length || nbytes > cf.length - cf.base - addr)
      fail("pair cache '{}': record {}: dataset '{}' indexes a chunk of {} bytes at offset {} (a chunk takes at most "
           "{}; the file has {}): the chunk index is corrupted",
           file, r, name, nbytes, addr, limit, cf.length);
    c.offset.push_back(cf.base + addr);
    c.nbytes.push_back(nbytes);
    c.mask.push_back(mask);
  }
  return c;
}

void decode_record_chunks(const RecordChunks& c, void* buf) {
  const size_t record_bytes = c.per * c.fsize;
  const int64_t rows = c.pipe.rows;
  const size_t chunk_bytes = record_bytes * static_cast<size_t>(rows);
  if (c.offset.empty() || chunk_bytes == 0) return;
  const int fd = ::open(c.file.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) fail("pair cache '{}': cannot open for reading: {}", c.file, std::strerror(errno));
  struct Closer {
    int fd;
    ~Closer() { ::close(fd); }
  } closer{fd};
  // One-record chunks decode straight into buf; chunks of several records into `whole`, then the
  // wanted records are copied out.
  std::vector<uint8_t> raw, plain(chunk_bytes), whole(rows > 1 ? chunk_bytes : 0);
  auto* out = static_cast<uint8_t*>(buf);
  for (size_t i = 0; i < c.offset.size(); ++i) {
    const int64_t first = (c.first_chunk + static_cast<int64_t>(i)) * rows;  // the chunk's first record
    raw.resize(c.nbytes[i]);
    for (size_t got = 0; got < raw.size();) {
      const ssize_t n = ::pread(fd, raw.data() + got, raw.size() - got, static_cast<off_t>(c.offset[i] + got));
      if (n <= 0) fail("pair cache '{}': record {}: cannot read the chunk of dataset '{}'", c.file, first, c.name);
      got += static_cast<size_t>(n);
    }
    // Filters in reverse: gzip (the last one), then shuffle; each must give exactly one chunk's bytes.
    uint8_t* dst = rows > 1 ? whole.data() : out + static_cast<size_t>(first - c.start) * record_bytes;
    const bool shuffled = c.pipe.shuffle >= 0 && !(c.mask[i] & (1u << c.pipe.shuffle)) && c.fsize > 1;
    uint8_t* inflated = shuffled ? plain.data() : dst;
    if (c.pipe.deflate >= 0 && !(c.mask[i] & (1u << c.pipe.deflate))) {
      uLongf got = static_cast<uLongf>(chunk_bytes);
      const int z = uncompress(inflated, &got, raw.data(), static_cast<uLong>(raw.size()));
      if (z != Z_OK || got != chunk_bytes)
        fail("pair cache '{}': record {}: dataset '{}': gzip data does not inflate to one chunk ({} bytes): {}",
             c.file, first, c.name, chunk_bytes, z == Z_OK ? fmt::format("{} bytes", got) : fmt::format("zlib error {}", z));
    } else if (raw.size() != chunk_bytes) {
      fail("pair cache '{}': record {}: dataset '{}' stores {} bytes uncompressed, a chunk is {} bytes", c.file, first,
           c.name, raw.size(), chunk_bytes);
    } else {
      std::memcpy(inflated, raw.data(), chunk_bytes);
    }
    // Shuffle works over the chunk's elements (all of its records).
    if (shuffled) unshuffle(plain.data(), dst, c.per * static_cast<size_t>(rows), c.fsize);
    if (rows > 1) {
      const int64_t lo = std::max(first, c.start), hi = std::min(first + rows, c.start + c.count);
      std::memcpy(out + static_cast<size_t>(lo - c.start) * record_bytes, whole.data() + static_cast<size_t>(lo - first) * record_bytes,
                  static_cast<size_t>(hi - lo) * record_bytes);
    }
  }
}

void read_record_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, void* buf, const std::string& file,
                      const std::string& name, bool multi_record) {
  const RecordChunks chunks = locate_record_chunks(dset, start, count, file, name, multi_record);
  if (chunks.per == 0 || count <= 0) return;
  H5Id ftype(H5Dget_type(dset));
  const size_t msize = H5Tget_size(mtype);
  if (H5Tequal(ftype.get(), mtype) > 0) {
    decode_record_chunks(chunks, buf);
    return;
  }
  // Stored type -> memory type, record by record in place (work holds per * max(fsize, msize) bytes).
  std::vector<uint8_t> stored(static_cast<size_t>(count) * chunks.per * chunks.fsize);
  decode_record_chunks(chunks, stored.data());
  std::vector<uint8_t> work(chunks.per * std::max(chunks.fsize, msize));
  auto* out = static_cast<uint8_t*>(buf);
  for (int64_t i = 0; i < count; ++i) {
    std::memcpy(work.data(), stored.data() + static_cast<size_t>(i) * chunks.per * chunks.fsize, chunks.per * chunks.fsize);
    if (H5Tconvert(ftype.get(), mtype, chunks.per, work.data(), nullptr, H5P_DEFAULT) < 0)
      fail("pair cache '{}': record {}: dataset '{}': cannot convert its {} values: {}", file, start + i, name,
           type_name(ftype.get()), h5_error());
    std::memcpy(out + static_cast<size_t>(i) * chunks.per * msize, work.data(), chunks.per * msize);
  }
}

void write_rows(hid_t dset, hid_t mtype, int64_t start, int64_t count, const void* buf, const std::string& file,
                const std::string& name) {
  const RowSelection sel = select_rows(dset, start, count, file, "select rows of " + name);
  check_ok(H5Dwrite(dset, mtype, sel.mem_space.get(), sel.file_space.get(), H5P_DEFAULT, buf), file,
           fmt::format("write record {} of dataset '{}'", start, name));
}

// Grows dimension 0 of a dataset to n rows.
void extend_rows(hid_t dset, int64_t n, const std::string& file, const std::string& name) {
  auto dims = dataset_dims(dset);
  std::vector<hsize_t> d(dims.begin(), dims.end());
  d[0] = static_cast<hsize_t>(n);
  check_ok(H5Dset_extent(dset, d.data()), file, "extend dataset " + name);
}

// Creates an extendible dataset [0, row...] with chunks [chunk_rows, row...], optionally shuffle+gzip.
H5Id create_rows_dataset(hid_t file, const std::string& name, hid_t ftype, const std::vector<int64_t>& row,
                         hsize_t chunk_rows, bool compress, const std::string& path, size_t chunk_cache_bytes) {
  std::vector<hsize_t> dims{0}, maxdims{H5S_UNLIMITED}, chunk{chunk_rows};
  for (auto r : row) {
    dims.push_back(static_cast<hsize_t>(r));
    maxdims.push_back(static_cast<hsize_t>(r));
    chunk.push_back(static_cast<hsize_t>(r));
  }
  H5Id space(check_id(H5Screate_simple(static_cast<int>(dims.size()), dims.data(), maxdims.data()), path,
                      "dataspace of " + name));
  H5Id dcpl(H5Pcreate(H5P_DATASET_CREATE));
  check_ok(H5Pset_chunk(dcpl.get(), static_cast<int>(chunk.size()), chunk.data()), path, "chunking of " + name);
  if (compress) {
    check_ok(H5Pset_shuffle(dcpl.get()), path, "shuffle filter of " + name);
    check_ok(H5Pset_deflate(dcpl.get(), kGzipLevel), path, "gzip filter of " + name);
  }
  H5Id dapl(H5Pcreate(H5P_DATASET_ACCESS));
  // 1.0: chunks written whole leave the cache first.
  if (chunk_cache_bytes > 0)
    check_ok(H5Pset_chunk_cache(dapl.get(), 521, chunk_cache_bytes, 1.0), path, "chunk cache of " + name);
  return H5Id(check_id(H5Dcreate2(file, name.c_str(), ftype, space.get(), H5P_DEFAULT, dcpl.get(), dapl.get()),
                       path, "create dataset " + name));
}

namespace {
// One attribute (replaced when it exists).
void write_attr_raw(hid_t obj, const char* name, hid_t ftype, hid_t mtype, hid_t space, const void* buf,
                    const std::string& path) {
  if (H5Aexists(obj, name) > 0) H5Adelete(obj, name);
  H5Id a(check_id(H5Acreate2(obj, name, ftype, space, H5P_DEFAULT, H5P_DEFAULT), path,
                  fmt::format("create attribute {}", name)));
  check_ok(H5Awrite(a.get(), mtype, buf), path, fmt::format("write attribute {}", name));
}
}  // namespace

void write_attr_int(hid_t obj, const char* name, int64_t v, const std::string& path) {
  H5Id space(H5Screate(H5S_SCALAR));
  write_attr_raw(obj, name, H5T_STD_I64LE, H5T_NATIVE_INT64, space.get(), &v, path);
}
void write_attr_ints(hid_t obj, const char* name, const std::vector<int64_t>& v, const std::string& path) {
  hsize_t n = v.size();
  H5Id space(H5Screate_simple(1, &n, nullptr));
  write_attr_raw(obj, name, H5T_STD_I64LE, H5T_NATIVE_INT64, space.get(), v.data(), path);
}
void write_attr_str(hid_t obj, const char* name, const std::string& v, const std::string& path) {
  H5Id space(H5Screate(H5S_SCALAR));
  H5Id t = make_vlen_string_type();
  const char* p = v.c_str();
  write_attr_raw(obj, name, t.get(), t.get(), space.get(), &p, path);
}

// Attribute readers; a missing or ill-typed attribute throws naming the file and attribute.
H5Id open_attr(hid_t obj, const char* name, const std::string& path) {
  if (H5Aexists(obj, name) <= 0)
    fail_hint("is this a pair cache written by PairCacheWriter? see docs/pair_cache.md",
              "pair cache '{}': root attribute '{}' is missing", path, name);
  return H5Id(check_id(H5Aopen(obj, name, H5P_DEFAULT), path, fmt::format("open attribute {}", name)));
}
std::vector<int64_t> read_attr_ints(hid_t obj, const char* name, const std::string& path) {
  H5Id a = open_attr(obj, name, path);
  H5Id t(H5Aget_type(a.get()));
  if (H5Tget_class(t.get()) != H5T_INTEGER)
    fail("pair cache '{}': root attribute '{}' has type {}, expected integer", path, name, type_name(t.get()));
  H5Id space(H5Aget_space(a.get()));
  const hssize_t n = H5Sget_simple_extent_npoints(space.get());
  if (n < 0 || n > kMaxAttrValues)
    fail("pair cache '{}': root attribute '{}' holds {} values, expected at most {}", path, name, n, kMaxAttrValues);
  std::vector<int64_t> v(static_cast<size_t>(std::max<hssize_t>(n, 0)));
  if (!v.empty()) check_ok(H5Aread(a.get(), H5T_NATIVE_INT64, v.data()), path, fmt::format("read attribute {}", name));
  return v;
}
std::string read_attr_str(hid_t obj, const char* name, const std::string& path) {
  H5Id a = open_attr(obj, name, path);
  H5Id t(H5Aget_type(a.get()));
  if (H5Tget_class(t.get()) != H5T_STRING)
    fail("pair cache '{}': root attribute '{}' has type {}, expected string", path, name, type_name(t.get()));
  {
    H5Id space(H5Aget_space(a.get()));
    if (H5Sget_simple_extent_npoints(space.get()) != 1)
      fail("pair cache '{}': root attribute '{}' holds {} values, expected one string", path, name,
           H5Sget_simple_extent_npoints(space.get()));
  }
  if (H5Tis_variable_str(t.get()) > 0) {
    H5Id mt = make_vlen_string_type();
    char* p = nullptr;
    check_ok(H5Aread(a.get(), mt.get(), &p), path, fmt::format("read attribute {}", name));
    std::string s = p ? p : "";
    H5free_memory(p);
    return s;
  }
  const size_t size = H5Tget_size(t.get());
  if (size == 0 || size > kMaxAttrString)
    fail("pair cache '{}': root attribute '{}' is a string of {} bytes, expected 1..{}", path, name, size, kMaxAttrString);
  std::string s(size, '\0');
  H5Id mt(H5Tcopy(H5T_C_S1));
  H5Tset_size(mt.get(), size);
  check_ok(H5Aread(a.get(), mt.get(), s.data()), path, fmt::format("read attribute {}", name));
  s.resize(std::strlen(s.c_str()));
  return s;
}

// Reads n string elements of a dataset starting at start (variable-length or fixed-length strings).
std::vector<std::string> read_strings(hid_t dset, int64_t start, int64_t n, const std::string& path,
                                      const std::string& name) {
  std::vector<std::string> out;
  if (n == 0) return out;
  H5Id ft(H5Dget_type(dset));
  if (H5Tis_variable_str(ft.get()) > 0) {
    H5Id mt = make_vlen_string_type();
    std::vector<char*> ptrs(static_cast<size_t>(n), nullptr);
    read_rows(dset, mt.get(), start, n, ptrs.data(), path, name);
    out.reserve(ptrs.size());
    for (auto* p : ptrs) out.emplace_back(p ? p : "");
    hsize_t cnt = static_cast<hsize_t>(n);
    H5Id ms(H5Screate_simple(1, &cnt, nullptr));
    H5Dvlen_reclaim(mt.get(), ms.get(), H5P_DEFAULT, ptrs.data());
  } else {
    const size_t size = H5Tget_size(ft.get());
    if (size == 0 || size > (1u << 20)) fail("pair cache '{}': dataset '{}' holds strings of {} bytes, expected 1..1 MiB", path, name, size);
    H5Id mt(H5Tcopy(H5T_C_S1));
    H5Tset_size(mt.get(), size);
    std::vector<char> buf(size * static_cast<size_t>(n));
    read_rows(dset, mt.get(), start, n, buf.data(), path, name);
    for (int64_t i = 0; i < n; ++i) {
      const char* p = buf.data() + i * size;
      out.emplace_back(p, strnlen(p, size));
    }
  }
  return out;
}

// Fsyncs a file by path.
void fsync_path(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY);
  if (fd < 0) fail("cannot open '{}' to fsync: {}", path, std::strerror(errno));
  const int r = ::fsync(fd);
  ::close(fd);
  if (r != 0) fail("cannot fsync '{}': {}", path, std::strerror(errno));
}

}  // namespace h5
}  // namespace simu::data
