#include "models/precision.h"

#include <ATen/autocast_mode.h>

#include "common/error.h"

namespace simu::models {

Precision default_inference_precision(const torch::Device& device) {
  return device.is_cuda() ? Precision::kFp16 : Precision::kFp32;
}

Precision parse_precision(const std::string& name, const torch::Device& device, const std::string& what) {
  if (name == "auto" || name.empty()) return default_inference_precision(device);
  if (name == "fp32" || name == "float32") return Precision::kFp32;
  if (name == "bf16" || name == "bfloat16") return Precision::kBf16;
  if (name == "fp16" || name == "float16") return Precision::kFp16;
  fail("{} '{}' is not a precision (expected fp16, bf16, fp32 or auto)", what, name);
}

std::string precision_name(Precision p) {
  switch (p) {
    case Precision::kFp32: return "fp32";
    case Precision::kBf16: return "bf16";
    case Precision::kFp16: return "fp16";
  }
  return "?";
}

torch::ScalarType precision_dtype(Precision p) {
  switch (p) {
    case Precision::kBf16: return torch::kBFloat16;
    case Precision::kFp16: return torch::kFloat16;
    case Precision::kFp32: break;
  }
  return torch::kFloat32;
}

void check_precision(Precision p, const torch::Device& device, const std::string& what) {
  if (p != Precision::kFp32 && !device.is_cuda())
    fail_hint("use fp32 on the CPU (the default there)", "{} {} needs a CUDA device; this run is on {}", what,
              precision_name(p), device.str());
}

Autocast::Autocast(Precision p, bool enable)
    : enabled_(enable && p != Precision::kFp32), fp32_(enable && p == Precision::kFp32) {
  if (!enabled_ && !fp32_) return;
  prev_enabled_ = at::autocast::is_autocast_enabled(at::kCUDA);
  prev_dtype_ = at::autocast::get_autocast_dtype(at::kCUDA);
  if (fp32_) {
    at::autocast::set_autocast_enabled(at::kCUDA, false);
    no_tf32_.emplace();
    auto& ctx = at::globalContext();
    prev_conv_ = ctx.float32Precision(at::Float32Backend::CUDA, at::Float32Op::CONV);
    ctx.setFloat32Precision(at::Float32Backend::CUDA, at::Float32Op::CONV, at::Float32Precision::IEEE);
    return;
  }
  at::autocast::set_autocast_enabled(at::kCUDA, true);
  at::autocast::set_autocast_dtype(at::kCUDA, precision_dtype(p));
  at::autocast::increment_nesting();
}

Autocast::~Autocast() {
  if (fp32_) {
    at::globalContext().setFloat32Precision(at::Float32Backend::CUDA, at::Float32Op::CONV, prev_conv_);
    no_tf32_.reset();
    at::autocast::set_autocast_enabled(at::kCUDA, prev_enabled_);
    return;
  }
  if (!enabled_) return;
  if (at::autocast::decrement_nesting() == 0) at::autocast::clear_cache();
  at::autocast::set_autocast_enabled(at::kCUDA, prev_enabled_);
  at::autocast::set_autocast_dtype(at::kCUDA, prev_dtype_);
}

}  // namespace simu::models
