// Inference precision of the Stage-1 models (condition embedder, flow model, decoder).
//
// The released pipeline.yaml runs Stage 1 under CUDA float16 autocast (`dtype: float16`); training
// (train_fmdpo) uses bf16 autocast, the paper's recipe. On the CPU everything runs in float32.
//   fp32: no autocast;  bf16 / fp16: CUDA autocast with that dtype (matmuls, convolutions and
//   attention in the low precision, LayerNorm / softmax reductions in fp32 as autocast does).
// The fused CUDA kernels of the flow model (fused_ops.h) store bf16 or fp16: they run under either
// autocast (flow_model.cpp `fused_path`); set_fused_kernels(false) gives the plain ATen reference path.
#pragma once

#include <torch/torch.h>

#include <optional>
#include <string>

namespace simu::models {

enum class Precision { kFp32, kBf16, kFp16 };

// "fp32" | "bf16" | "fp16" (also "float32", "bfloat16", "float16"); "auto" gives the inference default
// for `device`. Anything else: an error naming `what` (e.g. "--precision") and the accepted values.
Precision parse_precision(const std::string& name, const torch::Device& device, const std::string& what = "precision");
std::string precision_name(Precision p);
// Inference default: fp16 on CUDA (the released pipeline), fp32 on the CPU.
Precision default_inference_precision(const torch::Device& device);
// The autocast dtype of p (kFloat32 for fp32).
torch::ScalarType precision_dtype(Precision p);
// Checks that p can run on device (bf16/fp16 need CUDA); error naming `what` otherwise.
void check_precision(Precision p, const torch::Device& device, const std::string& what = "precision");

// CUDA autocast with p's dtype for its lifetime (no-op when `enable` is false); restores the previous
// state after; scopes nest. fp32 means IEEE float32: autocast off inside the scope (also within an outer bf16/fp16 scope), and no TF32 in cuBLAS matmuls
// (at::NoTF32Guard) nor in cuDNN convolutions (PyTorch's default allows TF32 there, which put the
// decoder 8e-4 away from the fp32 fixture on an H100).
class Autocast {
 public:
  explicit Autocast(Precision p, bool enable = true);
  ~Autocast();
  Autocast(const Autocast&) = delete;
  Autocast& operator=(const Autocast&) = delete;

 private:
  bool enabled_ = false;  // a low-precision autocast scope is open
  bool fp32_ = false;     // an IEEE-fp32 scope is open
  bool prev_enabled_ = false;
  at::ScalarType prev_dtype_ = at::kBFloat16;
  at::Float32Precision prev_conv_ = at::Float32Precision::NONE;
  std::optional<at::NoTF32Guard> no_tf32_;
};

}  // namespace simu::models
