// The local launcher (train_fmdpo / train_stage1 --nproc-per-node N): starts the ranks of one machine
// as child processes of this program and watches them through heartbeat files. And the two steps the
// training programs share around it: the ranks' arguments and each rank's device.
#pragma once

#include <torch/torch.h>

#include <chrono>
#include <string>
#include <vector>

namespace simu::training {

// Progress signal to a launching parent: touches $SIMU_HEARTBEAT_FILE when set (no-op otherwise).
void heartbeat();

// Starts nproc local ranks of this program (/proc/self/exe with args) with RANK, LOCAL_RANK,
// WORLD_SIZE, LOCAL_WORLD_SIZE, MASTER_ADDR=127.0.0.1, a free MASTER_PORT, NCCL_NVLS_ENABLE=0 and a
// heartbeat file each; waits for them. A rank that exits non-zero or by a signal, or sends no
// heartbeat for hang_timeout, ends the whole job (SIGTERM, then SIGKILL after 5 s) and this throws
// simu::Error naming the rank. Returns when all ranks exit 0.
void launch_local_ranks(int nproc, const std::vector<std::string>& args, std::chrono::seconds hang_timeout);

// This program's arguments (argv[1..]) without --nproc-per-node N / --nproc-per-node=N: what the
// launcher passes to every rank.
std::vector<std::string> relaunch_args(int argc, char** argv);

// The device of a rank: "cpu", or "cuda" = the local rank's GPU (made current). Errors name
// train.device when no CUDA device is visible or LOCAL_RANK exceeds the visible devices.
torch::Device rank_device(const std::string& device, int local_rank);

}  // namespace simu::training
