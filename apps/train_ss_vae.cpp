// train_ss_vae: trains the sparse-structure VAE (official SparseStructureEncoder + Decoder) from scratch
// on the shape world's voxelised shapes, and reports its reconstruction IoU on the test split.
//   train_ss_vae --config configs/miniature/ss_vae.yaml [--set train.steps=2000] [--resume latest|DIR]
//   train_ss_vae --config ... --nproc-per-node 2        (starts the local ranks itself)
//   train_ss_vae --config ... --evaluate RUN/weights    (the test table of exported weights; no training)
#include <cstdlib>
#include <cstring>

#include <c10/cuda/CUDAFunctions.h>

#include "common/cli.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "common/random.h"
#include "pipeline/world/shapes.h"
#include "pipeline/world/voxelize.h"
#include "training/distributed.h"
#include "training/launcher.h"
#include "training/ss_vae_trainer.h"

namespace {

using namespace simu::training;
namespace world = simu::world;

// The first n instance seeds of a family's split, from seed 0 up (fixed lists, the same in every run).
std::vector<ShapeKey> first_instances(const std::string& family, world::Split split, int64_t n) {
  std::vector<ShapeKey> keys;
  uint64_t seed = 0;
  for (int64_t i = 0; i < n; ++i, ++seed) keys.push_back({family, seed = world::next_instance_seed(family, split, seed)});
  return keys;
}

// A shape's canonical mesh. The loader asks for both grids of a sample (target, then the encoder's) on
// one thread, so each thread keeps its last shape and makes it once.
const simu::physics::Mesh& shape_mesh(const ShapeKey& k) {
  thread_local ShapeKey last{"", 0};
  thread_local simu::physics::Mesh mesh;
  if (last.family.empty() || last.family != k.family || last.seed != k.seed) {
    mesh = world::make_shape(k.family, k.seed).mesh;
    last = k;
  }
  return mesh;
}

// The shape world as the VAE's data. Training: family index % F in turn (the world's train split's
// families, or data.families), a Train instance drawn from (data.seed, index): a fresh one every time,
// or one of data.train_instances fixed ones. Validation / test: the first val_per_family /
// test_per_family instances of each family's Val / Test split, and the held-out family's test ones.
std::shared_ptr<ShapeSet> world_shapes(const SsVaeConfig& cfg) {
  auto set = std::make_shared<ShapeSet>();
  const int R = static_cast<int>(cfg.data.resolution);
  set->resolution = R;
  set->held_out_family = world::held_out_family();
  auto families = cfg.data.families.empty() ? world::split_families(world::Split::Train) : cfg.data.families;
  for (const auto& f : families) {
    SIMU_CHECK(world::is_family(f), "{}: data.families: '{}' is not a shape-world family", cfg.file, f);
    SIMU_CHECK(f != world::held_out_family(), "{}: data.families: '{}' is the held-out family, never trained on",
               cfg.file, f);
  }
  set->occupancy = [R](const ShapeKey& k) { return world::voxelize_filled(shape_mesh(k), R); };
  // The encoder's own grid of the same shape when it reads another side (data.encoder_resolution).
  const int Ri = static_cast<int>(cfg.encoder_resolution());
  if (Ri != R) {
    set->input_resolution = Ri;
    set->input_occupancy = [Ri](const ShapeKey& k) { return world::voxelize_filled(shape_mesh(k), Ri); };
  }
  const uint64_t data_seed = simu::splitmix64(cfg.data.seed);
  const int64_t F = static_cast<int64_t>(families.size());
  if (cfg.data.train_instances > 0) {
    // A fixed pool per family, each sample one of its members; grids made once.
    auto pool = std::make_shared<std::vector<std::vector<uint64_t>>>();
    for (const auto& f : families) {
      std::vector<uint64_t> seeds;
      uint64_t s = data_seed;
      for (int64_t i = 0; i < cfg.data.train_instances; ++i, ++s) seeds.push_back(s = world::next_instance_seed(f, world::Split::Train, s));
      pool->push_back(std::move(seeds));
    }
    set->train = [families, pool, data_seed, F](int64_t index) {
      const auto& seeds = (*pool)[index % F];
      return ShapeKey{families[index % F], seeds[simu::splitmix64(data_seed ^ static_cast<uint64_t>(index)) % seeds.size()]};
    };
    set->occupancy = cached_occupancy(set->occupancy, R);
    if (set->input_occupancy) set->input_occupancy = cached_occupancy(set->input_occupancy, Ri);
  } else {
    set->train = [families, data_seed, F](int64_t index) {
      const auto& f = families[index % F];
      return ShapeKey{f, world::next_instance_seed(f, world::Split::Train, simu::splitmix64(data_seed ^ static_cast<uint64_t>(index)))};
    };
  }
  for (const auto& f : families) {
    for (auto& k : first_instances(f, world::Split::Val, cfg.eval.val_per_family)) set->val.push_back(k);
    for (auto& k : first_instances(f, world::Split::Test, cfg.eval.test_per_family)) set->test.push_back(k);
  }
  for (auto& k : first_instances(world::held_out_family(), world::Split::Test, cfg.eval.test_per_family)) set->test.push_back(k);
  return set;
}

torch::Device pick_device(const SsVaeConfig& cfg, int local_rank) {
  if (cfg.train.device != "cuda") return torch::kCPU;
  if (!torch::cuda::is_available())
    simu::fail_hint("set train.device: cpu (slow) or run on a GPU machine", "train.device is cuda but no CUDA device is visible");
  SIMU_CHECK(local_rank < static_cast<int>(torch::cuda::device_count()), "LOCAL_RANK {} but only {} CUDA devices are visible",
             local_rank, torch::cuda::device_count());
  c10::cuda::set_device(static_cast<c10::DeviceIndex>(local_rank));
  return torch::Device(torch::kCUDA, local_rank);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Train the sparse-structure VAE (SparseStructureEncoder + Decoder) on the shape world's voxelised shapes"};
  std::string config_path, resume, evaluate;
  int nproc = 0;
  bool overwrite = false;
  app.add_option("--config", config_path, "training config (YAML), e.g. configs/miniature/ss_vae.yaml")->required();
  app.add_option("--resume", resume, "continue from 'latest' (newest under run.out_dir/checkpoints) or a checkpoint dir");
  app.add_flag("--overwrite", overwrite, "start afresh in a run.out_dir that holds an earlier run (its outputs are removed)");
  app.add_option("--nproc-per-node", nproc, "start this many local ranks (one per GPU) and watch them");
  app.add_option("--evaluate", evaluate,
                 "no training: reconstruction IoU of exported weights (a run's weights/ folder: ss_encoder.*, "
                 "ss_decoder.*) on the test split, by family, printed and written to DIR/eval.json");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    // Launcher mode: validate the config, then start and watch the ranks.
    if (nproc > 1 && !std::getenv("RANK")) {
      auto cfg = SsVaeConfig::load(config_path, common.sets);
      prepare_run_dir(cfg.file, cfg.run.out_dir, ss_vae_run_outputs(), !resume.empty(), overwrite, /*lead=*/true);
      std::vector<std::string> args;
      for (int i = 1; i < argc; ++i) {
        if (std::strcmp(argv[i], "--nproc-per-node") == 0) { ++i; continue; }
        if (std::strncmp(argv[i], "--nproc-per-node=", 17) == 0) continue;
        args.push_back(argv[i]);
      }
      launch_local_ranks(nproc, args, std::chrono::seconds(static_cast<int64_t>(cfg.dist.hang_timeout_s)));
      return 0;
    }
    const auto env = DistEnv::from_environment();
    simu::log::set_rank(env.rank);
    auto cfg = SsVaeConfig::load(config_path, common.sets);
    const auto device = pick_device(cfg, env.local_rank);
    const auto shapes = world_shapes(cfg);
    // Evaluation of exported weights (one process).
    if (!evaluate.empty()) {
      auto enc = simu::models::load_ss_encoder(evaluate + "/ss_encoder.json", evaluate + "/ss_encoder.safetensors", device);
      auto dec = simu::models::load_ss_decoder(evaluate + "/ss_decoder.json", evaluate + "/ss_decoder.safetensors", device);
      const auto iou = reconstruction_iou(*enc, *dec, *shapes, shapes->test, cfg.eval.batch,
                                          static_cast<int>(cfg.data.workers), cfg.train.precision == "bf16");
      const auto table = iou_table(shapes->test, iou, shapes->held_out_family);
      const nlohmann::json j = {{"split", "test"}, {"weights", evaluate}, {"config", cfg.file}, {"iou", table.to_json()}};
      simu::fs::atomic_write(evaluate + "/eval.json", j.dump(1) + "\n");
      std::printf("Test reconstruction IoU of %s (posterior mean, logits > 0):\n%s", evaluate.c_str(), table.markdown().c_str());
      return 0;
    }
    prepare_run_dir(cfg.file, cfg.run.out_dir, ss_vae_run_outputs(), !resume.empty(), overwrite, /*lead=*/env.rank == 0);
    auto comm = Communicator::create(env, device, std::chrono::milliseconds(static_cast<int64_t>(cfg.dist.timeout_s * 1000)));
    SsVaeTrainer trainer(cfg, shapes, *comm, device);
    if (!resume.empty()) trainer.resume(resolve_resume(cfg.run.out_dir + "/checkpoints", resume));
    trainer.run();
    return 0;
  });
}
