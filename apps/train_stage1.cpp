// train_stage1: Stage-1 pretraining from scratch (docs/train_stage1.md): the MoT flow model and the
// condition embedder trained with the flow-matching objective on a stage-1 sample cache.
//   train_stage1 --config configs/miniature/train_stage1.yaml [--set train.steps=2000] [--resume latest|DIR]
//   train_stage1 --config ... --nproc-per-node 2        (starts the local ranks itself)
//   torchrun --nproc-per-node 2 --no-python train_stage1 --config ...
#include <cstdlib>

#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "data/stage1_cache.h"
#include "training/distributed.h"
#include "training/flow_objective.h"
#include "training/launcher.h"
#include "training/stage1_config.h"
#include "training/stage1_data.h"
#include "training/stage1_model.h"
#include "training/stage1_targets.h"
#include "training/trainer.h"

int main(int argc, char** argv) {
  CLI::App app{"Stage-1 pretraining from scratch: flow model and condition embedder, flow matching on a stage-1 "
               "sample cache"};
  std::string config_path, resume;
  int nproc = 0;
  bool overwrite = false;
  app.add_option("--config", config_path, "training config (YAML), e.g. configs/miniature/train_stage1.yaml")->required();
  app.add_option("--resume", resume, "continue from 'latest' (newest under run.out_dir/checkpoints) or a checkpoint dir");
  app.add_flag("--overwrite", overwrite, "start afresh in a run.out_dir that holds an earlier run (its outputs are removed)");
  app.add_option("--nproc-per-node", nproc, "start this many local ranks (one per GPU) and watch them");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    using namespace simu::training;
    const std::string build_hint = "build one with build_stage1_data";
    // Launcher mode: validate the config, then start and watch the ranks.
    if (nproc > 1 && !std::getenv("RANK")) {
      auto cfg = Stage1Config::load(config_path, common.sets);
      prepare_out_dir(cfg, !resume.empty(), overwrite, /*lead=*/true, build_hint);
      launch_local_ranks(nproc, relaunch_args(argc, argv),
                         std::chrono::seconds(static_cast<int64_t>(cfg.dist.hang_timeout_s)));
      return 0;
    }
    const auto env = DistEnv::from_environment();
    simu::log::set_rank(env.rank);
    auto cfg = Stage1Config::load(config_path, common.sets);
    prepare_out_dir(cfg, !resume.empty(), overwrite, /*lead=*/env.rank == 0, build_hint);
    const torch::Device device = rank_device(cfg.train.device, env.local_rank);
    auto comm = Communicator::create(env, device, std::chrono::milliseconds(static_cast<int64_t>(cfg.dist.timeout_s * 1000)));
    // The model and the shape-latent targets (checked against the cache's grid), then the training
    // split in memory.
    auto model = make_stage1_model(cfg.model.generator, cfg.model.embedder, cfg.model.init, device, cfg.train.seed);
    const auto& flow = model->generator->config().backbone;
    const int64_t R = simu::data::Stage1CacheReader::open(cfg.data.cache).info().occupancy_resolution;
    auto targets = make_shape_targets(cfg.targets, flow.latent("shape"), R, device, cfg.file);
    auto samples = load_stage1_samples(cfg.data.cache, simu::data::parse_sample_split(cfg.dataset.split),
                                       /*progress=*/env.rank == 0 && cfg.run.progress);
    const auto counts = count_parameters(model);
    if (env.rank == 0)
      simu::log::info("Stage-1 model: flow model {:.2f} M parameters, condition embedder {:.2f} M; {} on {}",
                      counts.flow / 1e6, counts.embedder / 1e6, cfg.train.precision, device.str());
    Trainer trainer(cfg, std::make_unique<FlowObjective>(cfg, model, samples, targets, device), *comm, device);
    if (!resume.empty()) trainer.resume(resolve_resume(cfg.run.out_dir + "/checkpoints", resume));
    trainer.run();
    return 0;
  });
}
