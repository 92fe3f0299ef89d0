// The local launcher (train_fmdpo --nproc-per-node N): starts the ranks of one machine as child
// processes of this program and watches them through heartbeat files.
#pragma once

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

}  // namespace simu::training
