#include "training/train_run.h"

#include "common/error.h"
#include "common/log.h"
#include "training/checkpoint.h"
#include "training/cond_inputs.h"
#include "training/generator_policy.h"
#include "training/launcher.h"
#include "training/pair_source.h"
#include "training/trainer.h"

namespace simu::training {

int64_t run_training(const TrainConfig& cfg, const TrainRunOptions& options) {
  const DistEnv& env = options.env;
  prepare_out_dir(cfg, !options.resume.empty(), options.overwrite, /*lead=*/env.rank == 0);
  const torch::Device device = rank_device(cfg.train.device, env.local_rank);
  auto comm = Communicator::create(env, device, std::chrono::milliseconds(static_cast<int64_t>(cfg.dist.timeout_s * 1000)));
  auto model = make_generator_policy(cfg, device);
  Trainer trainer(cfg, *model, pair_cache_source(cfg.data.cache, cfg.data.prefetch), *comm, device);
  attach_condition_embedder(trainer, cfg, device);  // inputs-mode caches: the embedder runs in the step
  if (!options.resume.empty()) trainer.resume(resolve_resume(cfg.run.out_dir + "/checkpoints", options.resume));
  trainer.run();
  return trainer.steps_done();
}

}  // namespace simu::training
