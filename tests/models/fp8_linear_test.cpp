// models/fp8_linear.h on the CPU: the row-wise e4m3 scaling against independent math (the row's
// largest magnitude lands on 448, every value on the e4m3 grid, round-trip error within half an e4m3
// step, zeros and NaN rows), the reference emulation of the FP8 product against float64 math, the
// autograd function's input gradient (fp8 and bf16 backward), the Linear hook (off = torch::linear
// bit for bit), and the device checks.
#include <cmath>

#include "models/fp8_linear.h"
#include "models/linear.h"
#include "test_util.h"

namespace sm = simu::models;

namespace {

// Rows of normal values whose magnitudes span 1e-3 .. 1e3 across rows: [rows, cols] float32.
torch::Tensor spread_rows(int64_t rows, int64_t cols, uint64_t seed) {
  torch::manual_seed(seed);
  auto mag = torch::pow(10.0, torch::linspace(-3, 3, rows)).unsqueeze(1);  // [rows, 1]
  return torch::randn({rows, cols}) * mag;
}

// True when |v| is an e4m3fn value: 0, a subnormal k * 2^-9 (k < 8), or a normal (1 + m/8) * 2^e,
// e in [-6, 8], |v| <= 448. Independent of torch's conversion.
bool on_e4m3_grid(double v) {
  const double a = std::fabs(v);
  if (a == 0) return true;
  if (a > 448) return false;
  if (a < std::ldexp(1.0, -6)) {
    const double k = a / std::ldexp(1.0, -9);
    return k == std::floor(k);
  }
  const int e = static_cast<int>(std::floor(std::log2(a)));
  const double m = (a / std::ldexp(1.0, e) - 1.0) * 8;
  return m == std::floor(m);
}

// Cosine similarity of two tensors, in float64.
double cosine(const torch::Tensor& a, const torch::Tensor& b) {
  auto x = a.to(torch::kFloat64).flatten(), y = b.to(torch::kFloat64).flatten();
  return (x.dot(y) / (x.norm() * y.norm())).item<double>();
}

}  // namespace

// The row's amax maps to +-448 exactly and the scale is amax / 448 (to one float rounding: it is
// computed as amax * (1/448)).
TEST(Fp8Linear, RowScaleMapsAmaxTo448) {
  auto v = spread_rows(16, 64, 1);
  auto r = sm::quantize_rows(v);
  ASSERT_EQ(r.q.scalar_type(), torch::kFloat8_e4m3fn);
  ASSERT_EQ(r.scale.sizes(), (std::vector<int64_t>{16, 1}));
  auto amax = v.abs().amax(1, true);
  // 1/448 rounded to fp32, then the product: 2 fp32 roundings.
  EXPECT_TRUE(torch::allclose(r.scale.to(torch::kFloat64), amax.to(torch::kFloat64) / 448.0, simu::testing::gamma(2), 0.0));
  EXPECT_TRUE(torch::equal(r.q.to(torch::kFloat32).abs().amax(1), torch::full({16}, 448.0f)));
}

// Every quantised value lies on the e4m3 grid, and the round trip is within half an e4m3 step:
// relative 2^-4 for normal values (3 mantissa bits), absolute 2^-10 * scale for subnormals.
TEST(Fp8Linear, RoundTripWithinHalfAStep) {
  auto v = spread_rows(12, 256, 2);
  auto r = sm::quantize_rows(v);
  auto q = r.q.to(torch::kFloat64).flatten();
  auto qa = q.accessor<double, 1>();
  for (int64_t i = 0; i < q.numel(); ++i) ASSERT_TRUE(on_e4m3_grid(qa[i])) << qa[i];
  auto back = sm::dequantize_rows(r).to(torch::kFloat64);
  auto v64 = v.to(torch::kFloat64), s64 = r.scale.to(torch::kFloat64).expand_as(v64);
  auto err = (back - v64).abs();
  auto normal = (v64.abs() / s64) >= std::ldexp(1.0, -6);
  auto bound = torch::where(normal, v64.abs() * std::ldexp(1.0, -4), s64 * std::ldexp(1.0, -10));
  // Plus the fp32 dequantisation q * scale: one rounding of |back| <= |v| (1 + 2^-4): 2u |v| covers it.
  EXPECT_TRUE((err <= bound + v64.abs() * (2 * simu::testing::kFp32Unit)).all().item<bool>())
      << ((err - bound).max().item<double>());
  // Not a no-op: e4m3 does round (some error is of the order of the bound).
  EXPECT_GT((err / (v64.abs() + 1e-30)).max().item<double>(), 1e-2);
}

// An all-zero row has scale 1 and zeros; a NaN row gives a NaN scale and a NaN output row, the other
// rows stay finite.
TEST(Fp8Linear, ZeroAndNanRows) {
  auto v = torch::randn({3, 32});
  v[0].zero_();
  v[2][5] = std::nan("");
  auto r = sm::quantize_rows(v);
  EXPECT_EQ(r.scale[0].item<float>(), 1.0f);
  EXPECT_TRUE(torch::equal(r.q[0].to(torch::kFloat32), torch::zeros({32})));
  EXPECT_TRUE(std::isnan(r.scale[2].item<float>()));
  auto w = sm::quantize_rows(torch::randn({16, 32}));
  auto y = sm::fp8_matmul(r, w, torch::Tensor(), true).to(torch::kFloat32);  // [3, 16]
  EXPECT_TRUE(torch::equal(y[0], torch::zeros({16})));
  EXPECT_TRUE(torch::isfinite(y[1]).all().item<bool>());
  EXPECT_TRUE(torch::isnan(y[2]).all().item<bool>());
}

// The CPU product is the emulation: sum_k (qa sa)(qb sb) + bias in fp32, rounded to bf16 (half a bf16
// step: 2^-8 relative at most with bf16's 8 significant bits, plus the fp32 accumulation's rounding).
TEST(Fp8Linear, EmulatedProductMatchesFloat64Math) {
  torch::manual_seed(3);
  auto a = sm::quantize_rows(torch::randn({37, 64}));
  auto b = sm::quantize_rows(torch::randn({48, 64}) * 0.1);
  auto bias = torch::randn({48});
  auto got = sm::fp8_matmul(a, b, bias, true);
  ASSERT_EQ(got.scalar_type(), torch::kBFloat16);
  auto a64 = a.q.to(torch::kFloat64) * a.scale.to(torch::kFloat64);
  auto b64 = b.q.to(torch::kFloat64) * b.scale.to(torch::kFloat64);
  auto want = torch::matmul(a64, b64.t()) + bias.to(torch::kFloat64);  // [37, 48]
  auto err = (got.to(torch::kFloat64) - want).abs();
  // fp32: the two dequantisations, 64 products and sums, the bias: gamma(67) of the terms' magnitudes;
  // then one bf16 rounding of the result.
  auto terms = torch::matmul(a64.abs(), b64.abs().t()) + bias.to(torch::kFloat64).abs();
  auto bound = want.abs() * simu::testing::kBf16Unit + terms * simu::testing::gamma(67) * (1 + simu::testing::kBf16Unit);
  EXPECT_TRUE((err <= bound).all().item<bool>()) << err.max().item<double>();
}

// fp8_linear: forward = the emulated product of the quantised input and weight; the input gradient
// through FP8 = quantised dY times the per-input-channel quantised W; through bf16 = dY W in bf16.
TEST(Fp8Linear, ForwardAndInputGradient) {
  torch::manual_seed(4);
  auto W = torch::randn({48, 32}) * 0.2, b = torch::randn({48});
  auto x = torch::randn({2, 5, 32}).requires_grad_(true);
  auto g = torch::randn({2, 5, 48});
  for (auto mode : {sm::Fp8Backward::kFp8, sm::Fp8Backward::kBf16}) {
    x.mutable_grad() = torch::Tensor();
    auto w = sm::make_fp8_weight(W, b, mode);
    auto y = sm::fp8_linear(x, *w);
    ASSERT_EQ(y.sizes(), (std::vector<int64_t>{2, 5, 48}));
    ASSERT_EQ(y.scalar_type(), torch::kFloat32);  // x's dtype outside autocast
    // (The FP8 weight keeps its bias in bf16, as _scaled_mm's epilogue takes it.)
    auto want = sm::fp8_matmul_reference(sm::quantize_rows(x.detach().reshape({10, 32})), sm::quantize_rows(W),
                                         b.to(torch::kBFloat16));
    EXPECT_TRUE(torch::equal(y.detach().reshape({10, 48}), want.to(torch::kBFloat16).to(torch::kFloat32)));
    y.backward(g);
    // dY reaches the function in bf16 (its output's dtype; the cast to float32 passes it back so).
    auto g2 = g.reshape({10, 48}).to(torch::kBFloat16);
    torch::Tensor dx;
    if (mode == sm::Fp8Backward::kFp8)
      dx = sm::fp8_matmul_reference(sm::quantize_rows(g2), sm::quantize_rows(W.t().contiguous()), torch::Tensor());
    else
      dx = torch::matmul(g2, W.to(torch::kBFloat16)).to(torch::kFloat32);
    // The same quantised operands; the two results differ by a bf16 rounding of each (2 u_bf16) and
    // two fp32 accumulations of 48 terms.
    const double tol = 2 * simu::testing::kBf16Unit + simu::testing::two_paths(48);
    EXPECT_TRUE(simu::testing::close(x.grad().reshape({10, 32}), dx, tol, sm::fp8_backward_name(mode)));
    // Within e4m3's rounding of the exact dY W (cosine, not bitwise): each operand within half a step
    // (2^-4 relative) gives a relative error e <= 2^-3 and cos >= 1 - e^2 / 2 = 0.992.
    EXPECT_GT(cosine(x.grad(), torch::matmul(g, W)), 0.99);
  }
  // No graph without a gradient to compute.
  torch::NoGradGuard ng;
  EXPECT_FALSE(sm::fp8_linear(x, *sm::make_fp8_weight(W, b, sm::Fp8Backward::kFp8)).requires_grad());
}

// Against the exact product an FP8 linear is close but not exact: relative Frobenius error of a few
// percent for Gaussian data (each operand rounded to 3 mantissa bits, RMS ~2^-4/sqrt(3) each).
TEST(Fp8Linear, CloseToExactProduct) {
  torch::manual_seed(5);
  auto W = torch::randn({64, 256}) / 16, x = torch::randn({128, 256});
  auto y = sm::fp8_linear(x, *sm::make_fp8_weight(W, torch::Tensor(), sm::Fp8Backward::kFp8));
  auto exact = torch::matmul(x, W.t());
  const double rel = ((y - exact).norm() / exact.norm()).item<double>();
  // Each operand's rounding error is uniform within half a step, 2^-3 m^-1 relative for a mantissa
  // m in [1, 2): RMS 2^-3 E[1/m] / sqrt(12) = 0.026; the product's ~0.037, and the Frobenius norm over
  // 8192 outputs of 256 terms stays within a few percent of that. Neither bound depends on the kernels
  // (the quantisation is exact arithmetic, the fp32 product's rounding is ~1e-5 of it).
  EXPECT_LT(rel, 0.06);
  EXPECT_GT(rel, 0.005);
}

// The Linear hook: with an FP8 weight forward is fp8_linear; without one, torch::linear bit for bit.
TEST(Fp8Linear, LinearHook) {
  torch::manual_seed(6);
  sm::Linear lin(32, 16);
  auto x = torch::randn({7, 32});
  auto plain = torch::linear(x, lin->weight, lin->bias);
  auto w = sm::make_fp8_weight(lin->weight, lin->bias, sm::Fp8Backward::kFp8);
  lin->set_fp8_weight(w);
  EXPECT_TRUE(torch::equal(lin->forward(x), sm::fp8_linear(x, *w)));
  EXPECT_FALSE(torch::equal(lin->forward(x), plain));
  lin->set_fp8_weight(nullptr);
  EXPECT_TRUE(torch::equal(lin->forward(x), plain));
}

// Device checks and names: no FP8 on the CPU (the error names the caller's key); unknown backward names.
TEST(Fp8Linear, DeviceAndNames) {
  EXPECT_FALSE(sm::fp8_supported(torch::kCPU));
  try {
    sm::require_fp8_device(torch::kCPU, "c.yaml: train.fp8_base");
    ADD_FAILURE() << "no error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("c.yaml: train.fp8_base"), std::string::npos) << e.what();
  }
  EXPECT_EQ(sm::parse_fp8_backward("bf16", "x"), sm::Fp8Backward::kBf16);
  EXPECT_EQ(sm::fp8_backward_name(sm::parse_fp8_backward("fp8", "x")), "fp8");
  EXPECT_THROW(sm::parse_fp8_backward("e5m2", "x"), simu::Error);
}
