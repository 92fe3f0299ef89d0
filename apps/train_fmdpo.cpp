// train_fmdpo: FM-DPO fine-tuning of the Stage-1 shape branch's LoRA adapters on a pair cache.
//   train_fmdpo --config configs/lora64.yaml [--set optim.lr=2e-5] [--resume latest|DIR]
//   train_fmdpo --config ... --nproc-per-node 2        (starts the local ranks itself)
//   torchrun --nproc-per-node 2 --no-python train_fmdpo --config ...
#include <cstdlib>

#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "training/cond_inputs.h"
#include "training/distributed.h"
#include "training/launcher.h"
#include "training/generator_policy.h"
#include "training/trainer.h"

int main(int argc, char** argv) {
  CLI::App app{"FM-DPO fine-tuning of the shape branch's LoRA adapters on cached latent preference pairs"};
  std::string config_path, resume;
  int nproc = 0;
  bool overwrite = false;
  app.add_option("--config", config_path, "training config (YAML), e.g. configs/lora64.yaml")->required();
  app.add_option("--resume", resume, "continue from 'latest' (newest under run.out_dir/checkpoints) or a checkpoint dir");
  app.add_flag("--overwrite", overwrite, "start afresh in a run.out_dir that holds an earlier run (its outputs are removed)");
  app.add_option("--nproc-per-node", nproc, "start this many local ranks (one per GPU) and watch them");
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    using namespace simu::training;
    // Launcher mode: validate the config, then start and watch the ranks.
    if (nproc > 1 && !std::getenv("RANK")) {
      auto cfg = TrainConfig::load(config_path, common.sets);
      prepare_out_dir(cfg, !resume.empty(), overwrite, /*lead=*/true);
      launch_local_ranks(nproc, relaunch_args(argc, argv), std::chrono::seconds(static_cast<int64_t>(cfg.dist.hang_timeout_s)));
      return 0;
    }
    const auto env = DistEnv::from_environment();
    simu::log::set_rank(env.rank);
    auto cfg = TrainConfig::load(config_path, common.sets);
    prepare_out_dir(cfg, !resume.empty(), overwrite, /*lead=*/env.rank == 0);
    const torch::Device device = rank_device(cfg.train.device, env.local_rank);
    auto comm = Communicator::create(env, device, std::chrono::milliseconds(static_cast<int64_t>(cfg.dist.timeout_s * 1000)));
    auto model = make_generator_policy(cfg, device);
    Trainer trainer(cfg, *model, pair_cache_source(cfg.data.cache, cfg.data.prefetch), *comm, device);
    attach_condition_embedder(trainer, cfg, device);  // inputs-mode caches: the embedder runs in the step
    if (!resume.empty()) trainer.resume(resolve_resume(cfg.run.out_dir + "/checkpoints", resume));
    trainer.run();
    return 0;
  });
}
