// bench_lift: time per object of the lift path (resample/lift.h lift_objects: released preprocessing,
// condition embedder, 25-step CFG sampling, decoder, marching cubes, pose) at batch 1 and 8, at the
// released dimensions with random weights (configs/stage1_real.yaml, configs/cond_embedder_sam3d_stage1.yaml
// = 7,528 condition tokens per object, configs/ss_decoder.yaml). A synthetic 640x480 photo with 8
// objects (boxes in front of a wall, pinhole point map) stands in for a real one. Prints a table of
// per-object milliseconds split into preprocess / embed / sampling / decoder / mesh / pose.
// Random decoder weights give arbitrary occupancy: the table reports the occupied voxels per object
// next to the mesh time (--decoder-bias shifts the output logits to change it). Other models through
// --generator-config / --embedder-config / --decoder-config and their preprocessing through
// --preprocess (e.g. the miniature: configs/miniature/, docs/train_stage1.md "Sizing").
#include <c10/cuda/CUDACachingAllocator.h>
#include <fmt/format.h>
#include <fmt/ranges.h>
#include <torch/cuda.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <chrono>
#include <functional>
#include <thread>

#include <sys/resource.h>

#include "common/source_dir.h"
#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "data/depth_io.h"
#include "pipeline/resample/lift.h"
#include "pipeline/resample/marching_cubes.h"
#include "data/preprocess.h"

namespace {

double peak_gib(const torch::Device& d) {
  if (!d.is_cuda()) return 0;
  const auto s = c10::cuda::CUDACachingAllocator::getDeviceStats(d.index() < 0 ? 0 : d.index());
  return static_cast<double>(s.allocated_bytes[0].peak) / (1024.0 * 1024.0 * 1024.0);
}

// A 640x480 photo: a wall at 3 m, 8 boxes (4 x 2 grid) at 1.5..2.2 m, their masks; f = 0.9 W.
simu::resample::LiftInputs synthetic_photo(int64_t n_objects) {
  const int64_t W = 640, H = 480;
  const double f = 0.9 * W, cx = W / 2.0, cy = H / 2.0;
  auto z = torch::full({H, W}, 3.0, torch::kFloat32);
  auto rgb = torch::rand({3, H, W}, torch::TensorOptions().dtype(torch::kFloat32)) * 0.2 + 0.4;
  simu::resample::LiftInputs in;
  for (int64_t k = 0; k < n_objects; ++k) {
    const int64_t col = k % 4, row = (k / 4) % 2;
    const int64_t x0 = 30 + col * 150, y0 = 40 + row * 220, w = 100 + 7 * k, h = 120 + 5 * k;
    auto mask = torch::zeros({H, W}, torch::kFloat32);
    mask.slice(0, y0, std::min(y0 + h, H)).slice(1, x0, std::min(x0 + w, W)).fill_(1.0);
    z = torch::where(mask > 0, torch::full_like(z, 1.5 + 0.1 * static_cast<double>(k)), z);
    rgb = torch::where(mask.unsqueeze(0) > 0, torch::rand({3, 1, 1}).expand({3, H, W}), rgb);
    in.objects.push_back({fmt::format("box_{}", k), mask, {}, ""});
  }
  in.rgb = rgb;
  in.pointmap = simu::data::unproject_depth(z, {f, f, cx, cy});
  in.camera.fx = in.camera.fy = f;
  in.camera.cx = cx;
  in.camera.cy = cy;
  in.camera.width = static_cast<int>(W);
  in.camera.height = static_cast<int>(H);
  return in;
}

// Minor page faults of this process so far (first touches of fresh memory).
long minor_faults() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_minflt;
}

// Median of `reps` runs of fn in ms (after one untimed run), each after `idle_ms` of sleep (0: back to back).
double median_ms(int reps, const std::function<void()>& fn, int idle_ms = 0) {
  fn();
  std::vector<double> ms;
  for (int i = 0; i < reps; ++i) {
    if (idle_ms > 0) std::this_thread::sleep_for(std::chrono::milliseconds(idle_ms));
    const auto t0 = std::chrono::steady_clock::now();
    fn();
    ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  }
  std::sort(ms.begin(), ms.end());
  return ms[ms.size() / 2];
}

// The CPU stages alone, back to back (warm threads, caches, allocator): one object's preprocessing and
// one decoded grid's logits -> mesh, next to what the same work costs inside a lift call.
void diagnose_cpu_stages(simu::resample::Resampler& rs, const simu::resample::LiftInputs& photo,
                         const torch::Device& dev) {
  const auto& obj = photo.objects.at(0);
  const auto pm = photo.pointmap.permute({2, 0, 1}).contiguous();
  auto pre_fn = [&] {
    (void)simu::data::prepare_condition_inputs(photo.rgb, obj.mask, pm, simu::data::PreprocessConfig{});
  };
  const double pre = median_ms(5, pre_fn), pre_idle = median_ms(5, pre_fn, 500);
  // A decoded grid of random latents (random weights: arbitrary occupancy).
  const auto& shape = rs.generator()->config().backbone.latent("shape");
  const auto latent = torch::randn({1, shape.tokens(), shape.in_channels}, torch::TensorOptions().device(dev));
  const auto logits = rs.decode_logits(latent).to(torch::kCPU);
  simu::resample::ResampledShape out;
  auto mesh_fn = [&] { simu::resample::mesh_from_logits(logits, out); };  // [1, 1, R, R, R]
  const double mesh = median_ms(5, mesh_fn), mesh_idle = median_ms(5, mesh_fn, 500);
  const double mc = median_ms(5, [&] { (void)simu::resample::marching_cubes(logits); });
  fmt::print("diagnose ({} threads, median of 5): preprocess one object {:.1f} ms back to back, {:.1f} ms after 0.5 s idle; "
             "logits -> mesh {:.1f} / {:.1f} ms (marching cubes alone {:.1f} ms; {} occupied voxels, {} vertices, {} "
             "triangles)\n",
             at::get_num_threads(), pre, pre_idle, mesh, mesh_idle, mc, out.coords.size(0), out.mesh.V.rows(),
             out.mesh.F.rows());
}

struct Row {
  std::string graphs;
  int64_t batch;
  double wall_ms, first_ms;
  simu::resample::LiftTimings t;
  int64_t voxels;
  double peak;
};

// Times lift_objects on the first B objects of `photo` with graphs "on" or "off": the first call apart,
// then the median of `iters` calls (per-call stage times and page faults logged).
Row time_lift(simu::resample::Resampler& rs, const simu::resample::LiftInputs& photo, const std::string& g, int64_t B,
              int iters, const torch::Device& dev, const simu::data::PreprocessConfig& preprocess) {
  auto ms_of = [](const simu::resample::LiftTimings& t) {
    return fmt::format("preprocess {:.1f}, embed {:.1f}, sample {:.1f}, decode {:.1f}, mesh {:.1f}, pose {:.1f} ms",
                       t.preprocess * 1e3, t.embed * 1e3, t.sample * 1e3, t.decode * 1e3, t.mesh * 1e3, t.pose * 1e3);
  };
  rs.set_cuda_graphs(g == "on");
  auto in = photo;
  in.objects.resize(static_cast<size_t>(B));
  simu::resample::LiftOptions opt;
  opt.preprocess = preprocess;
  // The first call (a fresh process's only call: kernels, allocator, graph captures) is timed apart.
  const auto f0 = std::chrono::steady_clock::now();
  const auto first = simu::resample::lift_objects(rs, in, opt);
  const double first_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - f0).count();
  simu::log::info("graphs {} batch {}: first call {:.1f} ms ({})", g, B, first_ms, ms_of(first.seconds));
  if (dev.is_cuda()) c10::cuda::CUDACachingAllocator::resetPeakStats(dev.index() < 0 ? 0 : dev.index());
  std::vector<Row> runs;
  for (int i = 0; i < iters; ++i) {
    opt.seed = static_cast<uint64_t>(i + 1);
    const long faults0 = minor_faults();
    const auto t0 = std::chrono::steady_clock::now();
    const auto res = simu::resample::lift_objects(rs, in, opt);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    const long faults = minor_faults() - faults0;
    int64_t voxels = 0;
    for (const auto& o : res.objects)
      if (!o.samples.empty() && o.samples[0].coords.defined()) voxels += o.samples[0].coords.size(0);
    runs.push_back({g, B, ms, first_ms, res.seconds, voxels / B, 0});
    simu::log::info("graphs {} batch {}: call {}/{} {:.1f} ms ({}); {} minor page faults", g, B, i + 1, iters, ms,
                    ms_of(res.seconds), faults);
  }
  std::sort(runs.begin(), runs.end(), [](const Row& a, const Row& b) { return a.wall_ms < b.wall_ms; });
  Row r = runs[runs.size() / 2];
  r.peak = peak_gib(dev);
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Benchmark lift: per-object time at batch 1 and 8 (released dimensions, random weights)"};
  std::string device = "cuda", precision = "auto";
  std::vector<int64_t> batches = {1, 8};
  int iters = 3, steps = 25;
  double decoder_bias = 0;
  bool small = false;
  app.add_option("--batches", batches, "objects per lift call")->capture_default_str();
  app.add_option("--steps", steps, "sampling steps")->capture_default_str();
  app.add_option("--iters", iters, "timed calls per batch size (median by total)")->capture_default_str();
  app.add_option("--device", device, "cuda | cuda:N | cpu")->capture_default_str();
  app.add_option("--precision", precision, "auto | fp16 | bf16 | fp32 (as lift --precision)")->capture_default_str();
  app.add_option("--decoder-bias", decoder_bias, "added to the decoder's output bias (random weights: occupancy)")
      ->capture_default_str();
  app.add_flag("--small", small, "fixture-size models (CPU smoke run of this program)");
  std::vector<std::string> graphs = {"off"};
  app.add_option("--graphs", graphs,
                 "eager launches (off: lift's default) and/or sampling through persistent CUDA graphs (on: captured "
                 "in the first call, replayed after), each a row")
      ->check(CLI::IsMember({"on", "off"}))->capture_default_str();
  std::string generator_config, embedder_config, decoder_config, preprocess_file;
  app.add_option("--generator-config", generator_config, "generator config (default: the released size)");
  app.add_option("--embedder-config", embedder_config, "condition embedder config (default: the released size)");
  app.add_option("--decoder-config", decoder_config, "decoder config (default: the released size)");
  app.add_option("--preprocess", preprocess_file, "preprocessing config (data::PreprocessConfig keys; default: released)");
  bool diagnose = false;
  app.add_flag("--diagnose", diagnose,
               "also time the CPU stages alone, back to back (preprocessing of one object, logits -> mesh of one "
               "decoded grid): what they cost when caches and threads are warm");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    const torch::Device dev(device);
    if (dev.is_cuda() && !torch::cuda::is_available()) {
      fmt::print("bench_lift: skipped: no CUDA device (use --device cpu --small for a smoke run)\n");
      return 0;
    }
    simu::resample::ResamplerConfig cfg;  // released inference sampler defaults, real-size configs
    cfg.device = device;
    cfg.steps = steps;
    cfg.embedder_config = simu::source_dir() + "/configs/cond_embedder_sam3d_stage1.yaml";
    if (small) {
      cfg.generator_config = simu::source_dir() + "/configs/stage1_small.yaml";
      cfg.decoder_config = simu::source_dir() + "/configs/ss_decoder_small.yaml";
      cfg.embedder_config = simu::source_dir() + "/configs/demo_embedder_small.json";
      cfg.generator_overrides = {"flow_model.cond_channels=48"};
    }
    if (!generator_config.empty()) cfg.generator_config = generator_config;
    if (!embedder_config.empty()) cfg.embedder_config = embedder_config;
    if (!decoder_config.empty()) cfg.decoder_config = decoder_config;
    simu::data::PreprocessConfig preprocess;
    if (!preprocess_file.empty()) {
      simu::config::Reader r(simu::config::load_file(preprocess_file), preprocess_file);
      preprocess = simu::data::PreprocessConfig::from(r);
      r.finish();
    }
    simu::resample::apply_precision(cfg, precision);
    cfg.random_weights = true;  // a benchmark: random init, banner logged
    torch::NoGradGuard no_grad;
    simu::resample::Resampler rs(cfg);
    if (decoder_bias != 0) {
      auto params = rs.decoder()->named_parameters();
      SIMU_CHECK(params.contains("out_layer.2.bias"), "decoder has no out_layer.2.bias");
      params["out_layer.2.bias"].add_(decoder_bias);
    }
    const auto& mc = rs.generator()->config().backbone;
    fmt::print("device {}; {}; generator {} ({} ch, {} blocks); embedder {} ({} tokens/object); decoder {}; {} steps, "
               "rescale_t {}, CFG {} on [{}, {}]; occupancy {}^3\n",
               dev.str(), simu::resample::effective_precision(rs), cfg.generator_config, mc.model_channels,
               mc.num_blocks, cfg.embedder_config, rs.embedder()->num_tokens(), cfg.decoder_config, cfg.steps,
               cfg.rescale_t, cfg.cfg_strength, cfg.cfg_interval.first, cfg.cfg_interval.second,
               simu::resample::occupancy_resolution(rs));
    torch::manual_seed(0);
    const int64_t max_b = *std::max_element(batches.begin(), batches.end());
    const auto photo = synthetic_photo(max_b);
    std::vector<Row> rows;
    for (const auto& g : graphs)
      for (const int64_t B : batches) rows.push_back(time_lift(rs, photo, g, B, iters, dev, preprocess));
    if (diagnose) diagnose_cpu_stages(rs, photo, dev);
    fmt::print("\n| graphs | objects per call | call ms | per object ms | first call ms per object | preprocess | embed | "
               "sampling | decoder | mesh | pose | voxels/obj | peak alloc GiB |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for (const auto& r : rows) {
      const double b = static_cast<double>(r.batch);
      fmt::print("| {} | {} | {:.1f} | {:.1f} | {:.1f} | {:.1f} | {:.1f} | {:.1f} | {:.1f} | {:.1f} | {:.2f} | {} | {:.2f} |\n",
                 r.graphs, r.batch, r.wall_ms, r.wall_ms / b, r.first_ms / b, r.t.preprocess * 1e3 / b, r.t.embed * 1e3 / b,
                 r.t.sample * 1e3 / b, r.t.decode * 1e3 / b, r.t.mesh * 1e3 / b, r.t.pose * 1e3 / b, r.voxels, r.peak);
    }
    fmt::print("(per-object columns in ms; mesh = the resampler's per-row pose decode + marching cubes + canonical "
               "frame; pose = conversion to the scene convention)\n");
    return 0;
  });
}
