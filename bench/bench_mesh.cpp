// bench_mesh: CPU time of the resampler's per-object "logits -> canonical mesh" step
// (resample::mesh_from_logits: occupied voxels, marching cubes on the logits, voxel frame, canonical
// frame) on 64^3 grids: (a) random logits as random weights give (~42% occupied, spatially
// uncorrelated), (b) the same noise smoothed by a 3^3 box filter (larger components), (c) a ball.
// Prints a table per thread count: ms per object for the whole step, for marching cubes alone, and for
// the sequential marching_cubes_reference (the implementation before the fast path, same mesh);
// vertices, triangles, and the threads used (at::get_num_threads()). The median of --reps runs.
#include <ATen/Parallel.h>
#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <functional>

#include "common/cli.h"
#include "pipeline/resample/marching_cubes.h"
#include "pipeline/resample/resampler.h"

using namespace simu::physics;
using namespace simu::resample;

namespace {

// Median wall time in milliseconds of `reps` calls of f (after one warm-up call).
double median_ms(int reps, const std::function<void()>& f) {
  f();
  std::vector<double> t;
  for (int i = 0; i < reps; ++i) {
    const auto t0 = std::chrono::steady_clock::now();
    f();
    t.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
  std::sort(t.begin(), t.end());
  return t[t.size() / 2];
}

// Logits [R, R, R] whose values are > 0 at a fraction `occupied` of the voxels (threshold at the quantile).
torch::Tensor shift_to_occupancy(torch::Tensor x, double occupied) {
  const auto sorted = std::get<0>(x.flatten().sort());
  const int64_t k = static_cast<int64_t>((1.0 - occupied) * static_cast<double>(x.numel()));
  return (x - sorted[k].item<float>()).contiguous();
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Benchmark logits -> canonical mesh (marching cubes) per object on 64^3 grids"};
  int64_t res = 64;
  int reps = 5;
  double occupied = 0.42;
  std::vector<int> threads = {1, 0};
  app.add_option("--res", res, "grid resolution")->capture_default_str();
  app.add_option("--reps", reps, "timed runs per case (median)")->capture_default_str();
  app.add_option("--occupied", occupied, "occupied fraction of the random grids")->capture_default_str();
  app.add_option("--threads", threads, "thread counts to run (0 = all cores, at::get_num_threads default)")
      ->capture_default_str();
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    const int default_threads = at::get_num_threads();
    // Test grids.
    torch::manual_seed(0);
    const auto noise = torch::randn({res, res, res});
    const auto smooth = torch::avg_pool3d(noise.view({1, 1, res, res, res}), 3, 1, 1).view({res, res, res});
    auto i = torch::arange(res, torch::kFloat32);
    const double c = (static_cast<double>(res) - 1) / 2, r = 0.375 * static_cast<double>(res);
    const auto d = torch::sqrt((i.view({res, 1, 1}) - c).pow(2) + (i.view({1, res, 1}) - c).pow(2) +
                               (i.view({1, 1, res}) - c).pow(2));
    const std::vector<std::pair<std::string, torch::Tensor>> cases = {
        {"random", shift_to_occupancy(noise, occupied)},
        {"random-smoothed", shift_to_occupancy(smooth, occupied)},
        {"sphere", (r - d).contiguous()},
    };
    fmt::print("bench_mesh: {}^3 grids, median of {} runs, {} cores reported by ATen\n", res, reps, default_threads);
    fmt::print("{:<16} {:>7} {:>9} {:>10} {:>10} {:>13} {:>11} {:>11}\n", "case", "threads", "occupied", "vertices",
               "triangles", "mesh_from_ms", "mc_only_ms", "mc_ref_ms");
    for (int t : threads) {
      at::set_num_threads(t > 0 ? t : default_threads);
      for (const auto& [name, logits] : cases) {
        ResampledShape out;
        const double full = median_ms(reps, [&] { mesh_from_logits(logits, out); });
        Mesh mesh;
        const double mc = median_ms(reps, [&] { mesh = marching_cubes(logits); });
        const double ref = median_ms(reps, [&] { mesh = marching_cubes_reference(logits); });
        const double occ = (logits > 0).to(torch::kFloat64).mean().item<double>();
        fmt::print("{:<16} {:>7} {:>9.3f} {:>10} {:>10} {:>13.2f} {:>11.2f} {:>11.2f}\n", name, at::get_num_threads(), occ,
                   out.mesh.V.rows(), out.mesh.F.rows(), full, mc, ref);
      }
    }
    at::set_num_threads(default_threads);
    return 0;
  });
}
