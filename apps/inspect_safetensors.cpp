// inspect_safetensors: lists the tensors of a safetensors file (name, dtype, shape) and its metadata.
#include <fmt/ranges.h>

#include "common/cli.h"
#include "data/safetensors.h"

int main(int argc, char** argv) {
  CLI::App app{"List the tensors (name, dtype, shape) and metadata of a safetensors file"};
  std::string path;
  std::string filter;
  app.add_option("file", path, "safetensors file")->required();
  app.add_option("--filter", filter, "only names containing this text");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    const auto f = simu::data::SafeTensorsFile::open(path);
    int64_t total = 0;
    for (const auto& k : f.keys()) {
      const auto& i = f.info(k);
      int64_t n = 1;
      for (auto d : i.shape) n *= d;
      total += n;
      if (!filter.empty() && k.find(filter) == std::string::npos) continue;
      fmt::print("{:<80} {:<5} [{}]\n", k, i.dtype, fmt::join(i.shape, ", "));
    }
    for (const auto& [k, v] : f.metadata()) fmt::print("metadata {} = {}\n", k, v);
    fmt::print("{} tensors, {} elements\n", f.keys().size(), total);
    return 0;
  });
}
