#include "models/linear.h"

#include <ATen/autocast_mode.h>
#include <fmt/ranges.h>
#include <torch/cuda.h>

#include <cmath>

#include "common/error.h"

namespace simu::models {

namespace {
bool is_16bit(torch::ScalarType t) { return t == torch::kBFloat16 || t == torch::kHalf; }
const void* storage_of(const torch::Tensor& t) { return t.defined() ? t.data_ptr() : nullptr; }
int64_t version_of(const torch::Tensor& t) { return t.defined() ? t._version() : 0; }
}  // namespace

ComputeCopy::ComputeCopy(const torch::Tensor& weight, const torch::Tensor& bias, torch::ScalarType dtype) {
  SIMU_CHECK(is_16bit(dtype), "compute copy: the dtype must be bfloat16 or float16, got {}", c10::toString(dtype));
  SIMU_CHECK(weight.dim() == 2 && weight.scalar_type() == torch::kFloat32 &&
                 (!bias.defined() || (bias.dim() == 1 && bias.size(0) == weight.size(0) &&
                                      bias.scalar_type() == torch::kFloat32 && bias.device() == weight.device())),
             "compute copy: needs a float32 weight [out, in] and bias [out] on one device, got weight [{}] {}",
             fmt::join(weight.sizes(), ", "), c10::toString(weight.scalar_type()));
  // A plain tensor outside autograd (and outside inference mode, so that refresh may write it later).
  torch::NoGradGuard no_grad;
  c10::InferenceMode normal(false);
  w_ = weight.detach().to(dtype);
  if (bias.defined()) b_ = bias.detach().to(dtype);
  w_src_ = storage_of(weight);
  b_src_ = storage_of(bias);
  w_version_ = version_of(weight);
  b_version_ = version_of(bias);
}

bool ComputeCopy::fits(const torch::Tensor& weight, const torch::Tensor& bias) const {
  return weight.defined() && storage_of(weight) == w_src_ && storage_of(bias) == b_src_ && weight.device() == w_.device() &&
         weight.sizes() == w_.sizes() && weight.scalar_type() == torch::kFloat32 &&
         (!bias.defined() || (bias.sizes() == b_.sizes() && bias.scalar_type() == torch::kFloat32));
}

bool ComputeCopy::refresh(const torch::Tensor& weight, const torch::Tensor& bias) {
  const int64_t wv = version_of(weight), bv = version_of(bias);
  if (wv == w_version_ && bv == b_version_) return false;
  torch::NoGradGuard no_grad;
  w_.copy_(weight.detach());
  if (bias.defined()) b_.copy_(bias.detach());
  w_version_ = wv;
  b_version_ = bv;
  return true;
}

int64_t ComputeCopy::bytes() const {
  return w_.numel() * w_.element_size() + (b_.defined() ? b_.numel() * b_.element_size() : 0);
}

LinearImpl::LinearImpl(int64_t in, int64_t out, bool with_bias) : in_features(in), out_features(out) {
  // torch.nn.Linear's default initialisation (kaiming_uniform a=sqrt(5), bias U(-1/sqrt(in), 1/sqrt(in))).
  weight = register_parameter("weight", torch::empty({out, in}));
  torch::nn::init::kaiming_uniform_(weight, std::sqrt(5.0));
  if (with_bias) {
    const double bound = in > 0 ? 1.0 / std::sqrt(static_cast<double>(in)) : 0.0;
    bias = register_parameter("bias", torch::empty({out}).uniform_(-bound, bound));
  }
}

void LinearImpl::set_compute_copy(c10::optional<torch::ScalarType> dtype) {
  SIMU_CHECK(!dtype || is_16bit(*dtype), "Linear compute copy: the dtype must be bfloat16 or float16, got {}",
             c10::toString(*dtype));
  if (dtype != compute_dtype_ && compute_) {
    // A CUDA copy may have been read on another stream than the one that allocated it (the pose stream's
    // side stream, a graph's replay stream): let its readers finish before the allocator may hand the
    // memory out again (CUDA graphs that read it hold it, and it is not freed here then).
    if (compute_.use_count() == 1 && compute_->weight().is_cuda()) torch::cuda::synchronize(compute_->weight().device().index());
    compute_.reset();
  }
  compute_dtype_ = dtype;
}

std::pair<torch::Tensor, torch::Tensor> LinearImpl::product_weights(const torch::Tensor& x) {
  if (!compute_dtype_) return {weight, bias};
  // Where autocast would cast weight/bias to the copy's dtype: autocast on for x's device in that
  // dtype, fp32 weight/bias on x's device, and no gradient wanted for them.
  const auto dev = x.device().type();
  const bool applies = at::autocast::is_autocast_enabled(dev) && at::autocast::get_autocast_dtype(dev) == *compute_dtype_ &&
                       weight.scalar_type() == torch::kFloat32 && weight.device() == x.device() &&
                       (!bias.defined() || bias.scalar_type() == torch::kFloat32) &&
                       !(at::GradMode::is_enabled() && (weight.requires_grad() || (bias.defined() && bias.requires_grad())));
  if (!applies) return {weight, bias};
  if (!compute_ || !compute_->fits(weight, bias)) compute_ = std::make_shared<ComputeCopy>(weight, bias, *compute_dtype_);
  else compute_->refresh(weight, bias);
  return {compute_->weight(), compute_->bias()};
}

torch::Tensor LinearImpl::forward(const torch::Tensor& x) {
  if (fp8_) {
    auto y = fp8_linear(x, *fp8_);
    return adapter_ && adapter_enabled_ ? adapter_->add_to(y, x) : y;
  }
  // Under autocast the 16-bit copy passes through unchanged and x is cast as before.
  const auto [w, b] = product_weights(x);
  if (adapter_ && adapter_enabled_) {
    auto y = adapter_->forward_with_base(x, w, b);  // a fused adapter's whole layer, where it has one
    if (y.defined()) return y;
  }
  auto y = torch::linear(x, w, b);
  if (adapter_ && adapter_enabled_) y = adapter_->add_to(y, x);
  return y;
}

int set_compute_copies(torch::nn::Module& root, c10::optional<torch::ScalarType> dtype, bool frozen_only) {
  // (modules(include_self) would need root to be held by a shared_ptr.)
  std::vector<torch::nn::Module*> all{&root};
  for (const auto& m : root.modules(/*include_self=*/false)) all.push_back(m.get());
  int n = 0;
  for (auto* m : all) {
    auto* linear = dynamic_cast<LinearImpl*>(m);
    if (!linear) continue;
    const bool frozen = !linear->weight.requires_grad() && !(linear->bias.defined() && linear->bias.requires_grad());
    if (dtype && frozen_only && !frozen) continue;
    linear->set_compute_copy(dtype);
    ++n;
  }
  return n;
}

}  // namespace simu::models
