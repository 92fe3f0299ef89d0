// pair_cache_bench: write / random-read / stream throughput of the HDF5 pair cache at real latent size
// ([4096, 8]) with a condition of --cond-len x 1024 tokens, f16 and f32. Prints a table.
#include <fmt/format.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>

#include "common/cli.h"
#include "data/pair_cache.h"

int main(int argc, char** argv) {
  CLI::App app{"Throughput of the pair cache: write, random read, PairStream (one rank)"};
  int64_t n = 256, cond_len = 64, batch = 16;
  std::string dir = std::filesystem::temp_directory_path().string();
  app.add_option("--n", n, "pairs")->capture_default_str();
  app.add_option("--cond-len", cond_len, "condition tokens (x 1024 channels)")->capture_default_str();
  app.add_option("--batch", batch, "global batch of the stream")->capture_default_str();
  app.add_option("--dir", dir, "where to write the temporary caches")->capture_default_str();
  simu::cli::CommonOptions common;
  simu::cli::add_common_options(app, common);
  return simu::cli::run(app, argc, argv, [&] {
    simu::cli::apply_common_options(common);
    using clock = std::chrono::steady_clock;
    auto secs = [](clock::time_point a) { return std::chrono::duration<double>(clock::now() - a).count(); };
    fmt::print("{:<6} {:>6} {:>10} {:>12} {:>14} {:>14}\n", "dtype", "pairs", "MiB", "write p/s", "rand read p/s",
               "stream p/s");
    for (auto dtype : {torch::kFloat16, torch::kFloat32}) {
      const auto path = fmt::format("{}/pair_cache_bench_{}_{}.h5", dir, dtype == torch::kFloat16 ? "f16" : "f32", ::getpid());
      // Write.
      auto t0 = clock::now();
      simu::data::make_synthetic_cache(path, n, {4096, 8}, {cond_len, 1024}, 0, dtype);
      const double write = n / secs(t0);
      // Random reads in a permuted order.
      const auto reader = simu::data::PairCacheReader::open(path);
      const auto perm = simu::data::epoch_permutation(n, 1, 0);
      t0 = clock::now();
      for (auto i : perm) reader.read(i);
      const double rand_read = n / secs(t0);
      // Stream: one epoch of global batches on one rank (prefetch thread).
      simu::data::PairStream stream(path, 0, 1, batch, 1);
      t0 = clock::now();
      int64_t got = 0;
      for (int64_t s = 0; s < stream.steps_per_epoch(); ++s) got += static_cast<int64_t>(stream.next_batch().size());
      const double streamed = got / secs(t0);
      fmt::print("{:<6} {:>6} {:>10.1f} {:>12.1f} {:>14.1f} {:>14.1f}\n", dtype == torch::kFloat16 ? "f16" : "f32", n,
                 std::filesystem::file_size(path) / 1048576.0, write, rand_read, streamed);
      std::filesystem::remove(path);
    }
    return 0;
  });
}
