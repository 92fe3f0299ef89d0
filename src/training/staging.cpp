#include "training/staging.h"

#include <ATen/CPUGeneratorImpl.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include "common/random.h"

namespace simu::training {

torch::Tensor stack_to(const std::vector<torch::Tensor>& parts, const torch::Device& device, const UploadStream& stream,
                       std::vector<torch::Tensor>& held) {
  if (!stream) return torch::stack(parts).to(device);
  auto dtype = parts.front().scalar_type();
  for (const auto& p : parts) dtype = c10::promoteTypes(dtype, p.scalar_type());
  std::vector<int64_t> shape = parts.front().sizes().vec();
  shape.insert(shape.begin(), static_cast<int64_t>(parts.size()));
  auto host = torch::empty(shape, torch::TensorOptions().dtype(dtype).pinned_memory(true));
  at::stack_out(host, parts);
  held.push_back(host);
  const c10::cuda::CUDAStreamGuard on_upload(c10::cuda::CUDAStream(c10::cuda::CUDAStream::UNCHECKED, *stream));
  auto dev = torch::empty(shape, torch::TensorOptions().dtype(dtype).device(device));
  dev.copy_(host, /*non_blocking=*/true);
  return dev;
}

torch::Tensor gather_to(const torch::Tensor& src, const torch::Tensor& rows, const torch::Device& device,
                        const UploadStream& stream, std::vector<torch::Tensor>& held) {
  if (!stream) return torch::index_select(src, 0, rows).to(device);
  std::vector<int64_t> shape = src.sizes().vec();
  shape[0] = rows.size(0);
  auto host = torch::empty(shape, torch::TensorOptions().dtype(src.scalar_type()).pinned_memory(true));
  at::index_select_out(host, src, 0, rows);
  held.push_back(host);
  const c10::cuda::CUDAStreamGuard on_upload(c10::cuda::CUDAStream(c10::cuda::CUDAStream::UNCHECKED, *stream));
  auto dev = torch::empty(shape, torch::TensorOptions().dtype(src.scalar_type()).device(device));
  dev.copy_(host, /*non_blocking=*/true);
  return dev;
}

at::Generator sample_generator(uint64_t seed, int64_t step, int64_t sample_id) {
  const uint64_t s =
      splitmix64(splitmix64(splitmix64(seed) ^ static_cast<uint64_t>(step)) ^ static_cast<uint64_t>(sample_id));
  return at::make_generator<at::CPUGeneratorImpl>(s);
}

void Uploads::record(const UploadStream& stream) {
  if (!stream) return;
  ready = std::make_shared<at::cuda::CUDAEvent>();
  ready->record(c10::cuda::CUDAStream(c10::cuda::CUDAStream::UNCHECKED, *stream));
}

void Uploads::wait(const std::vector<torch::Tensor*>& device_tensors, const torch::Device& device) {
  if (!ready) return;
  const auto compute = c10::cuda::getCurrentCUDAStream(device.index());
  ready->block(compute);
  for (auto* t : device_tensors) t->record_stream(compute);
}

}  // namespace simu::training
