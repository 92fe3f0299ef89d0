// CUDA graphs of the Stage-1 sampler (generator.h): GraphedForward (capture and replay of one backbone
// forward) and the persistent per-shape sampling graphs of ClassifierFreeGuidance (attach_graph).
#include <fmt/ranges.h>

#include <ATen/autocast_mode.h>

#include <algorithm>
#include <atomic>
#include <set>

#include "common/error.h"
#include "models/generator.h"
#include "models/linear.h"

#ifdef SIMU_HAVE_CUDA_KERNELS
#include <ATen/cuda/CUDAEvent.h>
#include <ATen/cuda/CUDAGraph.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#endif

namespace simu::models {

// ---------------------------------------------------------------------------------------------
// CUDA graphs

struct GraphedForward::State {
  SparseStructureFlowTdfyWrapper backbone{nullptr};
  torch::Tensor cond;
  const ConditionCache* cache = nullptr;
  // Static inputs (the graph reads these addresses) and the outputs it writes.
  Latents x, y;
  torch::Tensor t, d;
#ifdef SIMU_HAVE_CUDA_KERNELS
  std::unique_ptr<at::cuda::CUDAGraph> graph;
#endif
};

GraphedForward::GraphedForward(SparseStructureFlowTdfyWrapper backbone, torch::Tensor cond, const ConditionCache* cache)
    : s_(std::make_unique<State>()) {
  s_->backbone = std::move(backbone);
  s_->cond = std::move(cond);
  s_->cache = cache;
}

GraphedForward::~GraphedForward() = default;

namespace {
std::atomic<int64_t> g_graph_replays{0};
std::atomic<int64_t> g_graph_captures{0};
}  // namespace

int64_t GraphedForward::replay_count() { return g_graph_replays.load(); }
int64_t GraphedForward::capture_count() { return g_graph_captures.load(); }

namespace {
std::atomic<bool> g_overlapped_capture{true};
}  // namespace

void GraphedForward::set_overlapped_capture(bool on) { g_overlapped_capture = on; }
bool GraphedForward::overlapped_capture() { return g_overlapped_capture.load(); }

#ifdef SIMU_HAVE_CUDA_KERNELS
namespace {
// What a capture needs: the forward's static inputs, the two streams, the graph and where its outputs go.
struct CaptureArgs {
  SparseStructureFlowTdfyWrapper& backbone;
  const Latents& x;
  const torch::Tensor& t;
  const c10::optional<torch::Tensor>& d;
  const torch::Tensor& cond;
  const ConditionCache* cache;
  c10::cuda::CUDAStream main, side;
  at::cuda::CUDAGraph* graph;
  Latents* y;
};

// Records one backbone forward into a.graph (writing *a.y) on the current stream; the capture is ended
// also when the forward throws.
void record_forward(CaptureArgs& a) {
  a.graph->capture_begin({0, 0}, cudaStreamCaptureModeThreadLocal);
  try {
    *a.y = a.backbone->forward(a.x, a.t, a.cond, a.d, a.cache);
  } catch (...) {
    try {
      a.graph->capture_end();
    } catch (...) {
    }
    throw;
  }
  a.graph->capture_end();
}

// Host-synchronous capture (the earlier scheme): wait for the device, a discarded eager warm-up
// forward on a side stream, wait again, capture, wait again.
void capture_synchronous(CaptureArgs& a) {
  a.main.synchronize();
  const c10::cuda::CUDAStreamGuard stream_guard(a.side);
  (void)a.backbone->forward(a.x, a.t, a.cond, a.d, a.cache);
  a.side.synchronize();
  record_forward(a);
  a.side.synchronize();
}

// Overlapped capture: the warm-up forward is this evaluation's own (its result is returned), and the
// capture, which only records launches, follows it on the same side stream without waiting for the
// device: the host records the graph while the device still runs the warm-up. Events order the side
// stream after the main stream's inputs and the main stream after the warm-up.
Latents capture_overlapped(CaptureArgs& a) {
  at::cuda::CUDAEvent inputs_ready;
  inputs_ready.record(a.main);
  inputs_ready.block(a.side);
  Latents y_eager;
  {
    const c10::cuda::CUDAStreamGuard stream_guard(a.side);
    y_eager = a.backbone->forward(a.x, a.t, a.cond, a.d, a.cache);
    record_forward(a);
  }
  at::cuda::CUDAEvent warmup_done;
  warmup_done.record(a.side);
  warmup_done.block(a.main);
  // The warm-up's outputs were allocated on the side stream and are read on the main one from now on.
  for (auto& [k, v] : y_eager) v.record_stream(a.main);
  return y_eager;
}
}  // namespace
#endif

Latents GraphedForward::run(const Latents& x, const torch::Tensor& t, const c10::optional<torch::Tensor>& d) {
  auto& s = *s_;
#ifdef SIMU_HAVE_CUDA_KERNELS
  if (s.cond.is_cuda()) {
    if (!s.graph) {
      // Static input buffers with the first call's shapes, filled with this call's inputs.
      for (const auto& [k, v] : x) s.x[k] = v.clone();
      s.t = t.clone();
      if (d) s.d = d->clone();
      c10::optional<torch::Tensor> dd;
      if (s.d.defined()) dd = s.d;
      const c10::cuda::CUDAGuard device_guard(s.cond.device());
      auto graph = std::make_unique<at::cuda::CUDAGraph>();
      CaptureArgs a{s.backbone, s.x, s.t, dd, s.cond, s.cache, c10::cuda::getCurrentCUDAStream(),
                    c10::cuda::getStreamFromPool(false, s.cond.device().index()), graph.get(), &s.y};
      if (overlapped_capture()) {
        // Kernel plans, workspaces and the autocast cache's weight copies come from the warm-up,
        // which is this evaluation: its result is the answer, no replay this time.
        auto y = capture_overlapped(a);
        s.graph = std::move(graph);
        ++g_graph_captures;
        return y;
      }
      capture_synchronous(a);
      s.graph = std::move(graph);
      ++g_graph_captures;
    }
    // Copy the inputs in (same shapes as captured), replay.
    for (const auto& [k, v] : x) {
      const auto it = s.x.find(k);
      SIMU_CHECK(it != s.x.end() && it->second.sizes() == v.sizes(),
                 "graphed forward: latent '{}' [{}] does not match the captured shape", k, fmt::join(v.sizes(), ", "));
      it->second.copy_(v);
    }
    SIMU_CHECK(t.sizes() == s.t.sizes() && d.has_value() == s.d.defined() && (!d || d->sizes() == s.d.sizes()),
               "graphed forward: t/d shapes differ from the captured ones");
    s.t.copy_(t);
    if (d) s.d.copy_(*d);
    s.graph->replay();
    ++g_graph_replays;
    // Copies out (latents are small): a later replay overwrites the graph's outputs.
    Latents out;
    for (const auto& [k, v] : s.y) out[k] = v.clone();
    return out;
  }
#endif
  return s.backbone->forward(x, t, s.cond, d, s.cache);
}

namespace {
// What a captured forward depends on besides its inputs: every parameter's storage and dtype (an
// in-place update keeps it, a reload or .to() does not), which Linear adapters are on, the kernel
// switches and the train/eval mode.
uint64_t graph_fingerprint(SparseStructureFlowTdfyWrapper& bb) {
  uint64_t h = 1469598103934665603ull;
  auto mix = [&](uint64_t v) {
    h ^= v;
    h *= 1099511628211ull;
  };
  for (const auto& p : bb->parameters()) {
    mix(reinterpret_cast<uintptr_t>(p.data_ptr()));
    mix(static_cast<uint64_t>(p.scalar_type()));
    mix(p.requires_grad());
  }
  for (const auto& m : bb->modules())
    if (const auto* l = dynamic_cast<const LinearImpl*>(m.get())) {
      mix(reinterpret_cast<uintptr_t>(l->adapter().get()));
      mix(l->adapter_enabled());
    }
  mix(bb->fused_kernels());
  mix(bb->training_kernels());
  mix(bb->is_training());
  mix(bb->stream_lag());
  return h;
}
}  // namespace

std::shared_ptr<SamplingGraph> ClassifierFreeGuidanceImpl::attach_graph(const torch::Tensor& c, const Latents& xs,
                                                                       const torch::Tensor& t,
                                                                       const c10::optional<torch::Tensor>& d,
                                                                       int64_t zero_from) {
  // The shapes, dtypes and autocast state the capture is valid for.
  std::string key = fmt::format("{} {} [{}] {} t[{}] d[{}] ac {} {}", c.device().str(), c10::toString(c.scalar_type()),
                                fmt::join(c.sizes(), ","), xs.size(), fmt::join(t.sizes(), ","),
                                d ? fmt::format("{}", fmt::join(d->sizes(), ",")) : std::string("-"),
                                at::autocast::is_autocast_enabled(at::kCUDA),
                                c10::toString(at::autocast::get_autocast_dtype(at::kCUDA)));
  key += fmt::format(" zero_from {}", zero_from);
  for (const auto& [k, v] : xs) key += fmt::format(" {}[{}]{}", k, fmt::join(v.sizes(), ","), c10::toString(v.scalar_type()));
  const uint64_t fp = graph_fingerprint(backbone);
  auto& gs = graph_cache.graphs;
  std::shared_ptr<SamplingGraph> g;
  for (auto it = gs.begin(); it != gs.end(); ++it)
    if ((*it)->key == key) {
      if ((*it)->fingerprint == fp) g = *it;
      else gs.erase(it);  // the model changed under it: capture again
      break;
    }
  if (g) {
    // A later call: this call's condition and its keys/values into the graph's buffers, and the
    // weights' current values into the copies the graph reads.
    g->cond.copy_(c);
    backbone->condition_cache_into(g->cond, g->kv);
    g->refresh_weights();
  } else {
    g = std::make_shared<SamplingGraph>();
    g->key = key;
    g->fingerprint = fp;
    g->cond = c.clone();
    g->kv = backbone->condition_cache(g->cond, zero_from);
    g->graph = std::make_unique<GraphedForward>(backbone, g->cond, &g->kv);
    g->last_use = ++graph_cache.tick;
    gs.push_back(g);
    while (gs.size() > std::max<size_t>(graph_cache.max_graphs, 1)) {
      auto oldest = std::min_element(gs.begin(), gs.end(), [](const auto& a, const auto& b) { return a->last_use < b->last_use; });
      gs.erase(oldest);
    }
  }
  g->last_use = ++graph_cache.tick;
  return g;
}

void SamplingGraph::remember_weights(SparseStructureFlowTdfyWrapper& backbone) {
  weights_known = true;
  if (!at::autocast::is_autocast_enabled(at::kCUDA)) return;
  const auto low = at::autocast::get_autocast_dtype(at::kCUDA);
  // Linear layers with a compute copy in the autocast dtype: the capture read the copy (sampling runs
  // without grad mode, so it applied), not an autocast cast of the weight.
  std::set<const c10::TensorImpl*> through_copy;
  for (const auto& m : backbone->modules()) {
    const auto* l = dynamic_cast<const LinearImpl*>(m.get());
    if (!l || !l->compute_copy() || l->compute_copy()->dtype() != low || !l->compute_copy()->fits(l->weight, l->bias)) continue;
    copies.push_back({l->weight, l->bias, l->compute_copy()});
    through_copy.insert(l->weight.unsafeGetTensorImpl());
    if (l->bias.defined()) through_copy.insert(l->bias.unsafeGetTensorImpl());
  }
  // The other weights: the autocast cache's copies (cached_cast returns the cached one).
  for (const auto& p : backbone->parameters())
    if (p.is_cuda() && p.scalar_type() == torch::kFloat32 && p.requires_grad() && p.is_leaf() &&
        !through_copy.count(p.unsafeGetTensorImpl()))
      weights.emplace_back(p, at::autocast::cached_cast(low, p, c10::DeviceType::CUDA));
}

void SamplingGraph::refresh_weights() {
  for (auto& [p, w] : weights) w.copy_(p);
  for (auto& c : copies) c.copy->refresh(c.weight, c.bias);
}

}  // namespace simu::models
