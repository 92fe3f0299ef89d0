#include "data/safetensors.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fmt/ranges.h>
#include <nlohmann/json.hpp>

#include "common/error.h"
#include "common/fs.h"
#include "data/safetensors_header.h"

namespace simu::data {

namespace {
struct DTypeEntry {
  const char* name;
  torch::ScalarType type;
};
const DTypeEntry kDTypes[] = {
    {"F64", torch::kFloat64}, {"F32", torch::kFloat32},   {"F16", torch::kFloat16},
    {"BF16", torch::kBFloat16}, {"I64", torch::kInt64},   {"I32", torch::kInt32},
    {"I16", torch::kInt16},   {"I8", torch::kInt8},       {"U8", torch::kUInt8},
    {"U16", torch::kUInt16},  {"U32", torch::kUInt32},    {"U64", torch::kUInt64},
    {"BOOL", torch::kBool},   {"F8_E4M3", torch::kFloat8_e4m3fn}, {"F8_E5M2", torch::kFloat8_e5m2},
};
}  // namespace

torch::ScalarType dtype_from_name(const std::string& name) {
  for (const auto& e : kDTypes)
    if (name == e.name) return e.type;
  fail("unknown safetensors dtype '{}'", name);
}

std::string dtype_name(torch::ScalarType t) {
  for (const auto& e : kDTypes)
    if (t == e.type) return e.name;
  fail("torch dtype {} has no safetensors name", c10::toString(t));
}

// The file mapping, shared by every tensor viewing it.
struct SafeTensorsFile::Mapping {
  void* addr = nullptr;
  size_t size = 0;
  ~Mapping() {
    if (addr != nullptr && addr != MAP_FAILED) ::munmap(addr, size);
  }
};

SafeTensorsFile SafeTensorsFile::open(const std::string& path) {
  SafeTensorsFile f;
  f.path_ = path;
  const int fd = ::open(path.c_str(), O_RDONLY);
  if (fd < 0) fail("cannot open safetensors file '{}': {}", path, std::strerror(errno));
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    ::close(fd);
    fail("safetensors file '{}' is not a regular file", path);
  }
  const uint64_t size = static_cast<uint64_t>(st.st_size);
  if (size < 8) {
    ::close(fd);
    fail("{}: truncated safetensors file ({} bytes, the 8-byte header length is missing)", path, size);
  }
  f.map_ = std::make_shared<Mapping>();
  f.map_->size = size;
  f.map_->addr = ::mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_PRIVATE, fd, 0);
  ::close(fd);
  if (f.map_->addr == MAP_FAILED) fail("{}: mmap failed: {}", path, std::strerror(errno));
  const auto* bytes = static_cast<const uint8_t*>(f.map_->addr);

  // Header and tensor table: parsed and checked against the file's length (safetensors_header.h).
  auto header = parse_safetensors_header(bytes, size, path);
  f.data_start_ = header.data_start;
  f.metadata_ = std::move(header.metadata);
  for (auto& e : header.tensors) {
    TensorInfo info;
    info.dtype = e.dtype;
    info.scalar_type = dtype_from_name(e.dtype);
    info.shape = std::move(e.shape);
    info.begin = e.begin;
    info.end = e.end;
    f.keys_.push_back(e.name);
    f.infos_[e.name] = std::move(info);
  }
  return f;
}

const TensorInfo& SafeTensorsFile::info(const std::string& key) const {
  const auto it = infos_.find(key);
  if (it == infos_.end()) fail("{}: no tensor named '{}'", path_, key);
  return it->second;
}

torch::Tensor SafeTensorsFile::get(const std::string& key) const {
  const TensorInfo& i = info(key);
  auto* base = static_cast<uint8_t*>(map_->addr) + data_start_ + i.begin;
  const auto opts = torch::TensorOptions().dtype(i.scalar_type);
  const size_t align = c10::elementSize(i.scalar_type);
  if (i.end == i.begin) return torch::empty(i.shape, opts);
  if (reinterpret_cast<uintptr_t>(base) % align != 0) {
    auto out = torch::empty(i.shape, opts);
    std::memcpy(out.data_ptr(), base, i.end - i.begin);
    return out;
  }
  auto keep = map_;
  return torch::from_blob(base, i.shape, [keep](void*) mutable { keep.reset(); }, opts);
}

std::map<std::string, torch::Tensor> SafeTensorsFile::all() const {
  std::map<std::string, torch::Tensor> out;
  for (const auto& k : keys_) out[k] = get(k);
  return out;
}

std::map<std::string, torch::Tensor> load_safetensors(const std::string& path) { return SafeTensorsFile::open(path).all(); }

void save_safetensors(const std::string& path, const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                      const std::map<std::string, std::string>& metadata) {
  nlohmann::ordered_json header;
  if (!metadata.empty()) header["__metadata__"] = metadata;
  std::vector<torch::Tensor> cpu;
  uint64_t offset = 0;
  for (const auto& [name, t] : tensors) {
    if (name.empty() || name == "__metadata__") fail("{}: invalid tensor name '{}'", path, name);
    if (header.contains(name)) fail("{}: duplicate tensor name '{}'", path, name);
    auto c = t.detach().to(torch::kCPU).contiguous();
    const uint64_t nbytes = static_cast<uint64_t>(c.numel()) * c.element_size();
    header[name] = {{"dtype", dtype_name(c.scalar_type())}, {"shape", c.sizes().vec()}, {"data_offsets", {offset, offset + nbytes}}};
    offset += nbytes;
    cpu.push_back(std::move(c));
  }
  std::string json = header.dump();
  while ((json.size() + 8) % 8 != 0) json.push_back(' ');
  std::string bytes;
  bytes.reserve(8 + json.size() + offset);
  uint64_t n = json.size();
  for (int i = 0; i < 8; ++i) bytes.push_back(static_cast<char>((n >> (8 * i)) & 0xff));
  bytes += json;
  for (const auto& c : cpu) bytes.append(static_cast<const char*>(c.data_ptr()), c.numel() * c.element_size());
  fs::atomic_write(path, bytes);
}

void save_safetensors(const std::string& path, const std::map<std::string, torch::Tensor>& tensors,
                      const std::map<std::string, std::string>& metadata) {
  save_safetensors(path, std::vector<std::pair<std::string, torch::Tensor>>(tensors.begin(), tensors.end()), metadata);
}

}  // namespace simu::data
