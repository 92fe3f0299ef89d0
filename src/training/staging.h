// Host-to-device staging of a batch, shared by the objectives (objective.h): host tensors stacked into
// one device tensor, through pinned memory and a side CUDA stream when the trainer reads ahead, and the
// event a forward waits for before it reads them.
#pragma once

#include <torch/torch.h>

#include <ATen/cuda/CUDAEvent.h>

#include <memory>
#include <vector>

#include "training/objective.h"

namespace simu::training {

// Host tensors (one dtype after promotion, one shape) stacked into [n, ...] on the device. With an
// upload stream: stacked into a pinned host buffer (kept in `held` until the step ends; the caching
// host allocator also keeps it from reuse until the copy is done), copied asynchronously on that
// stream into memory allocated on it. Without one (the reference path, and the CPU):
// stack(parts).to(device), a synchronous copy from pageable memory on CUDA.
torch::Tensor stack_to(const std::vector<torch::Tensor>& parts, const torch::Device& device, const UploadStream& stream,
                       std::vector<torch::Tensor>& held);

// Rows `rows` (int64 [m], CPU) of a host tensor [N, ...] on the device as [m, ...]: gathered straight
// into a pinned buffer (kept in `held`) and copied on the upload stream; without one,
// index_select(src, 0, rows).to(device).
torch::Tensor gather_to(const torch::Tensor& src, const torch::Tensor& rows, const torch::Device& device,
                        const UploadStream& stream, std::vector<torch::Tensor>& held);

// A CPU generator for one sample's draws at one step, seeded from (seed, step, sample id) through
// splitmix64: the draws do not depend on the rank, the micro-batch split, the read-ahead or a resume.
at::Generator sample_generator(uint64_t seed, int64_t step, int64_t sample_id);

// The copies of one group of staged tensors: an event recorded on the upload stream after them (null
// without an upload stream) and the pinned buffers they came from.
struct Uploads {
  std::vector<torch::Tensor> host;             // pinned staging buffers, held to the step's end
  std::shared_ptr<at::cuda::CUDAEvent> ready;  // recorded after the group's copies (upload stream)
  // Records `ready` on the stream after the copies issued so far (no-op without a stream).
  void record(const UploadStream& stream);
  // Makes the current (compute) stream wait for the copies, and keeps the device tensors' memory from
  // reuse by the upload stream until the compute stream is past this point. No-op without an event.
  void wait(const std::vector<torch::Tensor*>& device_tensors, const torch::Device& device);
};

}  // namespace simu::training
