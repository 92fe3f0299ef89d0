#include "models/linear.h"

#include <cmath>

namespace simu::models {

LinearImpl::LinearImpl(int64_t in, int64_t out, bool with_bias) : in_features(in), out_features(out) {
  // torch.nn.Linear's default initialisation (kaiming_uniform a=sqrt(5), bias U(-1/sqrt(in), 1/sqrt(in))).
  weight = register_parameter("weight", torch::empty({out, in}));
  torch::nn::init::kaiming_uniform_(weight, std::sqrt(5.0));
  if (with_bias) {
    const double bound = in > 0 ? 1.0 / std::sqrt(static_cast<double>(in)) : 0.0;
    bias = register_parameter("bias", torch::empty({out}).uniform_(-bound, bound));
  }
}

torch::Tensor LinearImpl::forward(const torch::Tensor& x) {
  if (fp8_) {
    auto y = fp8_linear(x, *fp8_);
    return adapter_ && adapter_enabled_ ? adapter_->add_to(y, x) : y;
  }
  if (adapter_ && adapter_enabled_) {
    auto y = adapter_->forward_with_base(x, weight, bias);  // a fused adapter's whole layer, where it has one
    if (y.defined()) return y;
  }
  auto y = torch::linear(x, weight, bias);
  if (adapter_ && adapter_enabled_) y = adapter_->add_to(y, x);
  return y;
}

}  // namespace simu::models
