// bench_cudnn_sdpa: every cuDNN execution plan for the flow model's attention shapes, timed against the
// plan PyTorch's SDPA runs (at::scaled_dot_product_attention, its cuDNN backend). PyTorch builds one
// cuDNN graph per shape and runs the heuristic's first plan; this program builds the same attention
// (BSHD layout, scale 1/sqrt(D), no mask) through the cuDNN frontend (the PyPI package
// nvidia-cudnn-frontend, header-only, calling the libcudnn that LibTorch loaded), asks the heuristics in
// each mode for every plan, times each one and checks its outputs (and gradients) against PyTorch's.
// Cases (head dim 64, 16 heads):
//   train-self    bf16 forward with softmax stats + backward, B 4, 4,096 x 4,096 (FM-DPO micro-batch 2)
//   train-cross   bf16 forward + backward, B 2, 8,192 queries (both members) x L condition tokens
//   sample-self   fp16 inference forward, B 2, 4,096 x 4,096 (CFG rows)
//   sample-cross  fp16 inference forward, B 1, 4,096 x L
// --fp8: the training cases also through cuDNN's FP8 SDPA forward and backward (e4m3, unit scales, the
// heuristic's first plan), timed against PyTorch's bf16: the attention an FP8 training mode could have.
#include <fmt/format.h>

#include <string>
#include <vector>

#include "common/cli.h"
#include "common/error.h"

#ifdef SIMU_HAVE_CUDNN_FRONTEND
#include <ATen/ATen.h>
#include <ATen/cuda/CUDAContext.h>
#include <ATen/cuda/CUDAEvent.h>
#include <dlfcn.h>
#include <torch/cuda.h>
#include <torch/torch.h>

#include <cmath>
#include <functional>
#include <map>
#include <memory>

#define NV_CUDNN_FRONTEND_USE_DYNAMIC_LOADING
#include <cudnn_frontend.h>

namespace cudnn_frontend {
void* cudnn_dlhandle = nullptr;  // LibTorch's libcudnn, found in the process (main)
}  // namespace cudnn_frontend

namespace {

namespace fe = cudnn_frontend;

struct Case {
  std::string name;
  int64_t b, sq, skv;
  bool training;
  torch::ScalarType dtype;
};

struct Args {
  std::vector<std::string> cases = {"train-self", "train-cross", "sample-self", "sample-cross"};
  std::vector<int64_t> cond_lens = {2800, 7528};
  int iters = 20, warmup = 3;
  std::vector<std::string> modes = {"A", "B", "FALLBACK"};
  std::string implementation = "auto";
  bool fp8 = false;  // the training cases also in FP8 (cuDNN's FP8 SDPA forward and backward)
};

constexpr int64_t kHeads = 16, kDim = 64;

void check_fe(fe::error_t e, const std::string& what) {
  SIMU_CHECK(e.is_good(), "cuDNN frontend: {} failed: {}", what, e.get_message());
}

// Mean milliseconds of f over iters runs after warmup runs (CUDA events on the current stream).
double time_ms(const std::function<void()>& f, int iters, int warmup) {
  for (int i = 0; i < warmup; ++i) f();
  at::cuda::CUDAEvent start(cudaEventDefault), stop(cudaEventDefault);
  auto stream = at::cuda::getCurrentCUDAStream();
  start.record(stream);
  for (int i = 0; i < iters; ++i) f();
  stop.record(stream);
  stop.synchronize();
  return start.elapsed_time(stop) / iters;
}

fe::DataType_t fe_type(torch::ScalarType t) {
  return t == torch::kHalf ? fe::DataType_t::HALF : fe::DataType_t::BFLOAT16;
}

// [B, S, H, D] storage seen as [B, H, S, D] (the layout PyTorch's permuted views give cuDNN).
std::vector<int64_t> bshd_stride(int64_t s) { return {s * kHeads * kDim, kDim, kHeads * kDim, 1}; }

fe::HeurMode_t heur_mode(const std::string& m) {
  if (m == "A") return fe::HeurMode_t::A;
  if (m == "B") return fe::HeurMode_t::B;
  if (m == "FALLBACK") return fe::HeurMode_t::FALLBACK;
  if (m == "OPENSOURCE") return fe::HeurMode_t::OPENSOURCE;
  simu::fail("--modes: '{}' is not a heuristic mode (A, B, FALLBACK, OPENSOURCE)", m);
}

struct Tensors {
  torch::Tensor q, k, v, o, stats, d_o, dq, dk, dv;  // BSHD storage; stats [B, H, Sq, 1] fp32
};

// One graph (forward or backward) with its plans: builds every plan the mode's heuristics offer, then
// times each against `ref_ms` and reports its largest output difference from the reference tensors.
void run_graph(cudnnHandle_t handle, const Case& c, bool backward, const std::string& mode, const std::string& impl,
               Tensors& t, const std::vector<torch::Tensor>& ref, double ref_ms, const Args& a) {
  fe::graph::Graph g;
  g.set_io_data_type(fe_type(c.dtype)).set_intermediate_data_type(fe::DataType_t::FLOAT).set_compute_data_type(
      fe::DataType_t::FLOAT);
  auto tensor = [&](const char* name, int64_t uid, int64_t s) {
    return g.tensor(fe::graph::Tensor_attributes().set_name(name).set_uid(uid).set_dim({c.b, kHeads, s, kDim}).set_stride(
        bshd_stride(s)));
  };
  auto Q = tensor("Q", 1, c.sq), K = tensor("K", 2, c.skv), V = tensor("V", 3, c.skv);
  const float scale = 1.0f / std::sqrt(static_cast<float>(kDim));
  std::map<int64_t, void*> ptrs{{1, t.q.data_ptr()}, {2, t.k.data_ptr()}, {3, t.v.data_ptr()}};
  std::vector<std::pair<int64_t, torch::Tensor>> outputs;  // uid, buffer written by the plan
  if (!backward) {
    auto opts = fe::graph::SDPA_attributes().set_name("sdpa").set_generate_stats(c.training).set_attn_scale(scale);
    if (impl == "unified") opts.set_implementation(fe::AttentionImplementation_t::UNIFIED);
    if (impl == "composite") opts.set_implementation(fe::AttentionImplementation_t::COMPOSITE);
    auto [O, Stats] = g.sdpa(Q, K, V, opts);
    O->set_output(true).set_uid(4).set_dim({c.b, kHeads, c.sq, kDim}).set_stride(bshd_stride(c.sq));
    auto o = torch::empty_like(t.q);
    ptrs[4] = o.data_ptr();
    outputs.emplace_back(4, o);
    if (c.training) {
      Stats->set_output(true).set_uid(5).set_data_type(fe::DataType_t::FLOAT);
      auto st = torch::empty({c.b, kHeads, c.sq, 1}, t.q.options().dtype(torch::kFloat32));
      ptrs[5] = st.data_ptr();
      outputs.emplace_back(5, st);
    }
  } else {
    auto O = tensor("O", 4, c.sq), dO = tensor("dO", 6, c.sq);
    auto Stats = g.tensor(fe::graph::Tensor_attributes().set_name("Stats").set_uid(5).set_dim({c.b, kHeads, c.sq, 1})
                              .set_stride({kHeads * c.sq, c.sq, 1, 1}).set_data_type(fe::DataType_t::FLOAT));
    auto opts = fe::graph::SDPA_backward_attributes().set_name("sdpa_backward").set_attn_scale(scale);
    auto [dQ, dK, dV] = g.sdpa_backward(Q, K, V, O, dO, Stats, opts);
    dQ->set_output(true).set_uid(7).set_dim({c.b, kHeads, c.sq, kDim}).set_stride(bshd_stride(c.sq));
    dK->set_output(true).set_uid(8).set_dim({c.b, kHeads, c.skv, kDim}).set_stride(bshd_stride(c.skv));
    dV->set_output(true).set_uid(9).set_dim({c.b, kHeads, c.skv, kDim}).set_stride(bshd_stride(c.skv));
    ptrs[4] = t.o.data_ptr();
    ptrs[5] = t.stats.data_ptr();
    ptrs[6] = t.d_o.data_ptr();
    for (int64_t uid : {7, 8, 9}) {
      auto buf = torch::empty_like(uid == 7 ? t.q : t.k);
      ptrs[uid] = buf.data_ptr();
      outputs.emplace_back(uid, buf);
    }
  }
  const std::string what = fmt::format("{} {} mode {} impl {}", c.name, backward ? "backward" : "forward", mode, impl);
  auto status = g.validate();
  if (status.is_good()) status = g.build_operation_graph(handle);
  if (status.is_good()) status = g.create_execution_plans({heur_mode(mode)});
  if (status.is_good()) status = g.check_support(handle);
  if (status.is_good()) status = g.build_plans(handle, fe::BuildPlanPolicy_t::ALL);
  if (!status.is_good()) {
    fmt::print("| {} | - | no plan: {} | | | |\n", what, status.get_message().substr(0, 120));
    return;
  }
  const int64_t n = g.get_execution_plan_count();
  std::unordered_map<int64_t, void*> pack(ptrs.begin(), ptrs.end());
  for (int64_t i = 0; i < n; ++i) {
    std::string name;
    (void)g.get_plan_name_at_index(i, name);
    int64_t ws = 0;
    if (!g.get_workspace_size_plan_at_index(i, ws).is_good()) continue;
    auto workspace = torch::empty({std::max<int64_t>(ws, 1)}, t.q.options().dtype(torch::kUInt8));
    auto run = [&] { check_fe(g.execute_plan_at_index(handle, pack, workspace.data_ptr(), i), what + " execute"); };
    try {
      run();
      torch::cuda::synchronize();
    } catch (const std::exception& e) {
      fmt::print("| {} | {} | {} | failed: {} | | |\n", what, i, name, std::string(e.what()).substr(0, 100));
      continue;
    }
    double diff = 0;
    for (size_t j = 0; j < outputs.size() && j < ref.size(); ++j)
      diff = std::max(diff, (outputs[j].second.to(torch::kFloat32) - ref[j].to(torch::kFloat32)).abs().max().item<double>());
    const double ms = time_ms(run, a.iters, a.warmup);
    fmt::print("| {} | {} | {} | {:.3f} | {:.2f} | {:.3g} |\n", what, i, name.substr(0, 70), ms, ref_ms / ms, diff);
  }
}

// The same attention in FP8 (e4m3 Q, K, V, O, dO and gradients, unit scales; cuDNN's FP8 SDPA nodes, the
// heuristic's first plan): how much faster the opt-in FP8 training mode's attention could run. Timing and a
// coarse output check only (the values are rounded to e4m3); bf16_*: PyTorch's bf16 times of the same shape.
void run_fp8(cudnnHandle_t handle, const Case& c, const Tensors& t, double bf16_fwd_ms, double bf16_bwd_ms, const Args& a) {
  using TA = fe::graph::Tensor_attributes;
  using Map = std::unordered_map<std::shared_ptr<TA>, void*>;
  const auto f8 = torch::kFloat8_e4m3fn;
  auto q8 = t.q.to(f8), k8 = t.k.to(f8), v8 = t.v.to(f8), o8 = t.o.to(f8), do8 = t.d_o.to(f8);
  auto one = torch::ones({1, 1, 1, 1}, t.q.options().dtype(torch::kFloat32));
  std::vector<torch::Tensor> held;  // amax outputs and gradients
  auto build = [&](fe::graph::Graph& g, Map& m, bool backward) {
    g.set_io_data_type(fe::DataType_t::FP8_E4M3).set_intermediate_data_type(fe::DataType_t::FLOAT).set_compute_data_type(
        fe::DataType_t::FLOAT);
    auto tensor = [&](const char* name, int64_t s, void* p) {
      auto x = g.tensor(TA().set_name(name).set_dim({c.b, kHeads, s, kDim}).set_stride(bshd_stride(s)));
      m[x] = p;
      return x;
    };
    auto scalar = [&](const char* name) {
      auto x = g.tensor(TA().set_name(name).set_dim({1, 1, 1, 1}).set_stride({1, 1, 1, 1}).set_data_type(fe::DataType_t::FLOAT));
      m[x] = one.data_ptr();
      return x;
    };
    auto out = [&](const std::shared_ptr<TA>& x, const torch::Tensor& like, bool amax) {
      auto buf = amax ? torch::empty({1, 1, 1, 1}, one.options()) : torch::empty_like(like);
      held.push_back(buf);
      x->set_output(true);
      if (amax) x->set_dim({1, 1, 1, 1}).set_stride({1, 1, 1, 1}).set_data_type(fe::DataType_t::FLOAT);
      m[x] = buf.data_ptr();
    };
    const float scale = 1.0f / std::sqrt(static_cast<float>(kDim));
    auto Q = tensor("Q", c.sq, q8.data_ptr()), K = tensor("K", c.skv, k8.data_ptr()), V = tensor("V", c.skv, v8.data_ptr());
    if (!backward) {
      auto opts = fe::graph::SDPA_fp8_attributes().set_name("sdpa_fp8").set_generate_stats(true).set_attn_scale(scale);
      auto [O, Stats, amax_s, amax_o] = g.sdpa_fp8(Q, K, V, scalar("dq"), scalar("dk"), scalar("dv"), scalar("ds"),
                                                   scalar("ss"), scalar("so"), opts);
      O->set_dim({c.b, kHeads, c.sq, kDim}).set_stride(bshd_stride(c.sq));
      out(O, o8, false);
      Stats->set_data_type(fe::DataType_t::FLOAT);
      out(Stats, t.stats, false);
      out(amax_s, one, true);
      out(amax_o, one, true);
      return;
    }
    auto O = tensor("O", c.sq, o8.data_ptr()), dO = tensor("dO", c.sq, do8.data_ptr());
    auto Stats = g.tensor(TA().set_name("Stats").set_dim({c.b, kHeads, c.sq, 1}).set_stride({kHeads * c.sq, c.sq, 1, 1})
                              .set_data_type(fe::DataType_t::FLOAT));
    m[Stats] = t.stats.data_ptr();
    auto opts = fe::graph::SDPA_fp8_backward_attributes().set_name("sdpa_fp8_backward").set_attn_scale(scale);
    auto r = g.sdpa_fp8_backward(Q, K, V, O, dO, Stats, scalar("dq"), scalar("dk"), scalar("dv"), scalar("do"),
                                 scalar("ddo"), scalar("ds"), scalar("ddp"), scalar("ss"), scalar("sdq"), scalar("sdk"),
                                 scalar("sdv"), scalar("sdp"), opts);
    r[0]->set_dim({c.b, kHeads, c.sq, kDim}).set_stride(bshd_stride(c.sq));
    r[1]->set_dim({c.b, kHeads, c.skv, kDim}).set_stride(bshd_stride(c.skv));
    r[2]->set_dim({c.b, kHeads, c.skv, kDim}).set_stride(bshd_stride(c.skv));
    out(r[0], q8, false);
    out(r[1], k8, false);
    out(r[2], v8, false);
    for (int i = 3; i < 7; ++i) out(r[i], one, true);
  };
  for (const bool backward : {false, true}) {
    fe::graph::Graph g;
    Map m;
    build(g, m, backward);
    const std::string what = fmt::format("{} FP8 {}", c.name, backward ? "backward" : "forward");
    auto status = g.build(handle, {fe::HeurMode_t::A});
    if (!status.is_good()) {
      fmt::print("| {} | - | no plan: {} | | | |\n", what, status.get_message().substr(0, 160));
      continue;
    }
    int64_t ws = 0;
    check_fe(g.get_workspace_size(ws), what + " workspace");
    auto workspace = torch::empty({std::max<int64_t>(ws, 1)}, t.q.options().dtype(torch::kUInt8));
    auto run = [&] { check_fe(g.execute(handle, m, workspace.data_ptr()), what + " execute"); };
    run();
    torch::cuda::synchronize();
    const double ms = time_ms(run, a.iters, a.warmup);
    const double ref = backward ? bf16_bwd_ms : bf16_fwd_ms;
    fmt::print("| {} | 0 | first plan | {:.3f} | {:.2f} (vs PyTorch bf16) | |\n", what, ms, ref / ms);
  }
}

void run_case(cudnnHandle_t handle, const Case& c, const Args& a) {
  const auto o = torch::TensorOptions().device(torch::kCUDA).dtype(c.dtype);
  Tensors t;
  t.q = torch::randn({c.b, c.sq, kHeads, kDim}, o);
  t.k = torch::randn({c.b, c.skv, kHeads, kDim}, o);
  t.v = torch::randn({c.b, c.skv, kHeads, kDim}, o);
  t.d_o = torch::randn({c.b, c.sq, kHeads, kDim}, o);
  auto perm = [](const torch::Tensor& x) { return x.permute({0, 2, 1, 3}); };  // [B, H, S, D] views
  // PyTorch's cuDNN SDPA: the reference outputs and times.
  const double flops_fwd = 4.0 * c.b * kHeads * static_cast<double>(c.sq) * c.skv * kDim;
  if (!c.training) {
    torch::NoGradGuard ng;
    auto ref = perm(at::scaled_dot_product_attention(perm(t.q), perm(t.k), perm(t.v)));
    const double ms = time_ms([&] { (void)at::scaled_dot_product_attention(perm(t.q), perm(t.k), perm(t.v)); }, a.iters, a.warmup);
    fmt::print("\n{}: B {} x {} queries x {} keys, {}; PyTorch SDPA forward {:.3f} ms ({:.0f} TFLOP/s)\n", c.name, c.b, c.sq,
               c.skv, c10::toString(c.dtype), ms, flops_fwd / ms / 1e9);
    fmt::print("| graph | plan | name | ms | vs PyTorch | max abs diff |\n|---|---|---|---|---|---|\n");
    for (const auto& m : a.modes) run_graph(handle, c, false, m, a.implementation, t, {ref.contiguous()}, ms, a);
    return;
  }
  auto out = at::_scaled_dot_product_cudnn_attention(perm(t.q), perm(t.k), perm(t.v), {}, /*compute_log_sumexp=*/true);
  t.o = perm(std::get<0>(out)).contiguous();
  t.stats = std::get<1>(out).reshape({c.b, kHeads, c.sq, 1}).contiguous();
  const double fwd_ms = time_ms(
      [&] { (void)at::_scaled_dot_product_cudnn_attention(perm(t.q), perm(t.k), perm(t.v), {}, true); }, a.iters, a.warmup);
  // The backward through autograd, as the trainer runs it.
  auto q = perm(t.q).detach().requires_grad_(), k = perm(t.k).detach().requires_grad_(),
       v = perm(t.v).detach().requires_grad_();
  auto y = at::scaled_dot_product_attention(q, k, v);
  auto grads = torch::autograd::grad({y}, {q, k, v}, {perm(t.d_o)}, /*retain_graph=*/true);
  const double bwd_ms =
      time_ms([&] { (void)torch::autograd::grad({y}, {q, k, v}, {perm(t.d_o)}, /*retain_graph=*/true); }, a.iters, a.warmup);
  fmt::print("\n{}: B {} x {} queries x {} keys, {}; PyTorch SDPA forward {:.3f} ms ({:.0f} TFLOP/s), backward {:.3f} ms "
             "({:.0f} TFLOP/s)\n",
             c.name, c.b, c.sq, c.skv, c10::toString(c.dtype), fwd_ms, flops_fwd / fwd_ms / 1e9, bwd_ms,
             2.5 * flops_fwd / bwd_ms / 1e9);
  fmt::print("| graph | plan | name | ms | vs PyTorch | max abs diff |\n|---|---|---|---|---|---|\n");
  for (const auto& m : a.modes) run_graph(handle, c, false, m, a.implementation, t, {t.o, t.stats}, fwd_ms, a);
  std::vector<torch::Tensor> ref_grads;
  for (auto& gr : grads) ref_grads.push_back(perm(gr).contiguous());
  for (const auto& m : a.modes) run_graph(handle, c, true, m, "auto", t, ref_grads, bwd_ms, a);
  if (a.fp8) run_fp8(handle, c, t, fwd_ms, bwd_ms, a);
}

void run(const Args& a) {
  if (!torch::cuda::is_available()) {
    fmt::print("bench_cudnn_sdpa needs a CUDA device (none here)\n");
    return;
  }
  (void)torch::ones({1}, torch::kCUDA);  // CUDA and LibTorch's libcudnn loaded
  fe::cudnn_dlhandle = dlopen("libcudnn.so.9", RTLD_NOW | RTLD_NOLOAD);
  SIMU_CHECK(fe::cudnn_dlhandle != nullptr, "bench_cudnn_sdpa: libcudnn.so.9 is not loaded in this process: {}", dlerror());
  cudnnHandle_t handle = nullptr;
  SIMU_CHECK(fe::detail::create_handle(&handle) == CUDNN_STATUS_SUCCESS, "bench_cudnn_sdpa: cudnnCreate failed");
  SIMU_CHECK(fe::detail::set_stream(handle, at::cuda::getCurrentCUDAStream()) == CUDNN_STATUS_SUCCESS,
             "bench_cudnn_sdpa: cudnnSetStream failed");
  fmt::print("cuDNN backend {}, frontend {}; plans per heuristic mode, timed over {} runs after {}\n",
             fe::detail::get_backend_version(), CUDNN_FRONTEND_VERSION, a.iters, a.warmup);
  torch::manual_seed(0);
  for (const auto& name : a.cases) {
    if (name == "train-self") run_case(handle, {name, 4, 4096, 4096, true, torch::kBFloat16}, a);
    if (name == "sample-self") run_case(handle, {name, 2, 4096, 4096, false, torch::kHalf}, a);
    for (int64_t L : a.cond_lens) {
      if (name == "train-cross") run_case(handle, {name, 2, 8192, L, true, torch::kBFloat16}, a);
      if (name == "sample-cross") run_case(handle, {name, 1, 4096, L, false, torch::kHalf}, a);
    }
  }
  (void)fe::detail::destroy_handle(handle);
}

}  // namespace
#else
namespace {
struct Args {
  std::vector<std::string> cases, modes;
  std::vector<int64_t> cond_lens;
  int iters = 20, warmup = 3;
  std::string implementation = "auto";
  bool fp8 = false;
};
void run(const Args&) {
  fmt::print("bench_cudnn_sdpa was built without the cuDNN frontend headers (pip install nvidia-cudnn-frontend, then "
             "configure again): nothing to run\n");
}
}  // namespace
#endif

int main(int argc, char** argv) {
  CLI::App app{"Every cuDNN execution plan for the flow model's attention shapes against PyTorch's SDPA"};
  Args a;
  app.add_option("--cases", a.cases, "train-self | train-cross | sample-self | sample-cross")
      ->check(CLI::IsMember({"train-self", "train-cross", "sample-self", "sample-cross"}))->capture_default_str();
  app.add_option("--cond-lens", a.cond_lens, "condition lengths of the cross cases")->capture_default_str();
  app.add_option("--modes", a.modes, "cuDNN heuristic modes asked for plans: A | B | FALLBACK | OPENSOURCE")
      ->check(CLI::IsMember({"A", "B", "FALLBACK", "OPENSOURCE"}))->capture_default_str();
  app.add_option("--implementation", a.implementation, "forward SDPA node: auto | unified | composite")
      ->check(CLI::IsMember({"auto", "unified", "composite"}))->capture_default_str();
  app.add_option("--fp8", a.fp8, "also time the training cases in FP8 (e4m3, cuDNN's FP8 SDPA nodes)")->capture_default_str();
  app.add_option("--iters", a.iters, "timed runs per plan")->capture_default_str()->check(CLI::PositiveNumber);
  app.add_option("--warmup", a.warmup, "untimed runs first")->capture_default_str()->check(CLI::NonNegativeNumber);
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&] {
    run(a);
    return 0;
  });
}
