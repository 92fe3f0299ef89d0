// One training process of train_fmdpo as a library call: the device of this rank, the communicator,
// the generator policy with its adapters, the trainer (with the condition embedder of an inputs-mode
// cache), resume, run. apps/train_fmdpo.cpp (one rank of torchrun, or each rank it launches) and the
// Python module's simuscene.train_fmdpo (one rank in-process) call it.
#pragma once

#include <string>

#include "training/distributed.h"
#include "training/train_config.h"

namespace simu::training {

struct TrainRunOptions {
  std::string resume;      // "" (fresh), "latest" (newest under run.out_dir/checkpoints) or a checkpoint dir
  bool overwrite = false;  // a fresh run removes an earlier run's outputs in run.out_dir (else refused)
  DistEnv env;             // this process's place in the job (DistEnv::from_environment() in the program)
};

// Trains cfg on this rank: prepare_out_dir (rank 0 leads), device cuda:LOCAL_RANK when train.device is
// cuda (an error naming the key when none is visible), the communicator, the policy, the trainer, the
// condition embedder of an inputs-mode cache, the resume, then Trainer::run. Returns the optimizer
// steps done.
int64_t run_training(const TrainConfig& cfg, const TrainRunOptions& options);

}  // namespace simu::training
