// The frozen MLP's cuBLASLt epilogue products (GELU_AUX_BIAS forward, DGELU backward), their autograd
// function and the plain-ATen reference (mlp_epilogue.h).
#include "models/mlp_epilogue.h"

#include <ATen/autocast_mode.h>
#include <fmt/ranges.h>
#include <torch/autograd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cstdint>
#include <initializer_list>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <tuple>
#include <type_traits>

#include "common/error.h"
#include "models/linear.h"

#ifdef SIMU_HAVE_CUBLASLT
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cublasLt.h>
#include <dlfcn.h>
#endif

namespace simu::models::mlp_epilogue {

namespace {

#ifdef SIMU_HAVE_CUBLASLT
// cuBLASLt entry points looked up in the process: the libcublasLt that LibTorch loaded. Linking one here
// could load a second build of it from another folder (the CUDA toolkit's) ahead of torch's, and every
// ATen product would then run on that one. Null when the process has none.
void* lt_symbol(const char* name) { return dlsym(RTLD_DEFAULT, name); }
template <typename F>
F lt_function(const char* name) {
  void* p = lt_symbol(name);
  SIMU_CHECK(p != nullptr, "mlp_epilogue: {} is not in the process (LibTorch's libcublasLt is not loaded)", name);
  return reinterpret_cast<F>(p);
}
#define SIMU_LT(fn) ([] { static const auto f = lt_function<decltype(&::fn)>(#fn); return f; }())
#endif

std::atomic<int64_t> g_launches{0};
std::atomic<bool> g_enabled{true};
std::atomic<int> g_rank_gelu_aux{0}, g_rank_dgelu{0};  // set_algo_ranks

bool is_16bit(torch::ScalarType t) { return t == torch::kBFloat16 || t == torch::kHalf; }
bool aligned16(const torch::Tensor& t) { return reinterpret_cast<std::uintptr_t>(t.data_ptr()) % 16 == 0; }

// Every tensor defined, contiguous, 16-byte aligned, in like's dtype on its device.
bool operands_ok(std::initializer_list<const torch::Tensor*> ts, const torch::Tensor& like) {
  for (const auto* t : ts)
    if (!t->defined() || t->scalar_type() != like.scalar_type() || t->device() != like.device() || !t->is_contiguous() ||
        !aligned16(*t))
      return false;
  return true;
}

// fc1's product in the epilogue: x2 [rows >= 1, K] 16-bit on CUDA, w1 [N, K], b1 [N], K and N multiples of 8.
bool fc1_ok(const torch::Tensor& x2, const torch::Tensor& w1, const torch::Tensor& b1) {
  return mlp_epilogue::compiled() && x2.defined() && x2.is_cuda() && x2.dim() == 2 && x2.size(0) >= 1 &&
         is_16bit(x2.scalar_type()) && operands_ok({&x2, &w1, &b1}, x2) && w1.dim() == 2 && w1.size(1) == x2.size(1) &&
         b1.dim() == 1 && b1.size(0) == w1.size(0) && x2.size(1) % 8 == 0 && w1.size(0) % 8 == 0;
}

#ifdef SIMU_HAVE_CUBLASLT

// One column-major cuBLASLt product D = op(A) B (+ epilogue), D: m x n with leading dimension m, the aux
// matrix (GELU input) m x n with leading dimension m too. Row-major tensors are the transposed views.
struct LtProduct {
  cublasLtEpilogue_t epilogue;
  bool trans_a;      // op(A) = A^T (A stored k x m) or A (stored m x k)
  int64_t m, n, k;
  const void* a;
  int64_t lda;
  const void* b;     // stored k x n
  int64_t ldb;
  void* d;
  const void* bias;  // [m] or null
  void* aux;         // GELU input: written by GELU_AUX_BIAS, read by DGELU
  torch::ScalarType dtype;
  c10::Device device;
};

void check_lt(cublasStatus_t s, const char* what) {
  SIMU_CHECK(s == CUBLAS_STATUS_SUCCESS, "mlp_epilogue: cuBLASLt {} failed: {}", what, SIMU_LT(cublasLtGetStatusString)(s));
}

// Owning handles of the descriptors.
struct LtDeleter {
  void operator()(cublasLtMatmulDesc_t p) const { SIMU_LT(cublasLtMatmulDescDestroy)(p); }
  void operator()(cublasLtMatrixLayout_t p) const { SIMU_LT(cublasLtMatrixLayoutDestroy)(p); }
  void operator()(cublasLtMatmulPreference_t p) const { SIMU_LT(cublasLtMatmulPreferenceDestroy)(p); }
};
template <typename T>
using LtPtr = std::unique_ptr<std::remove_pointer_t<T>, LtDeleter>;

template <typename T>
void set_desc(cublasLtMatmulDesc_t d, cublasLtMatmulDescAttributes_t a, const T& v) {
  check_lt(SIMU_LT(cublasLtMatmulDescSetAttribute)(d, a, &v, sizeof(v)), "MatmulDescSetAttribute");
}
template <typename T>
void set_pref(cublasLtMatmulPreference_t p, cublasLtMatmulPreferenceAttributes_t a, const T& v) {
  check_lt(SIMU_LT(cublasLtMatmulPreferenceSetAttribute)(p, a, &v, sizeof(v)), "MatmulPreferenceSetAttribute");
}

LtPtr<cublasLtMatrixLayout_t> layout(cudaDataType_t type, int64_t rows, int64_t cols, int64_t ld) {
  cublasLtMatrixLayout_t l = nullptr;
  check_lt(SIMU_LT(cublasLtMatrixLayoutCreate)(&l, type, static_cast<uint64_t>(rows), static_cast<uint64_t>(cols), ld),
           "MatrixLayoutCreate");
  return LtPtr<cublasLtMatrixLayout_t>(l);
}

// The largest power of two (<= 256) dividing the address: what the heuristic may assume.
uint32_t alignment(const void* p) {
  const auto a = reinterpret_cast<std::uintptr_t>(p);
  uint32_t r = 1;
  while (r < 256 && a % (2 * r) == 0) r *= 2;
  return r;
}

// The heuristic's algorithm of the rank set_algo_ranks gives the product's epilogue (0: its first), per
// problem (shape, epilogue, dtype, workspace, pointer alignments, rank), kept for the process: a forward
// with a graph and one without run the same algorithm. nullopt: none.
using AlgoKey = std::tuple<int, int, bool, int64_t, int64_t, int64_t, int, size_t, uint32_t, uint32_t, uint32_t, uint32_t,
                           uint32_t, int>;
struct Chosen {
  std::optional<cublasLtMatmulAlgo_t> algo;
  AlgoInfo info;
};
std::mutex g_algo_mutex;
std::map<AlgoKey, Chosen> g_algos;
const AlgoInfo* g_last_algo = nullptr;  // the last product's entry of g_algos (nodes stay put); under g_algo_mutex

// One algorithm's configuration as cuBLASLt reports it (for benchmark tables).
std::string describe(const cublasLtMatmulAlgo_t& algo) {
  auto get = [&](cublasLtMatmulAlgoConfigAttributes_t a) {
    uint32_t v = 0;
    size_t written = 0;
    const auto s = SIMU_LT(cublasLtMatmulAlgoConfigGetAttribute)(&algo, a, &v, sizeof(v), &written);
    return s == CUBLAS_STATUS_SUCCESS ? static_cast<int64_t>(v) : int64_t{-1};
  };
  return fmt::format("id {} tile {} stages {} splitK {} swizzle {} cluster {}", get(CUBLASLT_ALGO_CONFIG_ID),
                     get(CUBLASLT_ALGO_CONFIG_TILE_ID), get(CUBLASLT_ALGO_CONFIG_STAGES_ID),
                     get(CUBLASLT_ALGO_CONFIG_SPLITK_NUM), get(CUBLASLT_ALGO_CONFIG_CTA_SWIZZLING),
                     get(CUBLASLT_ALGO_CONFIG_CLUSTER_SHAPE_ID));
}

std::optional<cublasLtMatmulAlgo_t> find_algo(cublasLtHandle_t handle, cublasLtMatmulDesc_t desc, cublasLtMatrixLayout_t la,
                                              cublasLtMatrixLayout_t lb, cublasLtMatrixLayout_t ld, const LtProduct& p,
                                              size_t ws_size) {
  const int rank = (p.epilogue == CUBLASLT_EPILOGUE_DGELU ? g_rank_dgelu : g_rank_gelu_aux).load();
  const AlgoKey key{static_cast<int>(c10::cuda::current_device()), static_cast<int>(p.epilogue), p.trans_a, p.m, p.n, p.k,
                    static_cast<int>(p.dtype), ws_size, alignment(p.a), alignment(p.b), alignment(p.d),
                    p.bias ? alignment(p.bias) : 0u, alignment(p.aux), rank};
  std::lock_guard<std::mutex> lock(g_algo_mutex);
  if (auto it = g_algos.find(key); it != g_algos.end()) {
    g_last_algo = &it->second.info;
    return it->second.algo;
  }
  cublasLtMatmulPreference_t raw = nullptr;
  check_lt(SIMU_LT(cublasLtMatmulPreferenceCreate)(&raw), "MatmulPreferenceCreate");
  LtPtr<cublasLtMatmulPreference_t> pref(raw);
  set_pref(raw, CUBLASLT_MATMUL_PREF_MAX_WORKSPACE_BYTES, static_cast<uint64_t>(ws_size));
  set_pref(raw, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_A_BYTES, std::get<8>(key));
  set_pref(raw, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_B_BYTES, std::get<9>(key));
  set_pref(raw, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_C_BYTES, std::get<10>(key));
  set_pref(raw, CUBLASLT_MATMUL_PREF_MIN_ALIGNMENT_D_BYTES, std::get<10>(key));
  // Split-K partial sums in fp32 only (no reduction in the 16-bit output type).
  set_pref(raw, CUBLASLT_MATMUL_PREF_REDUCTION_SCHEME_MASK,
           static_cast<uint32_t>(CUBLASLT_REDUCTION_SCHEME_NONE | CUBLASLT_REDUCTION_SCHEME_COMPUTE_TYPE));
  // The heuristic's list, best first; rank k where it has k + 1 usable entries, else its first.
  constexpr int kRequested = 16;
  std::array<cublasLtMatmulHeuristicResult_t, kRequested> results{};
  int found = 0;
  const auto s = SIMU_LT(cublasLtMatmulAlgoGetHeuristic)(handle, desc, la, lb, ld, ld, raw, kRequested, results.data(),
                                                         &found);
  Chosen c;
  c.info.found = s == CUBLAS_STATUS_SUCCESS ? found : 0;
  for (int r : {rank, 0}) {
    if (r < c.info.found && results[r].state == CUBLAS_STATUS_SUCCESS) {
      c.algo = results[r].algo;
      c.info.rank = r;
      c.info.config = describe(results[r].algo);
      break;
    }
  }
  const auto& entry = g_algos[key] = c;
  g_last_algo = &entry.info;
  return entry.algo;
}

// Runs the product on the current stream with ATen's cuBLASLt handle and workspace; false (nothing run)
// when cuBLASLt has no algorithm for it.
bool run_product(const LtProduct& p) {
  const c10::cuda::CUDAGuard guard(p.device);
  (void)at::cuda::getCurrentCUDABlasHandle();  // sets up the stream's workspace when cuBLAS and Lt share it
  cublasLtHandle_t handle = at::cuda::getCurrentCUDABlasLtHandle();
  const size_t ws_size = at::cuda::getCUDABlasLtWorkspaceSize();
  void* ws = at::cuda::getCUDABlasLtWorkspace();
  const cudaDataType_t type = p.dtype == torch::kHalf ? CUDA_R_16F : CUDA_R_16BF;
  cublasLtMatmulDesc_t raw = nullptr;
  check_lt(SIMU_LT(cublasLtMatmulDescCreate)(&raw, CUBLAS_COMPUTE_32F, CUDA_R_32F), "MatmulDescCreate");
  LtPtr<cublasLtMatmulDesc_t> desc(raw);
  set_desc(raw, CUBLASLT_MATMUL_DESC_TRANSA, p.trans_a ? CUBLAS_OP_T : CUBLAS_OP_N);
  set_desc(raw, CUBLASLT_MATMUL_DESC_TRANSB, CUBLAS_OP_N);
  set_desc(raw, CUBLASLT_MATMUL_DESC_EPILOGUE, p.epilogue);
  if (p.bias) set_desc(raw, CUBLASLT_MATMUL_DESC_BIAS_POINTER, p.bias);
  set_desc(raw, CUBLASLT_MATMUL_DESC_EPILOGUE_AUX_POINTER, static_cast<const void*>(p.aux));
  set_desc(raw, CUBLASLT_MATMUL_DESC_EPILOGUE_AUX_LD, p.m);
  auto la = p.trans_a ? layout(type, p.k, p.m, p.lda) : layout(type, p.m, p.k, p.lda);
  auto lb = layout(type, p.k, p.n, p.ldb);
  auto ld = layout(type, p.m, p.n, p.m);
  const auto algo = find_algo(handle, raw, la.get(), lb.get(), ld.get(), p, ws_size);
  if (!algo) return false;
  const float alpha = 1.0f, beta = 0.0f;
  check_lt(SIMU_LT(cublasLtMatmul)(handle, raw, &alpha, p.a, la.get(), p.b, lb.get(), &beta, p.d, ld.get(), p.d, ld.get(),
                          &*algo, ws, ws_size, at::cuda::getCurrentCUDAStream()),
           "Matmul");
  ++g_launches;
  return true;
}

#endif  // SIMU_HAVE_CUBLASLT

// fc1 (GELU epilogue) then fc2: {y [rows, C], pre [rows, N]}.
std::pair<torch::Tensor, torch::Tensor> forward_products(const torch::Tensor& x2, const torch::Tensor& w1,
                                                         const torch::Tensor& b1, const torch::Tensor& w2,
                                                         const torch::Tensor& b2) {
  auto [h, pre] = linear_gelu_aux(x2, w1, b1);  // [rows, N] each
  return {at::addmm(b2, h, w2.t()), pre};        // fc2 as the Linear computes it
}

using torch::autograd::AutogradContext;
using torch::autograd::variable_list;

// x2 [rows, K] -> y [rows, C]; backward: dX only (weights and biases frozen).
class FrozenMlpFn : public torch::autograd::Function<FrozenMlpFn> {
 public:
  static torch::Tensor forward(AutogradContext* ctx, const torch::Tensor& x2, const torch::Tensor& w1,
                               const torch::Tensor& b1, const torch::Tensor& w2, const torch::Tensor& b2) {
    auto [y, pre] = forward_products(x2, w1, b1, w2, b2);
    ctx->save_for_backward({pre, w1, w2});
    return y;
  }
  static variable_list backward(AutogradContext* ctx, variable_list grads) {
    if (!grads[0].defined()) return {torch::Tensor(), torch::Tensor(), torch::Tensor(), torch::Tensor(), torch::Tensor()};
    const auto saved = ctx->get_saved_variables();
    auto dy = grads[0].contiguous();  // [rows, C]
    if (!aligned16(dy)) dy = dy.clone();
    auto dpre = linear_dgelu(dy, saved[2], saved[0]);  // [rows, N]
    return {at::mm(dpre, saved[1]), torch::Tensor(), torch::Tensor(), torch::Tensor(), torch::Tensor()};
  }
};

}  // namespace

bool compiled() {
#ifdef SIMU_HAVE_CUBLASLT
  static const bool loaded = lt_symbol("cublasLtMatmul") != nullptr;
  return loaded;
#else
  return false;
#endif
}

int64_t launch_count() { return g_launches.load(); }

void set_enabled(bool on) { g_enabled = on; }
bool enabled() { return g_enabled.load(); }

void set_algo_ranks(int gelu_aux, int dgelu) {
  for (int r : {gelu_aux, dgelu})
    SIMU_CHECK(r >= 0 && r < 16, "mlp_epilogue::set_algo_ranks: {} is not a heuristic rank in [0, 15]", r);
  g_rank_gelu_aux = gelu_aux;
  g_rank_dgelu = dgelu;
}
std::pair<int, int> algo_ranks() { return {g_rank_gelu_aux.load(), g_rank_dgelu.load()}; }

AlgoInfo last_algo() {
#ifdef SIMU_HAVE_CUBLASLT
  std::lock_guard<std::mutex> lock(g_algo_mutex);
  return g_last_algo ? *g_last_algo : AlgoInfo{};
#else
  return {};
#endif
}

bool supports(const torch::Tensor& x2, const torch::Tensor& w1, const torch::Tensor& b1, const torch::Tensor& w2,
              const torch::Tensor& b2) {
  return fc1_ok(x2, w1, b1) && operands_ok({&w2, &b2}, x2) && w2.dim() == 2 && w2.size(1) == w1.size(0) &&
         b2.dim() == 1 && b2.size(0) == w2.size(0) && w2.size(0) % 8 == 0;
}

std::pair<torch::Tensor, torch::Tensor> linear_gelu_aux(const torch::Tensor& x2, const torch::Tensor& w1,
                                                        const torch::Tensor& b1) {
  SIMU_CHECK(x2.dim() == 2 && w1.dim() == 2 && w1.size(1) == x2.size(1) && b1.dim() == 1 && b1.size(0) == w1.size(0),
             "mlp_epilogue::linear_gelu_aux: x [{}], weight [{}], bias [{}] do not fit x W^T + b", fmt::join(x2.sizes(), ", "),
             fmt::join(w1.sizes(), ", "), fmt::join(b1.sizes(), ", "));
#ifdef SIMU_HAVE_CUBLASLT
  if (fc1_ok(x2, w1, b1)) {
    const int64_t rows = x2.size(0), K = x2.size(1), N = w1.size(0);
    auto h = torch::empty({rows, N}, x2.options()), pre = torch::empty({rows, N}, x2.options());
    // Column-major: h^T [N, rows] = W1 (stored K x N, transposed) x^T (stored K x rows) + b1, GELU; aux = pre^T.
    const LtProduct p{CUBLASLT_EPILOGUE_GELU_AUX_BIAS, true, N, rows, K, w1.data_ptr(), K, x2.data_ptr(), K,
                      h.data_ptr(), b1.data_ptr(), pre.data_ptr(), x2.scalar_type(), x2.device()};
    if (run_product(p)) return {h, pre};
  }
#endif
  auto pre = at::addmm(b1, x2, w1.t());
  return {at::gelu(pre, "tanh"), pre};
}

torch::Tensor linear_dgelu(const torch::Tensor& dy, const torch::Tensor& w2, const torch::Tensor& pre) {
  SIMU_CHECK(dy.dim() == 2 && w2.dim() == 2 && w2.size(0) == dy.size(1) && pre.dim() == 2 && pre.size(0) == dy.size(0) &&
                 pre.size(1) == w2.size(1),
             "mlp_epilogue::linear_dgelu: dy [{}], weight [{}], pre-activation [{}] do not fit (dy W) * gelu'(pre)",
             fmt::join(dy.sizes(), ", "), fmt::join(w2.sizes(), ", "), fmt::join(pre.sizes(), ", "));
#ifdef SIMU_HAVE_CUBLASLT
  const int64_t rows = dy.size(0), C = dy.size(1), N = w2.size(1);
  if (compiled() && dy.is_cuda() && is_16bit(dy.scalar_type()) && rows >= 1 && C % 8 == 0 && N % 8 == 0 &&
      operands_ok({&dy, &w2, &pre}, dy)) {
    auto dpre = torch::empty({rows, N}, dy.options());
    // Column-major: dPre^T [N, rows] = W2 (stored N x C) dY^T (stored C x rows), times gelu'(aux = pre^T).
    const LtProduct p{CUBLASLT_EPILOGUE_DGELU, false, N, rows, C, w2.data_ptr(), N, dy.data_ptr(), C,
                      dpre.data_ptr(), nullptr, pre.data_ptr(), dy.scalar_type(), dy.device()};
    if (run_product(p)) return dpre;
  }
#endif
  return at::gelu_backward(at::mm(dy, w2), pre, "tanh");
}

torch::Tensor mlp(const torch::Tensor& x, const torch::Tensor& w1, const torch::Tensor& b1, const torch::Tensor& w2,
                  const torch::Tensor& b2) {
  if (!compiled() || !x.is_cuda() || x.dim() < 2) return {};
  auto x2 = x.reshape({-1, x.size(-1)});  // [rows, K]
  if (!x2.is_contiguous()) x2 = x2.contiguous();
  if (!aligned16(x2)) x2 = x2.clone();
  if (!supports(x2, w1, b1, w2, b2)) return {};
  for (const auto* t : {&w1, &b1, &w2, &b2})
    SIMU_CHECK(!t->requires_grad(), "mlp_epilogue::mlp: the weights and biases are frozen (no gradient), one requires it");
  torch::Tensor y2;
  if (at::GradMode::is_enabled() && x2.requires_grad()) {
    y2 = FrozenMlpFn::apply(x2, w1, b1, w2, b2);
  } else {
    y2 = forward_products(x2, w1, b1, w2, b2).first;  // the same products; the aux is dropped
  }
  auto shape = x.sizes().vec();
  shape.back() = w2.size(0);
  return y2.view(shape);  // [..., C]
}

torch::Tensor mlp_reference(const torch::Tensor& x, const torch::Tensor& w1, const torch::Tensor& b1,
                            const torch::Tensor& w2, const torch::Tensor& b2) {
  auto x2 = x.reshape({-1, x.size(-1)});                      // [rows, K]
  auto h = at::gelu(at::addmm(b1, x2, w1.t()), "tanh");         // [rows, N]
  auto shape = x.sizes().vec();
  shape.back() = w2.size(0);
  return at::addmm(b2, h, w2.t()).view(shape);                 // [..., C]
}

torch::Tensor frozen_mlp(const torch::Tensor& x, LinearImpl& fc1, LinearImpl& fc2) {
  if (!g_enabled.load()) return {};
  if (!compiled() || !x.is_cuda() || x.dim() < 2 || !at::autocast::is_autocast_enabled(at::kCUDA)) return {};
  const auto lp = at::autocast::get_autocast_dtype(at::kCUDA);
  if (!is_16bit(lp)) return {};
  for (const LinearImpl* l : {&fc1, &fc2}) {
    // Any adapter, enabled or not: FM-DPO's reference pass (adapters off) must take the policy's (ATen) path.
    if (l->fp8_weight() || l->adapter() || !l->bias.defined()) return {};
    if (l->weight.requires_grad() || l->bias.requires_grad()) return {};  // a weight gradient: the ATen path
  }
  // Each Linear's compute copy where it applies (already 16-bit), else its weights cast as autocast would.
  auto cast = [&](const torch::Tensor& t) { return t.scalar_type() == lp ? t : t.to(lp); };
  const auto [w1, b1] = fc1.product_weights(x);
  const auto [w2, b2] = fc2.product_weights(x);
  return mlp(cast(x), cast(w1), cast(b1), cast(w2), cast(b2));
}

}  // namespace simu::models::mlp_epilogue
