// bench_world: how fast the shape world makes training data on the CPU. Times (median and 90th
// percentile over --scenes scenes, one thread; the thread's CPU time beside the wall time, since a
// shared machine's wall time counts other processes' turns): make_scene (room, instances, rest analysis, placement,
// render), render_scene alone (the z-buffer pass, shading, amodal masks), render_without (the edited
// image), make_scene with occlusion targets, corrupt_pointmap, and voxelize_filled at --resolution per
// family (median over --instances instances); then scenes per second with --threads threads.
#include "common/cli.h"
#include "common/parallel.h"
#include "common/timing.h"
#include "pipeline/world/corrupt.h"
#include "pipeline/world/scene.h"
#include "pipeline/world/voxelize.h"

#include <fmt/format.h>

#include <time.h>

#include <algorithm>
#include <vector>

using namespace simu::world;

namespace {

// Wall and this thread's CPU time of a call (seconds).
struct Timed {
  std::vector<double> wall, cpu;
  template <class Fn>
  void operator()(Fn&& fn) {
    timespec c0{}, c1{};
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &c0);
    const auto t0 = simu::Clock::now();
    fn();
    wall.push_back(simu::seconds_since(t0));
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &c1);
    cpu.push_back(double(c1.tv_sec - c0.tv_sec) + 1e-9 * double(c1.tv_nsec - c0.tv_nsec));
  }
};

// Median and 90th percentile (ms) of a list of seconds.
std::string stats(std::vector<double> s) {
  std::sort(s.begin(), s.end());
  return fmt::format("median {:7.2f} ms  p90 {:7.2f} ms", 1e3 * s[s.size() / 2], 1e3 * s[s.size() * 9 / 10]);
}
std::string stats(const Timed& t) { return fmt::format("cpu {}  | wall {}  (n {})", stats(t.cpu), stats(t.wall), t.cpu.size()); }

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Timing of the shape world: scenes, renders, edited renders, corruption, voxelisation, throughput"};
  int scenes = 40, instances = 20, resolution = 32, threads = 16, width = 320, height = 240;
  app.add_option("--scenes", scenes, "scenes timed")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--instances", instances, "instances per family voxelised")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--resolution", resolution, "voxel grid R")->capture_default_str();
  app.add_option("--threads", threads, "threads for the throughput run")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--width", width, "image width")->capture_default_str();
  app.add_option("--height", height, "image height")->capture_default_str();
  return simu::cli::run(app, argc, argv, [&] {
    SceneConfig cfg;
    cfg.width = width, cfg.height = height;
    SceneConfig occl = cfg;
    occl.targets = 1;
    Timed t_make, t_render, t_without, t_occl, t_corrupt;
    size_t objects = 0;
    uint64_t seed = 0;
    for (int k = 0; k < scenes; ++k) {
      seed = next_scene_seed(Split::Train, seed + 1);
      WorldScene s;
      t_make([&] { s = make_scene(cfg, seed, Split::Train); });
      objects += s.objects.size();
      t_render([&] { render_scene(s); });
      t_without([&] { const WorldScene e = render_without(s, {0}); });
      t_corrupt([&] { const PointMap c = corrupt_pointmap(s.pointmap, CorruptionConfig{}, seed); });
      t_occl([&] { const WorldScene o = make_scene(occl, seed, Split::Train); });
    }
    fmt::print("{}x{}, {:.1f} objects per scene on average\n", width, height, double(objects) / scenes);
    fmt::print("make_scene             {}\n", stats(t_make));
    fmt::print("  render_scene         {}\n", stats(t_render));
    fmt::print("render_without         {}\n", stats(t_without));
    fmt::print("make_scene, 1 target   {}\n", stats(t_occl));
    fmt::print("corrupt_pointmap       {}\n", stats(t_corrupt));
    Timed t_vox;
    for (const auto& f : families()) {
      Timed tf;
      for (int k = 0; k < instances; ++k) {
        const ShapeInstance s = make_shape(f, uint64_t(k));
        tf([&] { const auto g = voxelize_filled(s.mesh, resolution); });
        t_vox([&] { const auto g = voxelize_filled(s.mesh, resolution); });
      }
      fmt::print("voxelize_filled R={} {:<11} {}\n", resolution, f, stats(tf));
    }
    fmt::print("voxelize_filled R={} all         {}\n", resolution, stats(t_vox));
    // Throughput: independent scenes on `threads` threads.
    const int n = std::max(scenes, 4 * threads);
    const auto t0 = simu::Clock::now();
    simu::parallel_for_each(n, threads, [&](int64_t k) { make_scene(cfg, next_scene_seed(Split::Train, uint64_t(k) * 1000), Split::Train); });
    const double dt = simu::seconds_since(t0);
    fmt::print("throughput: {} scenes on {} threads in {:.2f} s = {:.1f} scenes/s\n", n, threads, dt, n / dt);
    return 0;
  });
}
