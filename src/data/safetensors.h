// safetensors reading (memory-mapped, zero copy where alignment allows) and atomic writing.
//
// Format: u64 little-endian header length N, N bytes of JSON
// {"name": {"dtype": "F32", "shape": [..], "data_offsets": [begin, end]}, "__metadata__": {..}},
// then the data buffer. Every malformation (truncated file, bad JSON, unknown dtype, offsets out of
// range or overlapping, byte count not matching the shape) is a simu::Error naming the file and key.
#pragma once

#include <torch/torch.h>

#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

namespace simu::data {

// One tensor's entry in the header.
struct TensorInfo {
  std::string dtype;             // safetensors name: "F32", "BF16", ...
  torch::ScalarType scalar_type;
  std::vector<int64_t> shape;
  uint64_t begin = 0, end = 0;   // offsets into the data buffer
};

// Maps a safetensors dtype name to torch and back; unknown names throw.
torch::ScalarType dtype_from_name(const std::string& name);
std::string dtype_name(torch::ScalarType t);

class SafeTensorsFile {
 public:
  // Opens and validates path (mmap). Throws simu::Error naming the file on any malformation.
  static SafeTensorsFile open(const std::string& path);

  const std::string& path() const { return path_; }
  // Tensor names in file order of their data offsets.
  const std::vector<std::string>& keys() const { return keys_; }
  bool contains(const std::string& key) const { return infos_.count(key) != 0; }
  const TensorInfo& info(const std::string& key) const;
  const std::map<std::string, std::string>& metadata() const { return metadata_; }
  // A CPU tensor over the mapped bytes (copy-on-write mapping: writing to it never touches the file;
  // a copy is made only when the bytes are not aligned for the dtype). Unknown key -> error.
  torch::Tensor get(const std::string& key) const;
  // All tensors, by name.
  std::map<std::string, torch::Tensor> all() const;

 private:
  struct Mapping;
  std::string path_;
  std::shared_ptr<Mapping> map_;
  std::vector<std::string> keys_;
  std::map<std::string, TensorInfo> infos_;
  std::map<std::string, std::string> metadata_;
  uint64_t data_start_ = 0;
};

// Reads every tensor of a file.
std::map<std::string, torch::Tensor> load_safetensors(const std::string& path);

// Writes tensors (any device; copied to CPU contiguous) and string metadata to path atomically
// (temporary file, fsync, rename). Names must be unique and non-empty.
void save_safetensors(const std::string& path, const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                      const std::map<std::string, std::string>& metadata = {});
void save_safetensors(const std::string& path, const std::map<std::string, torch::Tensor>& tensors,
                      const std::map<std::string, std::string>& metadata = {});

}  // namespace simu::data
