// pair_cache_bench: write / random-read / stream throughput and bytes per pair of the HDF5 pair cache
// at real latent size ([4096, 8]), in both condition modes: tokens (--cond-len x 1024 condition tokens,
// f16 and f32) and inputs (the released embedder's six inputs at 518 px, exact = float32, compact =
// uint8 images + float16 point maps; the embedder then runs in the training step). Prints a table.
#include <fmt/format.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>

#include "common/cli.h"
#include "common/error.h"
#include "data/pair_cache.h"

namespace {

struct Options {
  int64_t n = 32, cond_len = 7528, batch = 16, input_size = 518;
  std::vector<std::string> modes{"tokens", "inputs"};
  std::string dir = std::filesystem::temp_directory_path().string();
};

// One cache: written, read in a permuted order, streamed one epoch; one table row.
void bench_one(const Options& o, const std::string& mode, const std::string& storage) {
  using clock = std::chrono::steady_clock;
  auto secs = [](clock::time_point a) { return std::chrono::duration<double>(clock::now() - a).count(); };
  const auto path = fmt::format("{}/pair_cache_bench_{}_{}_{}.h5", o.dir, mode, storage, ::getpid());
  auto t0 = clock::now();
  if (mode == "tokens")
    simu::data::make_synthetic_cache(path, o.n, {4096, 8}, {o.cond_len, 1024}, 0,
                                     storage == "f16" ? torch::kFloat16 : torch::kFloat32, nullptr, o.cond_len);
  else
    simu::data::make_synthetic_inputs_cache(path, o.n, {4096, 8}, {o.cond_len, 1024},
                                            simu::data::InputsLayout::storage_named(storage, o.input_size, o.input_size),
                                            0, torch::kFloat16);
  const double write = o.n / secs(t0);
  const auto reader = simu::data::PairCacheReader::open(path);
  const auto perm = simu::data::epoch_permutation(o.n, 1, 0);
  t0 = clock::now();
  for (auto i : perm) reader.read(i);
  const double rand_read = o.n / secs(t0);
  simu::data::PairStream stream(path, 0, 1, std::min(o.batch, o.n), 1);
  t0 = clock::now();
  int64_t got = 0;
  for (int64_t s = 0; s < stream.steps_per_epoch(); ++s) got += static_cast<int64_t>(stream.next_batch().size());
  const double streamed = got / secs(t0);
  const double mb = std::filesystem::file_size(path) / 1e6;
  fmt::print("| {} | {} | {} | {:.1f} | {:.2f} | {:.1f} | {:.1f} | {:.1f} |\n", mode, storage, o.n, mb, mb / o.n,
             write, rand_read, streamed);
  std::filesystem::remove(path);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Throughput and bytes per pair of the pair cache in both condition modes: write, random read, "
               "PairStream (one rank)"};
  Options o;
  app.add_option("--n", o.n, "pairs per cache")->capture_default_str();
  app.add_option("--cond-len", o.cond_len, "tokens mode: condition tokens per pair (x 1024 channels; 7,528 = the "
                                           "released embedder's)")->capture_default_str();
  app.add_option("--input-size", o.input_size, "inputs mode: image / mask / point map side")->capture_default_str();
  app.add_option("--modes", o.modes, "tokens and/or inputs")->delimiter(',')->capture_default_str()
      ->check(CLI::IsMember({"tokens", "inputs"}));
  app.add_option("--batch", o.batch, "global batch of the stream")->capture_default_str();
  app.add_option("--dir", o.dir, "where to write the temporary caches")->capture_default_str();
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    SIMU_CHECK(o.n >= 1, "--n must be >= 1, got {}", o.n);
    fmt::print("| mode | storage | pairs | MB | MB/pair | write pairs/s | random read pairs/s | stream pairs/s |\n");
    fmt::print("|---|---|---|---|---|---|---|---|\n");
    for (const auto& mode : o.modes)
      for (const char* storage : mode == "tokens" ? std::vector<const char*>{"f16", "f32"}
                                                  : std::vector<const char*>{"exact", "compact"})
        bench_one(o, mode, storage);
    return 0;
  });
}
