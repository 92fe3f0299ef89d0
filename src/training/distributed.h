// Data-parallel plumbing: rendezvous from the environment, gradient averaging, the local launcher.
//
// One process per GPU. Ranks meet through c10d's TCPStore at MASTER_ADDR:MASTER_PORT (rank 0 hosts
// it). Gradients are averaged with c10d ProcessGroupNCCL on GPU and c10d ProcessGroupGloo on CPU.
// The torch wheel ships Gloo's code inside libtorch_cpu but not its headers, which ProcessGroupGloo.hpp
// includes: they come from Debian's libgloo-dev (headers only, never linked). A build without them
// (CMake says so) falls back on CPU to a store-based reduction (each rank posts its flattened tensor,
// all sum in rank order) and logs why; backend() tells which one runs.
// Every collective waits at most `timeout`; a rank missing from it is named in the error.
#pragma once

#include <torch/torch.h>

#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include <torch/csrc/distributed/c10d/Store.hpp>

namespace simu::training {

// Where this process sits in the job.
struct DistEnv {
  int rank = 0, local_rank = 0, world_size = 1;
  std::string master_addr = "127.0.0.1";
  int master_port = 29500;
  // RANK/LOCAL_RANK/WORLD_SIZE/MASTER_ADDR/MASTER_PORT (torchrun), else SLURM_PROCID/SLURM_LOCALID/
  // SLURM_NTASKS, else a single process. MASTER_ADDR, when unset under Slurm, is the first host of
  // SLURM_STEP_NODELIST (or SLURM_JOB_NODELIST, SLURM_NODELIST): the node of rank 0 under srun's
  // default block distribution. MASTER_PORT defaults to 29500.
  static DistEnv from_environment();
};

// First host of a Slurm host list ("gpu[03-05,07],cpu1" -> "gpu03"; "a-[2-4]-ib" -> "a-2-ib";
// "n1,n2" -> "n1"). Throws simu::Error naming the list when it is empty or its brackets do not close.
std::string first_slurm_host(const std::string& nodelist);

// Collectives among the ranks of a job (a no-op for world size 1).
class Communicator {
 public:
  // device: cuda -> NCCL for tensors; cpu -> Gloo (store-based without the gloo headers). timeout
  // bounds every collective.
  static std::unique_ptr<Communicator> create(const DistEnv& env, const torch::Device& device,
                                              std::chrono::milliseconds timeout);
  virtual ~Communicator() = default;
  virtual int rank() const = 0;
  virtual int world_size() const = 0;
  // What moves the tensors: "nccl", "gloo", "store" (TCPStore fallback) or "single" (world of one).
  virtual std::string backend() const = 0;
  // Averages tensors (all on the same device, floating point) over ranks, in place, as one buffer.
  virtual void all_reduce_mean(std::vector<torch::Tensor>& tensors) = 0;
  // Sums numbers over ranks (metrics); every rank gets the sums.
  virtual std::vector<double> all_reduce_sum(const std::vector<double>& values) = 0;
  // Waits for every rank; names the missing ones on timeout.
  virtual void barrier() = 0;
};

// CPU communicator over an existing store: c10d ProcessGroupGloo when this build has the gloo headers
// (have_gloo()), else the store-based reduction with a logged warning. What create() uses on CPU;
// tests use it with two threads. All ranks must call it together (Gloo connects them within timeout).
std::unique_ptr<Communicator> make_cpu_communicator(c10::intrusive_ptr<c10d::Store> store, int rank, int world_size,
                                                    std::chrono::milliseconds timeout);
// True when this build has c10d ProcessGroupGloo (the gloo headers were found at configure time).
bool have_gloo();
// Communicator over an existing store with the store-based reduction (the fallback; tests).
std::unique_ptr<Communicator> make_store_communicator(c10::intrusive_ptr<c10d::Store> store, int rank, int world_size,
                                                      std::chrono::milliseconds timeout);
// World of one (backend "single"): every collective returns its input. What create() gives a single
// process; tests of the training loop use it.
std::unique_ptr<Communicator> make_solo_communicator();
// TCPStore for env (rank 0 serves); waits for all ranks to connect within timeout.
c10::intrusive_ptr<c10d::Store> connect_store(const DistEnv& env, std::chrono::milliseconds timeout);

// A TCP port free on the loopback interface right now.
int free_port();


}  // namespace simu::training
