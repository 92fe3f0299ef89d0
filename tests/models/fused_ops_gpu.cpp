// The flow model's fused CUDA kernels against their plain-ATen references, and the whole forward with
// and without them, in both 16-bit storage types: bf16 (bf16 autocast, training) and fp16 (fp16
// autocast, the released inference precision). Tolerances: one rounding of the same fp32 value to the
// storage type on both sides, i.e. one unit in the last place of the largest value: 1/128 for bf16
// (8 significant bits), 1/1024 for fp16 (11 bits); we allow that ulp, measured max rel errors are
// printed by the tests that compare whole forwards.
#include <ATen/CPUGeneratorImpl.h>

#include <fstream>

#include <fmt/format.h>

#include "models/flow_model.h"
#include "models/fused_ops.h"
#include "models/generator.h"
#include "models/precision.h"
#include "flow_mid_config.h"
#include "test_util.h"

namespace {
// max |a - b| / max |b| over float copies.
double rel(const torch::Tensor& a, const torch::Tensor& b) {
  auto fa = a.to(torch::kFloat32).cpu(), fb = b.to(torch::kFloat32).cpu();
  return (fa - fb).abs().max().item<double>() / std::max(fb.abs().max().item<double>(), 1e-30);
}
// The two storage types of the kernels, and one unit in the last place at 1 for each.
const std::vector<torch::ScalarType> kLow = {torch::kBFloat16, torch::kHalf};
double ulp(torch::ScalarType t) { return t == torch::kHalf ? 1.0 / 1024 : 1.0 / 128; }
const char* name(torch::ScalarType t) { return t == torch::kHalf ? "fp16" : "bf16"; }
}  // namespace

TEST(FusedOpsGpu, LayerNormAffineMatchesReference) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled()) << "built without nvcc: no fused kernels to test";
  torch::manual_seed(1);
  const auto f32 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat32);
  for (const auto dt : kLow)
  for (const int64_t C : {256, 1024}) {
    // Residual-stream-like input (offset and spread) with per-batch and shared affine rows.
    auto x = torch::randn({2, 1031, C}, f32) * 3 + 0.5;
    for (const int64_t G : {1, 2}) {
      auto w = 1 + 0.1 * torch::randn({G, C}, f32), b = torch::randn({G, C}, f32);
      const auto before = simu::models::fused::launch_count();
      auto got = simu::models::fused::layer_norm_affine_bf16(x, w, b, 1e-6, dt);
      EXPECT_EQ(simu::models::fused::launch_count(), before + 1);
      auto want = simu::models::fused::layer_norm_affine_bf16_reference(x, w, b, 1e-6, dt);
      ASSERT_EQ(got.scalar_type(), dt);
      ASSERT_EQ(want.scalar_type(), dt);
      // One rounding of the same fp32 value on both sides: at most one ulp apart.
      EXPECT_LE(rel(got, want), ulp(dt)) << name(dt) << " C " << C << " G " << G;
      EXPECT_LT((got.to(torch::kFloat32) - want.to(torch::kFloat32)).abs().mean().item<double>(), 1e-3);
      // Independent: fp64 LayerNorm + affine, within the storage type's rounding.
      auto x64 = x.to(torch::kFloat64);
      auto m = x64.mean(-1, true), v = (x64 - m).pow(2).mean(-1, true);
      auto y64 = (x64 - m) / (v + 1e-6).sqrt() * w.to(torch::kFloat64).unsqueeze(1) + b.to(torch::kFloat64).unsqueeze(1);
      EXPECT_LE(rel(got, y64), ulp(dt)) << name(dt);
      // Without bias.
      EXPECT_LE(rel(simu::models::fused::layer_norm_affine_bf16(x, w, {}, 1e-6, dt),
                    simu::models::fused::layer_norm_affine_bf16_reference(x, w, {}, 1e-6, dt)), ulp(dt));
    }
  }
}

TEST(FusedOpsGpu, ResidualLayerNormAffineMatchesReference) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  torch::manual_seed(4);
  const auto f32 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat32);
  const int64_t B = 2, L = 517, C = 1024;
  auto x = torch::randn({B, L, C}, f32) * 3 + 0.5;
  for (const auto dt : kLow)
  for (const int64_t G : {1, 2}) {
    auto h = torch::randn({B, L, C}, f32).to(dt);
    auto w = 1 + 0.1 * torch::randn({G, C}, f32), b = torch::randn({G, C}, f32);
    // Gates as the modulation gives them (bf16 under autocast), per batch row or shared; and no gate.
    for (const auto& gate : {(0.3 * torch::randn({G, C}, f32)).to(dt), torch::Tensor()}) {
      const auto before = simu::models::fused::launch_count();
      auto [x_new, y] = simu::models::fused::residual_layer_norm_affine_bf16(x, h, gate, w, b, 1e-6);
      EXPECT_EQ(simu::models::fused::launch_count(), before + 1);
      auto [x_ref, y_ref] = simu::models::fused::residual_layer_norm_affine_bf16_reference(x, h, gate, w, b, 1e-6);
      ASSERT_EQ(x_new.scalar_type(), torch::kFloat32);
      ASSERT_EQ(y.scalar_type(), dt);
      ASSERT_EQ(y_ref.scalar_type(), dt);
      // The fp32 residual: the same two operations (at most a fused multiply-add's rounding apart).
      EXPECT_LE(rel(x_new, x_ref), 1e-6) << name(dt) << " G " << G << " gated " << gate.defined();
      // Independent check of the residual itself against fp64 math.
      auto want64 = x.to(torch::kFloat64) + h.to(torch::kFloat64) * (gate.defined() ? gate.to(torch::kFloat64).unsqueeze(1) : torch::ones({1}, f32.dtype(torch::kFloat64)));
      EXPECT_LE(rel(x_new.to(torch::kFloat64), want64), 1e-6);
      EXPECT_LE(rel(y, y_ref), ulp(dt)) << name(dt);
      EXPECT_LT((y.to(torch::kFloat32) - y_ref.to(torch::kFloat32)).abs().mean().item<double>(), 1e-3);
    }
  }
}

// The residual kernel with CFG's zero-condition rows as one broadcast row (tail): the same bits as the
// kernel on the concatenated sublayer output, for 1 of 2 and 1 of 3 rows attended, shared or per-row
// gates and none; no gradient allowed; the unsupported cases say so.
TEST(FusedOpsGpu, ResidualLayerNormAffineTailMatchesConcatenation) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  torch::manual_seed(6);
  const auto f32 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat32);
  const int64_t L = 517, C = 1024;
  for (const auto dt : kLow)
    for (const int64_t B : {2, 3}) {
      auto x = torch::randn({B, L, C}, f32) * 3 + 0.5;
      auto head = torch::randn({1, L, C}, f32).to(dt);  // the attended (conditional) row
      auto tail = torch::randn({1, 1, C}, f32).to(dt);  // the zero-condition rows' output
      auto full = torch::cat({head, tail.expand({B - 1, L, C})}, 0).contiguous();
      auto w = 1 + 0.1 * torch::randn({1, C}, f32), b = torch::randn({1, C}, f32);
      for (const auto& gate : {(0.3 * torch::randn({B, C}, f32)).to(dt), (0.3 * torch::randn({1, C}, f32)).to(dt), torch::Tensor()}) {
        ASSERT_TRUE(simu::models::fused::supports_residual_layer_norm_affine_tail(x, head, tail));
        const auto before = simu::models::fused::launch_count();
        auto [x_new, y] = simu::models::fused::residual_layer_norm_affine_tail_bf16(x, head, tail, gate, w, b, 1e-6);
        EXPECT_EQ(simu::models::fused::launch_count(), before + 1);
        auto [x_want, y_want] = simu::models::fused::residual_layer_norm_affine_bf16(x, full, gate, w, b, 1e-6);
        const auto what = fmt::format("{} B {} gate {}", name(dt), B, gate.defined() ? gate.size(0) : 0);
        EXPECT_TRUE(torch::equal(x_new, x_want)) << what;
        EXPECT_TRUE(torch::equal(y, y_want)) << what;
        // Independent check of a zero-condition row's residual: x + tail * gate in fp64.
        auto g64 = gate.defined() ? gate.to(torch::kFloat64).select(0, gate.size(0) - 1) : torch::ones({C}, f32.dtype(torch::kFloat64));
        auto want_last = x.select(0, B - 1).to(torch::kFloat64) + tail.reshape({1, C}).to(torch::kFloat64) * g64;
        EXPECT_LE(rel(x_new.select(0, B - 1).to(torch::kFloat64), want_last), 1e-6) << what;
      }
      // Not supported: a tail of another length or dtype; a head with more rows than x.
      EXPECT_FALSE(simu::models::fused::supports_residual_layer_norm_affine_tail(x, head, tail.narrow(2, 0, C / 2)));
      EXPECT_FALSE(simu::models::fused::supports_residual_layer_norm_affine_tail(x, head, tail.to(torch::kFloat32)));
      EXPECT_FALSE(simu::models::fused::supports_residual_layer_norm_affine_tail(
          x.narrow(0, 0, 1).contiguous(), torch::cat({head, head}, 0), tail));
      // Inference only: an input that requires a gradient is refused with the function's name.
      auto xg = x.clone().requires_grad_(true);
      try {
        (void)simu::models::fused::residual_layer_norm_affine_tail_bf16(xg, head, tail, torch::Tensor(), w, b, 1e-6);
        ADD_FAILURE() << "no error for an input that requires a gradient";
      } catch (const std::exception& e) {
        EXPECT_NE(std::string(e.what()).find("residual_layer_norm_affine_tail_bf16"), std::string::npos) << e.what();
      }
    }
}

namespace {
// The split shapes the tests run: (B, L, H, D). The real stream's 16 heads of 64 at 4,096 + 4 tokens, batch 2
// and 1 (B*L*H a multiple of the 16-byte kernel's 4 heads per warp); odd item counts B*L*H, so that the last
// warp of the 16-byte kernel has lanes past the end (2,585 heads of 64: 4 per warp; 231 of 128: 2 per warp);
// and heads of 256 (one per warp).
struct SplitShape {
  int64_t B, L, H, D;
};
const std::vector<SplitShape> kSplitShapes = {{2, 4100, 16, 64}, {1, 4100, 16, 64}, {1, 517, 5, 64}, {1, 77, 3, 128},
                                              {2, 33, 3, 256}};
std::string split_name(torch::ScalarType dt, const SplitShape& s) {
  return fmt::format("{} B {} L {} H {} D {}", name(dt), s.B, s.L, s.H, s.D);
}

// One split case against the ATen reference: q into a new tensor, k and v into a larger key/value buffer at
// an offset of `extra` tokens (as the pose tokens come first), through the kernel `wide` says (checked with
// the 16-byte launch counter). Returns q for comparing the two kernels.
torch::Tensor check_split(torch::ScalarType dt, const SplitShape& s, int64_t extra, bool wide) {
  const auto opt = torch::TensorOptions().device(torch::kCUDA).dtype(dt);
  const auto f32 = opt.dtype(torch::kFloat32);
  auto qkv = (torch::randn({s.B, s.L, 3, s.H, s.D}, f32) * 4).to(dt);
  qkv.select(1, 3).select(1, 0).select(1, 0).zero_();  // a zero query (token 3, head 0): the clamp keeps it zero
  auto gq = 1 + 0.2 * torch::randn({s.H, s.D}, f32), gk = torch::randn({s.H, s.D}, f32);
  auto k_buf = torch::zeros({s.B, s.L + extra, s.H, s.D}, opt), v_buf = torch::zeros({s.B, s.L + extra, s.H, s.D}, opt);
  auto q = torch::empty({s.B, s.L, s.H, s.D}, opt);
  const auto n0 = simu::models::fused::launch_count(), w0 = simu::models::fused::split_qkv_wide_launch_count();
  simu::models::fused::split_qkv_rms_norm(qkv, gq, gk, 8.0, q, k_buf.narrow(1, extra, s.L), v_buf.narrow(1, extra, s.L));
  EXPECT_EQ(simu::models::fused::launch_count(), n0 + 1);
  EXPECT_EQ(simu::models::fused::split_qkv_wide_launch_count(), w0 + (wide ? 1 : 0)) << "wide path expected: " << wide;
  auto q_ref = torch::empty_like(q), k_ref = torch::empty_like(q), v_ref = torch::empty_like(q);
  simu::models::fused::split_qkv_rms_norm_reference(qkv, gq, gk, 8.0, q_ref, k_ref, v_ref);
  EXPECT_LE(rel(q, q_ref), ulp(dt));
  EXPECT_LE(rel(k_buf.narrow(1, extra, s.L), k_ref), ulp(dt));
  EXPECT_TRUE(torch::equal(v_buf.narrow(1, extra, s.L), v_ref));
  EXPECT_EQ(q.select(1, 3).select(1, 0).abs().max().item<float>(), 0.f);
  // The buffer outside the written slice is untouched.
  if (extra > 0) EXPECT_EQ(k_buf.narrow(1, 0, extra).abs().max().item<float>(), 0.f);
  if (extra > 0) EXPECT_EQ(v_buf.narrow(1, 0, extra).abs().max().item<float>(), 0.f);
  // Independent check of the norm: with gamma = 1, |q| = scale (8) for every nonzero query.
  auto ones = torch::ones({s.H, s.D}, f32);
  auto q1 = torch::empty_like(q);
  simu::models::fused::split_qkv_rms_norm(qkv, ones, ones, 8.0, q1, k_ref, v_ref);
  auto norms = q1.to(torch::kFloat32).norm(2, {-1});  // [B, L, H]
  norms.select(1, 3).select(1, 0).fill_(8.0);           // the zero query
  EXPECT_LT((norms - 8.0).abs().max().item<double>(), 8.0 * 0.01);
  return q;
}
}  // namespace

// The split kernels against the ATen reference in both storage types, batch 1 and 2, head dims 64 / 128 /
// 256 and item counts that leave the 16-byte kernel's last warp partly empty. Paths: the 16-byte kernel
// (aligned outputs, k/v at a 16-byte aligned token offset), the 4-byte one forced (set_split_qkv_wide(false))
// and taken by itself for an output at a 4-byte (not 16-byte) aligned offset; the two kernels agree.
TEST(FusedOpsGpu, SplitQkvRmsNormMatchesReference) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  ASSERT_TRUE(simu::models::fused::split_qkv_wide()) << "the 16-byte split kernels are on by default";
  for (const auto dt : kLow)
  for (const auto& s : kSplitShapes) {
    SCOPED_TRACE(split_name(dt, s));
    // The same inputs (seed) through both kernels: one rounding of fp32 values that differ only in the
    // summation order of the norms, so at most one ulp apart.
    torch::manual_seed(2);
    auto q_wide = check_split(dt, s, 4, true);
    simu::models::fused::set_split_qkv_wide(false);
    torch::manual_seed(2);
    auto q_narrow = check_split(dt, s, 4, false);
    simu::models::fused::set_split_qkv_wide(true);
    EXPECT_LE(rel(q_wide, q_narrow), ulp(dt));
    // No offset: k and v start the buffer.
    torch::manual_seed(3);
    (void)check_split(dt, s, 0, true);
  }
  // An output 4-byte but not 16-byte aligned (2 elements into its buffer): the 4-byte kernel.
  torch::manual_seed(4);
  const int64_t B = 2, L = 517, H = 16, D = 64;
  for (const auto dt : kLow) {
    SCOPED_TRACE(name(dt));
    const auto opt = torch::TensorOptions().device(torch::kCUDA).dtype(dt);
    auto qkv = (torch::randn({B, L, 3, H, D}, opt.dtype(torch::kFloat32)) * 4).to(dt);
    auto gq = 1 + 0.2 * torch::randn({H, D}, opt.dtype(torch::kFloat32)), gk = torch::randn({H, D}, opt.dtype(torch::kFloat32));
    auto q = torch::empty({B * L * H * D + 2}, opt).narrow(0, 2, B * L * H * D).view({B, L, H, D});
    auto k = torch::empty_like(q), v = torch::empty_like(q);  // aligned: one unaligned output is enough
    const auto w0 = simu::models::fused::split_qkv_wide_launch_count();
    simu::models::fused::split_qkv_rms_norm(qkv, gq, gk, 8.0, q, k, v);
    EXPECT_EQ(simu::models::fused::split_qkv_wide_launch_count(), w0) << "an unaligned output takes the 4-byte kernel";
    auto q_ref = torch::empty_like(k), k_ref = torch::empty_like(k), v_ref = torch::empty_like(k);
    simu::models::fused::split_qkv_rms_norm_reference(qkv, gq, gk, 8.0, q_ref, k_ref, v_ref);
    EXPECT_LE(rel(q, q_ref), ulp(dt));
    EXPECT_LE(rel(k, k_ref), ulp(dt));
    EXPECT_TRUE(torch::equal(v, v_ref));
    // A gamma view 4 bytes into its buffer: copied aligned, the 16-byte kernel, the same numbers.
    auto gq_off = torch::empty({H * D + 1}, gq.options()).narrow(0, 1, H * D).view({H, D}).copy_(gq);
    auto q_al = torch::empty_like(k), q_goff = torch::empty_like(k);
    const auto w1 = simu::models::fused::split_qkv_wide_launch_count();
    simu::models::fused::split_qkv_rms_norm(qkv, gq, gk, 8.0, q_al, k_ref, v_ref);
    simu::models::fused::split_qkv_rms_norm(qkv, gq_off, gk, 8.0, q_goff, k_ref, v_ref);
    EXPECT_EQ(simu::models::fused::split_qkv_wide_launch_count(), w1 + 2);
    EXPECT_TRUE(torch::equal(q_al, q_goff));
    // An output at an odd element offset cannot take either kernel: an error naming it.
    auto q_odd = torch::empty({B * L * H * D + 1}, opt).narrow(0, 1, B * L * H * D).view({B, L, H, D});
    EXPECT_THROW(simu::models::fused::split_qkv_rms_norm(qkv, gq, gk, 8.0, q_odd, k, v), simu::Error);
  }
}

TEST(FusedOpsGpu, LinearGeluMatchesReference) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  torch::manual_seed(3);
  const auto f32 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat32);
  auto w = torch::randn({1024, 256}, f32) / 16, b = torch::randn({1024}, f32);
  for (const auto dt : kLow)
  for (const bool autocast : {false, true}) {
    auto x = torch::randn({2, 301, 256}, f32).to(dt);
    simu::models::Autocast ac(dt == torch::kHalf ? simu::models::Precision::kFp16 : simu::models::Precision::kBf16, autocast);
    auto got = simu::models::fused::linear_gelu_tanh_bf16(x, w, b);
    auto want = simu::models::fused::linear_gelu_tanh_bf16_reference(x, w, b);
    ASSERT_EQ(got.sizes(), want.sizes());
    ASSERT_EQ(got.scalar_type(), dt);
    ASSERT_EQ(want.scalar_type(), dt);
    // The epilogue applies GELU before rounding, the reference after: about one ulp (two allowed).
    EXPECT_LE(rel(got, want), 2 * ulp(dt)) << name(dt) << " autocast " << autocast;
    // Independent: tanh-GELU of the fp32 product of the rounded operands.
    auto y = torch::matmul(x.to(torch::kFloat32), w.to(dt).to(torch::kFloat32).t()) + b.to(dt).to(torch::kFloat32);
    auto g = 0.5 * y * (1 + torch::tanh(std::sqrt(2.0 / M_PI) * (y + 0.044715 * y.pow(3))));
    EXPECT_LE(rel(got, g), 2 * ulp(dt)) << name(dt);
  }
}

// The block's modulation rows from one kernel equal, bit for bit, what the block computed with ATen
// before: (1 + scale) on the modulation's dtype then .to(float32), shift and gates .to(float32), for
// bf16 / fp16 (autocast) and fp32 (share_mod) modulations of one row (sampling) and two (training).
TEST(FusedOpsGpu, ModulationRowsMatchAtenBitwise) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  torch::manual_seed(8);
  const int64_t C = 1024;
  for (const auto dt : {torch::kBFloat16, torch::kHalf, torch::kFloat32})
  for (const int64_t G : {1, 2}) {
    // Values around -1 (where 1 + scale loses bits), tiny and large ones.
    auto m32 = torch::randn({G, 6 * C}, torch::TensorOptions().device(torch::kCUDA)) * 2 - 1;
    m32.narrow(1, 0, 64).mul_(1e-4);
    m32.narrow(1, C, 64).fill_(-1).add_(torch::randn({G, 64}, m32.options()) * 1e-3);
    m32.narrow(1, 4 * C, 64).mul_(300);
    auto m = m32.to(dt);  // [G, 6C], as ada_linear returns it
    torch::NoGradGuard ng;
    const auto n0 = simu::models::fused::modulation_launch_count();
    auto rows = simu::models::fused::modulation_rows(m);
    EXPECT_EQ(simu::models::fused::modulation_launch_count(), n0 + 1);
    ASSERT_EQ(rows.sizes(), (std::vector<int64_t>{6, G, C}));
    ASSERT_EQ(rows.scalar_type(), torch::kFloat32);
    // The block's former expressions on [G, 1, C] chunks.
    std::vector<torch::Tensor> chunks;
    for (const auto& c : m.chunk(6, 1)) chunks.push_back(c.unsqueeze(1));
    for (int k = 0; k < 6; ++k) {
      auto want = (k == 1 || k == 4 ? (1 + chunks[k]) : chunks[k]).squeeze(1).to(torch::kFloat32);
      EXPECT_TRUE(torch::equal(rows[k], want)) << c10::toString(dt) << " G " << G << " row " << k;
    }
    EXPECT_TRUE(torch::equal(rows, simu::models::fused::modulation_rows_reference(m)));
  }
  // A modulation that requires a gradient under grad mode: the differentiable reference, no kernel.
  auto m = torch::randn({2, 6 * C}, torch::TensorOptions().device(torch::kCUDA)).to(torch::kBFloat16).requires_grad_();
  const auto n0 = simu::models::fused::modulation_launch_count();
  auto rows = simu::models::fused::modulation_rows(m);
  EXPECT_EQ(simu::models::fused::modulation_launch_count(), n0);
  rows.sum().backward();
  ASSERT_TRUE(m.grad().defined());
  EXPECT_TRUE(torch::equal(m.grad(), torch::ones_like(m)));
}

TEST(FusedOpsGpu, FlowForwardWithFusedKernelsMatchesReference) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  const torch::Device dev(torch::kCUDA);
  // A mid-size model the kernels support (tests/flow_mid_config.h).
  const auto path = simu::testing::mid_flow_config("fused_flow");
  // Seeded random weights: LibTorch seeds its default generators at random per process, so an
  // unseeded model differs from run to run (one such run failed a tolerance here, 2026-11-26).
  torch::manual_seed(15);
  auto gen = simu::models::load_generator(path, "", dev);
  auto rng = at::make_generator<at::CPUGeneratorImpl>(5);
  auto x = gen->noise(2, rng, dev);
  auto cond = torch::randn({2, 77, gen->config().backbone.cond_channels}, rng).to(dev);
  auto t = torch::full({1}, 400.0, torch::TensorOptions().device(dev));
  c10::optional<torch::Tensor> d = torch::zeros({1}, torch::TensorOptions().device(dev));
  torch::NoGradGuard ng;
  simu::models::Autocast ac(simu::models::Precision::kBf16);
  gen->backbone()->set_fused_kernels(false);
  const auto n0 = simu::models::fused::launch_count();
  const auto m0 = simu::models::fused::modulation_launch_count();
  auto want = gen->backbone()->forward(x, t, cond, d);
  EXPECT_EQ(simu::models::fused::launch_count(), n0) << "fused kernels ran although switched off";
  EXPECT_EQ(simu::models::fused::modulation_launch_count(), m0);
  gen->backbone()->set_fused_kernels(true);
  auto got = gen->backbone()->forward(x, t, cond, d);
  // 3 blocks x 2 streams x (3 norms, two of them with the residual in front, + 1 qkv split + 1
  // fc1-GELU) launches, and one modulation kernel per block.
  EXPECT_EQ(simu::models::fused::launch_count(), n0 + 3 * 2 * 5);
  EXPECT_EQ(simu::models::fused::modulation_launch_count(), m0 + 3);
  for (const auto& [k, v] : want) EXPECT_LE(rel(got.at(k), v), 2e-2) << k;
  // The pose stream on a second CUDA stream (the default) or on the same one. With the flash kernel for
  // its few-query attention on the side stream as on the main one, the same kernels on the same inputs:
  // the same numbers, with the side stream joined once after the last block (the default, lagged) or
  // at every block.
  ASSERT_TRUE(gen->backbone()->stream_lag());
  gen->backbone()->set_side_few_query_flash(true);
  auto overlapped = gen->backbone()->forward(x, t, cond, d);
  gen->backbone()->set_stream_overlap(false);
  auto serial = gen->backbone()->forward(x, t, cond, d);
  gen->backbone()->set_stream_overlap(true);
  for (const auto& [k, v] : serial) EXPECT_TRUE(torch::equal(overlapped.at(k), v)) << k;
  gen->backbone()->set_stream_lag(false);
  auto joined = gen->backbone()->forward(x, t, cond, d);
  gen->backbone()->set_stream_lag(true);
  for (const auto& [k, v] : serial) EXPECT_TRUE(torch::equal(joined.at(k), v)) << "joined per block " << k;
  gen->backbone()->set_side_few_query_flash(false);
  // The default (PyTorch's kernel for the side stream's few-query attention): the same attention up
  // to the kernel's rounding, the shape stream untouched.
  for (const auto& [k, v] : serial) {
    const double e = rel(got.at(k), v);
    EXPECT_LE(e, 2e-2) << "side few-query kernel " << k;
    if (k == "shape") EXPECT_TRUE(torch::equal(got.at(k), v)) << "the shape stream never reads the pose stream";
  }
  // Lagged and joined with the condition cache (sampling): the same numbers.
  {
    auto kv_cache = gen->backbone()->condition_cache(cond);
    gen->backbone()->set_stream_lag(false);
    auto joined_cached = gen->backbone()->forward(x, t, cond, d, &kv_cache);
    gen->backbone()->set_stream_lag(true);
    auto lagged_cached = gen->backbone()->forward(x, t, cond, d, &kv_cache);
    for (const auto& [k, v] : joined_cached) EXPECT_TRUE(torch::equal(lagged_cached.at(k), v)) << "lagged, cached " << k;
  }
  // The condition-cache path (sampling) agrees with the uncached one.
  auto cache = gen->backbone()->condition_cache(cond);
  auto cached = gen->backbone()->forward(x, t, cond, d, &cache);
  for (const auto& [k, v] : want) EXPECT_LE(rel(cached.at(k), v), 2e-2) << k;
  // With gradients recorded and a trainable base (every parameter requires a gradient here) the
  // reference ops run: the fused backward kernels give no weight gradients.
  {
    at::AutoGradMode grad(true);
    const auto n1 = simu::models::fused::launch_count();
    (void)gen->backbone()->forward(x, t, cond, d);
    EXPECT_EQ(simu::models::fused::launch_count(), n1);
  }
}

// The whole forward under fp16 autocast (the released inference precision): the fused kernels store
// fp16 and must agree with the reference path under the same autocast, as bf16 does above; both are
// also compared with an fp32 forward (the fp16 error should be well under the bf16 one).
TEST(FusedOpsGpu, FlowForwardFp16FusedMatchesReference) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  const torch::Device dev(torch::kCUDA);
  const auto path = simu::testing::mid_flow_config("fused_flow_fp16");
  // Seeded random weights: LibTorch seeds its default generators at random per process, so an
  // unseeded model differs from run to run (one such run failed a tolerance here, 2026-11-26).
  torch::manual_seed(16);
  auto gen = simu::models::load_generator(path, "", dev);
  auto rng = at::make_generator<at::CPUGeneratorImpl>(7);
  auto x = gen->noise(2, rng, dev);
  auto cond = torch::randn({2, 77, gen->config().backbone.cond_channels}, rng).to(dev);
  auto t = torch::full({1}, 400.0, torch::TensorOptions().device(dev));
  c10::optional<torch::Tensor> d = torch::zeros({1}, torch::TensorOptions().device(dev));
  torch::NoGradGuard ng;
  simu::models::Latents fp32;
  {
    simu::models::Autocast ac(simu::models::Precision::kFp32);
    fp32 = gen->backbone()->forward(x, t, cond, d);
  }
  for (const auto p : {simu::models::Precision::kFp16, simu::models::Precision::kBf16}) {
    simu::models::Autocast ac(p);
    gen->backbone()->set_fused_kernels(false);
    const auto n0 = simu::models::fused::launch_count();
    auto want = gen->backbone()->forward(x, t, cond, d);
    EXPECT_EQ(simu::models::fused::launch_count(), n0);
    gen->backbone()->set_fused_kernels(true);
    auto got = gen->backbone()->forward(x, t, cond, d);
    // Every block takes the fused path: 3 blocks x 2 streams x 5 launches, as in bf16.
    EXPECT_EQ(simu::models::fused::launch_count(), n0 + 3 * 2 * 5) << simu::models::precision_name(p);
    auto cache = gen->backbone()->condition_cache(cond);
    auto cached = gen->backbone()->forward(x, t, cond, d, &cache);
    // CFG's pair with an all-zero second row: the value-bias shortcut (ConditionCache::zero_from) on
    // the fused path against the full cache.
    auto pair = torch::cat({cond.narrow(0, 0, 1), cond.narrow(0, 0, 1) * 0}, 0);
    auto full = gen->backbone()->condition_cache(pair), skip = gen->backbone()->condition_cache(pair, 1);
    auto y_full = gen->backbone()->forward(x, t, pair, d, &full), y_skip = gen->backbone()->forward(x, t, pair, d, &skip);
    for (const auto& [k, v] : y_full) {
      fmt::print("{} {}: zero-row shortcut vs full cache {:.2e}\n", simu::models::precision_name(p), k, rel(y_skip.at(k), v));
      EXPECT_LE(rel(y_skip.at(k), v), p == simu::models::Precision::kFp16 ? 2.5e-3 : 2e-2) << k;
    }
    for (const auto& [k, v] : want) {
      const double e = rel(got.at(k), v), e32 = rel(got.at(k), fp32.at(k)), e32ref = rel(v, fp32.at(k));
      fmt::print("{} {}: fused vs reference {:.2e}, fused vs fp32 {:.2e}, reference vs fp32 {:.2e}\n",
                 simu::models::precision_name(p), k, e, e32, e32ref);
      // Same tolerance as bf16's (2e-2) for bf16; fp16 keeps 3 more mantissa bits: 8x tighter.
      EXPECT_LE(e, p == simu::models::Precision::kFp16 ? 2.5e-3 : 2e-2) << k;
      // The fused path is no further from fp32 than the reference path (up to the same slack).
      EXPECT_LE(e32, e32ref * 1.5 + (p == simu::models::Precision::kFp16 ? 1e-3 : 8e-3)) << k;
      EXPECT_LE(rel(cached.at(k), v), p == simu::models::Precision::kFp16 ? 2.5e-3 : 2e-2) << k;
    }
  }
}

namespace {
// LayerNorm without affine over the last dim, in whatever dtype x has (fp64 for the references).
torch::Tensor plain_layer_norm(const torch::Tensor& x, double eps) {
  auto m = x.mean(-1, true);
  auto v = (x - m).pow(2).mean(-1, true);
  return (x - m) / (v + eps).sqrt();
}
}  // namespace

TEST(FusedOpsGpu, LayerNormAffineGradientMatchesFp64) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  torch::manual_seed(11);
  const auto f32 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat32);
  const int64_t B = 2, L = 517, C = 1024;
  for (const auto dt : kLow)
  for (const int64_t G : {1, 2}) {
    auto x = (torch::randn({B, L, C}, f32) * 3 + 0.5).requires_grad_();
    auto w = 1 + 0.1 * torch::randn({G, C}, f32), b = torch::randn({G, C}, f32);
    auto gy = torch::randn({B, L, C}, f32).to(dt);
    const auto n0 = simu::models::fused::launch_count();
    auto y = simu::models::fused::layer_norm_affine_bf16(x, w, b, 1e-6, dt);
    ASSERT_EQ(y.scalar_type(), dt);
    y.backward(gy);
    EXPECT_EQ(simu::models::fused::launch_count(), n0 + 2) << "forward + backward kernel";
    // fp64 autograd of the same function.
    auto x64 = x.detach().to(torch::kFloat64).requires_grad_();
    auto y64 = plain_layer_norm(x64, 1e-6) * w.to(torch::kFloat64).unsqueeze(1) + b.to(torch::kFloat64).unsqueeze(1);
    y64.backward(gy.to(torch::kFloat64));
    EXPECT_LE(rel(x.grad(), x64.grad()), 1e-4) << name(dt) << " G " << G;
  }
  // A weight that requires a gradient: the reference runs (differentiable in w too).
  auto x = torch::randn({B, L, C}, f32).requires_grad_();
  auto w = torch::ones({1, C}, f32).requires_grad_();
  const auto n0 = simu::models::fused::launch_count();
  simu::models::fused::layer_norm_affine_bf16(x, w, {}, 1e-6).to(torch::kFloat32).sum().backward();
  EXPECT_EQ(simu::models::fused::launch_count(), n0);
  ASSERT_TRUE(w.grad().defined());
}

TEST(FusedOpsGpu, ResidualLayerNormAffineGradientMatchesFp64) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  torch::manual_seed(12);
  const auto f32 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat32);
  const int64_t B = 2, L = 517, C = 1024;
  for (const auto dt : kLow)
  for (const int64_t G : {1, 2}) {
    auto w = 1 + 0.1 * torch::randn({G, C}, f32), b = torch::randn({G, C}, f32);
    for (const auto& gate : {(0.3 * torch::randn({G, C}, f32)).to(dt), torch::Tensor()}) {
      // Gradients into both outputs (the residual stream and the normalised 16-bit copy), or only y.
      for (const bool both : {true, false}) {
        auto x = (torch::randn({B, L, C}, f32) * 3 + 0.5).requires_grad_();
        auto h = torch::randn({B, L, C}, f32).to(dt).requires_grad_();
        auto gx = torch::randn({B, L, C}, f32), gy = torch::randn({B, L, C}, f32).to(dt);
        const auto n0 = simu::models::fused::launch_count();
        auto [x_new, y] = simu::models::fused::residual_layer_norm_affine_bf16(x, h, gate, w, b, 1e-6);
        if (both) torch::autograd::backward({x_new, y}, {gx, gy});
        else y.backward(gy);
        EXPECT_EQ(simu::models::fused::launch_count(), n0 + 2);
        auto x64 = x.detach().to(torch::kFloat64).requires_grad_();
        auto h64 = h.detach().to(torch::kFloat64).requires_grad_();
        auto xn64 = gate.defined() ? x64 + h64 * gate.to(torch::kFloat64).unsqueeze(1) : x64 + h64;
        auto y64 = plain_layer_norm(xn64, 1e-6) * w.to(torch::kFloat64).unsqueeze(1) + b.to(torch::kFloat64).unsqueeze(1);
        if (both) torch::autograd::backward({xn64, y64}, {gx.to(torch::kFloat64), gy.to(torch::kFloat64)});
        else y64.backward(gy.to(torch::kFloat64));
        const std::string what = fmt::format("{} G {} gated {} both {}", name(dt), G, gate.defined(), both);
        EXPECT_LE(rel(x.grad(), x64.grad()), 1e-4) << what;
        // dh is stored in h's dtype: one rounding of the fp32 value.
        EXPECT_LE(rel(h.grad(), h64.grad()), ulp(dt)) << what;
        EXPECT_EQ(h.grad().scalar_type(), dt);
      }
    }
  }
}

namespace {
// fp64 autograd of the split (F.normalize(x) * gamma * scale for q and k, v copied) from the same 16-bit
// qkv, given the incoming gradients of q, k, v ([B, L, H, D], undefined: none) -> dqkv [B, L, 3, H, D] fp64.
torch::Tensor split_grad64(const torch::Tensor& qkv, const torch::Tensor& gq, const torch::Tensor& gk, double scale,
                           const std::vector<torch::Tensor>& grads) {
  auto x64 = qkv.detach().to(torch::kFloat64).requires_grad_();
  auto norm64 = [&](const torch::Tensor& x, const torch::Tensor& g) {
    return x / x.norm(2, -1, true).clamp_min(1e-12) * (g.to(torch::kFloat64) * scale);
  };
  const std::vector<torch::Tensor> outs = {norm64(x64.select(2, 0), gq), norm64(x64.select(2, 1), gk), x64.select(2, 2)};
  auto loss = torch::zeros({}, x64.options());
  for (int p = 0; p < 3; ++p)
    if (grads[p].defined()) loss = loss + (outs[p] * grads[p].to(torch::kFloat64)).sum();
  loss.backward();
  return x64.grad();
}
// dqkv against split_grad64: one rounding to the storage type (a ulp of the largest value), per part, and
// a small mean error.
void expect_split_grad(const torch::Tensor& got, const torch::Tensor& want, torch::ScalarType dt) {
  ASSERT_EQ(got.scalar_type(), dt);
  for (int part = 0; part < 3; ++part) EXPECT_LE(rel(got.select(2, part), want.select(2, part)), ulp(dt)) << "part " << part;
  EXPECT_LT((got.to(torch::kFloat64) - want).abs().mean().item<double>(), 2e-3 * want.abs().mean().item<double>() + 1e-6);
}
}  // namespace

// The differentiable split (forward and backward kernels through autograd) against fp64 autograd, in both
// storage types and the shapes of kSplitShapes, with the gradients arriving as attention hands them back
// (permuted [B, H, L, D] views): both launches take the 16-byte kernels. Then only q used (no incoming
// gradient for k and v: zero parts).
TEST(FusedOpsGpu, SplitQkvRmsNormGradientMatchesFp64) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  torch::manual_seed(13);
  const auto f32 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat32);
  const double scale = 8.0;
  for (const auto dt : kLow)
  for (const auto& s : kSplitShapes) {
    SCOPED_TRACE(split_name(dt, s));
    auto qkv = (torch::randn({s.B, s.L, 3, s.H, s.D}, f32) * 4).to(dt).requires_grad_();
    auto gq = 1 + 0.1 * torch::randn({s.H, s.D}, f32), gk = 1 + 0.1 * torch::randn({s.H, s.D}, f32);
    const auto n0 = simu::models::fused::launch_count(), w0 = simu::models::fused::split_qkv_wide_launch_count();
    auto [q, k, v] = simu::models::fused::split_qkv_rms_norm_autograd(qkv, gq, gk, scale);
    EXPECT_EQ(simu::models::fused::launch_count(), n0 + 1);
    // Values: as the reference split.
    auto rq = torch::empty_like(q), rk = torch::empty_like(k), rv = torch::empty_like(v);
    simu::models::fused::split_qkv_rms_norm_reference(qkv.detach(), gq, gk, scale, rq, rk, rv);
    EXPECT_LE(rel(q, rq), ulp(dt));
    EXPECT_LE(rel(k, rk), ulp(dt));
    EXPECT_TRUE(torch::equal(v, rv));
    // Gradients through [B, H, L, D] permuted views (rounded to dt on their way to the dt outputs).
    auto r = [&] { return torch::randn({s.B, s.H, s.L, s.D}, f32); };
    auto Rq = r(), Rk = r(), Rv = r();
    auto loss = (q.permute({0, 2, 1, 3}).to(torch::kFloat32) * Rq).sum() +
                (k.permute({0, 2, 1, 3}).to(torch::kFloat32) * Rk).sum() + (v.permute({0, 2, 1, 3}).to(torch::kFloat32) * Rv).sum();
    loss.backward();
    EXPECT_EQ(simu::models::fused::launch_count(), n0 + 2);
    EXPECT_EQ(simu::models::fused::split_qkv_wide_launch_count(), w0 + 2) << "16-byte forward and backward";
    auto in = [&](const torch::Tensor& R) { return R.to(dt).permute({0, 2, 1, 3}); };  // [B, L, H, D]
    const auto want = split_grad64(qkv, gq, gk, scale, {in(Rq), in(Rk), in(Rv)});
    expect_split_grad(qkv.grad(), want, dt);
    // Only q used: zero gradients for the k and v parts.
    qkv.mutable_grad() = torch::Tensor();
    auto [q2, k2, v2] = simu::models::fused::split_qkv_rms_norm_autograd(qkv, gq, gk, scale);
    (q2.to(torch::kFloat32) * Rq.permute({0, 2, 1, 3})).sum().backward();
    EXPECT_EQ(simu::models::fused::split_qkv_wide_launch_count(), w0 + 4);
    EXPECT_EQ(qkv.grad().select(2, 1).abs().max().item<double>(), 0.0);
    EXPECT_EQ(qkv.grad().select(2, 2).abs().max().item<double>(), 0.0);
    expect_split_grad(qkv.grad(), split_grad64(qkv, gq, gk, scale, {in(Rq), {}, {}}), dt);
  }
}

// The backward kernels at tensor level (split_qkv_rms_norm_backward) against fp64 autograd: the 16-byte
// kernel with missing gradients (k only; q and v only), the 4-byte kernel forced, and taken by itself for a
// gradient 4-byte but not 16-byte aligned; the two kernels agree within a ulp.
TEST(FusedOpsGpu, SplitQkvRmsNormBackwardPaths) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  torch::manual_seed(14);
  const auto f32 = torch::TensorOptions().device(torch::kCUDA).dtype(torch::kFloat32);
  const int64_t B = 2, L = 517, H = 16, D = 64;
  const double scale = 8.0;
  for (const auto dt : kLow) {
    SCOPED_TRACE(name(dt));
    auto qkv = (torch::randn({B, L, 3, H, D}, f32) * 4).to(dt);
    auto gq = 1 + 0.1 * torch::randn({H, D}, f32), gk = 1 + 0.1 * torch::randn({H, D}, f32);
    auto r = [&] { return torch::randn({B, L, H, D}, f32).to(dt); };
    const auto dq = r(), dk = r(), dv = r();
    auto run = [&](const torch::Tensor& a, const torch::Tensor& b, const torch::Tensor& c, bool wide) {
      const auto w0 = simu::models::fused::split_qkv_wide_launch_count();
      auto g = simu::models::fused::split_qkv_rms_norm_backward(qkv, gq, gk, scale, a, b, c);
      EXPECT_EQ(simu::models::fused::split_qkv_wide_launch_count(), w0 + (wide ? 1 : 0)) << "wide path expected: " << wide;
      expect_split_grad(g, split_grad64(qkv, gq, gk, scale, {a, b, c}), dt);
      return g;
    };
    // 16-byte kernel: all three, k only, q and v only.
    auto g_wide = run(dq, dk, dv, true);
    auto g_k = run({}, dk, {}, true);
    EXPECT_EQ(g_k.select(2, 0).abs().max().item<double>(), 0.0);
    EXPECT_EQ(g_k.select(2, 2).abs().max().item<double>(), 0.0);
    auto g_qv = run(dq, {}, dv, true);
    EXPECT_EQ(g_qv.select(2, 1).abs().max().item<double>(), 0.0);
    // The 4-byte kernel forced: within a ulp of the 16-byte one (summation order only).
    simu::models::fused::set_split_qkv_wide(false);
    auto g_narrow = run(dq, dk, dv, false);
    simu::models::fused::set_split_qkv_wide(true);
    EXPECT_LE(rel(g_narrow, g_wide), ulp(dt));
    // A gradient 2 elements into its buffer (4-byte aligned, not 16): read in place by the 4-byte kernel.
    auto dq_off = torch::empty({B * L * H * D + 2}, dq.options()).narrow(0, 2, B * L * H * D).view({B, L, H, D}).copy_(dq);
    auto g_off = run(dq_off, dk, dv, false);
    EXPECT_TRUE(torch::equal(g_off, g_narrow));
  }
}

TEST(FusedOpsGpu, FlowTrainingKernelsMatchReferenceGradients) {
  SIMU_REQUIRE_CUDA();
  ASSERT_TRUE(simu::models::fused::compiled());
  const torch::Device dev(torch::kCUDA);
  // A mid-size model the kernels support (tests/flow_mid_config.h).
  const auto path = simu::testing::mid_flow_config("fused_flow_train");
  // Seeded random weights: LibTorch seeds its default generators at random per process, so an
  // unseeded model differs from run to run (one such run failed a tolerance here, 2026-11-26).
  torch::manual_seed(17);
  auto gen = simu::models::load_generator(path, "", dev);
  for (auto& p : gen->parameters()) p.set_requires_grad(false);
  auto backbone = gen->backbone();
  backbone->set_training_kernels(true);
  auto rng = at::make_generator<at::CPUGeneratorImpl>(6);
  auto x0 = gen->noise(2, rng, dev);
  auto cond = torch::randn({2, 77, gen->config().backbone.cond_channels}, rng).to(dev);
  // Per-sample t as in training (one modulation row per batch element).
  auto t = torch::tensor({300.0f, 700.0f}, torch::TensorOptions().device(dev));
  c10::optional<torch::Tensor> d = torch::zeros({2}, torch::TensorOptions().device(dev));
  std::map<std::string, torch::Tensor> weights;
  for (const auto& [k, v] : x0) weights[k] = torch::randn(v.sizes(), rng).to(dev);
  simu::models::Autocast ac(simu::models::Precision::kBf16);
  // Forward + backward of sum(out * weights) with respect to the input latents.
  auto run = [&](bool fused, int64_t* launches) {
    backbone->set_fused_kernels(fused);
    simu::models::Latents x;
    std::vector<torch::Tensor> leaves;
    for (const auto& [k, v] : x0) {
      x[k] = v.clone().requires_grad_();
      leaves.push_back(x[k]);
    }
    const auto n0 = simu::models::fused::launch_count();
    auto out = backbone->forward(x, t, cond, d);
    if (launches) *launches = simu::models::fused::launch_count() - n0;
    torch::Tensor loss = torch::zeros({}, torch::TensorOptions().device(dev));
    for (const auto& [k, v] : out) loss = loss + (v.to(torch::kFloat32) * weights.at(k)).sum();
    auto grads = torch::autograd::grad({loss}, leaves);
    if (launches) *launches = simu::models::fused::launch_count() - n0;
    std::map<std::string, torch::Tensor> res;
    size_t i = 0;
    for (const auto& [k, v] : out) res["out." + k] = v.detach();
    for (const auto& [k, v] : x0) res["grad." + k] = grads[i++];
    return res;
  };
  auto want = run(false, nullptr);
  int64_t fwd = 0, total = 0;
  auto fwd_only = [&] {
    backbone->set_fused_kernels(true);
    simu::models::Latents x;
    for (const auto& [k, v] : x0) x[k] = v.clone().requires_grad_();
    const auto n0 = simu::models::fused::launch_count();
    auto out = backbone->forward(x, t, cond, d);
    fwd = simu::models::fused::launch_count() - n0;
    return out;
  };
  (void)fwd_only();
  auto got = run(true, &total);
  // 3 blocks x 2 streams x (3 norms + 1 qkv split), each once forward and once backward.
  EXPECT_EQ(fwd, 3 * 2 * 4);
  EXPECT_EQ(total, 2 * 3 * 2 * 4);
  for (const auto& [k, v] : want) EXPECT_LE(rel(got.at(k), v), 3e-2) << k;
  // Without a graph (FM-DPO's reference pass) the training kernels compute the same numbers.
  {
    torch::NoGradGuard ng;
    const auto n0 = simu::models::fused::launch_count();
    auto out = backbone->forward(x0, t, cond, d);
    EXPECT_EQ(simu::models::fused::launch_count() - n0, 3 * 2 * 4) << "no inference-only kernels in training mode";
    for (const auto& [k, v] : out) EXPECT_TRUE(torch::equal(v, got.at("out." + k))) << k;
  }
  backbone->set_training_kernels(false);
}
