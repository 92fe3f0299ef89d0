// train_fmdpo: FM-DPO fine-tuning of the Stage-1 shape branch's LoRA adapters on a pair cache.
//   train_fmdpo --config configs/lora64.yaml [--set optim.lr=2e-5] [--resume latest|DIR]
//   train_fmdpo --config ... --nproc-per-node 2        (starts the local ranks itself)
//   torchrun --nproc-per-node 2 --no-python train_fmdpo --config ...
#include <cstdlib>

#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "training/distributed.h"
#include "training/launcher.h"
#include "training/train_run.h"

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
    TrainRunOptions run;
    run.env = DistEnv::from_environment();
    simu::log::set_rank(run.env.rank);
    run.resume = resume;
    run.overwrite = overwrite;
    run_training(TrainConfig::load(config_path, common.sets), run);
    return 0;
  });
}
