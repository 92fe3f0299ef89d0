#include "training/trainer.h"

#include <ATen/CPUGeneratorImpl.h>
#include <ATen/cuda/CUDAEvent.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <numeric>
#include <random>
#include <sstream>

#include <fmt/ranges.h>

#include "common/cancel.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "common/timing.h"
#include "data/pair_cache.h"
#include "lora/lora_config.h"
#include "models/precision.h"
#include "training/launcher.h"
#include "training/observe.h"

namespace simu::training {

std::map<std::string, double> StepMetrics::scalars() const {
  std::map<std::string, double> m{{"loss", loss},           {"accuracy", accuracy}, {"margin", margin},
                                  {"grad_norm", grad_norm}, {"lr", lr},             {"pairs_per_s", pairs_per_s},
                                  {"time/step_s", seconds_step},           {"time/data_wait_s", seconds_data},
                                  {"time/compute_s", seconds_compute},     {"time/allreduce_s", seconds_allreduce},
                                  {"time/optimizer_s", seconds_optimizer}};
  for (const auto& [k, v] : per_kind) m[k] = v;
  return m;
}

// ---- trainer ---------------------------------------------------------------------------------

// One forward group's inputs, stacked [m, ...] in their stored dtype on the trainer's device.
struct StagedGroup {
  std::vector<int> kinds;                                  // the pairs' kinds, in order
  torch::Tensor x_pos, x_neg, eps_pos, eps_neg;            // [m, T, C]
  torch::Tensor t, w;                                      // [m]
  torch::Tensor cond;                                      // [m, L, Cc] tokens; undefined in inputs mode
  std::map<std::string, torch::Tensor> inputs;             // inputs mode: kwarg -> [m, ch, S, S]
  std::vector<torch::Tensor> host;                         // pinned staging buffers, held to the step's end
  std::shared_ptr<at::cuda::CUDAEvent> ready;              // recorded after its copies (upload stream)
  // The device tensors above.
  std::vector<torch::Tensor*> device_tensors() {
    std::vector<torch::Tensor*> out = {&x_pos, &x_neg, &eps_pos, &eps_neg, &t, &w};
    if (cond.defined()) out.push_back(&cond);
    for (auto& [name, v] : inputs) out.push_back(&v);
    return out;
  }
};

struct StagedBatch {
  DataPosition position;  // the source's position before this batch
  int64_t step = 0;       // the step whose noise it holds
  int64_t pairs = 0;
  std::vector<StagedGroup> groups;
};

struct StepTail {
  Clock::time_point compute_began;             // its forwards' start
  double seconds_data = 0, seconds_ahead = 0;  // reading this step's batch; reading the next one ahead
  torch::Tensor terms;                         // [7, pairs] per-pair metric terms on the device
  std::vector<int> kinds;                      // the pairs' kinds, in order
  std::vector<at::cuda::CUDAEvent> phase;      // device path: compute start, backward end, all-reduce end, update end
};

namespace {

const char* kKindNames[2] = {"completion", "preservation"};

// The step's means over its n pairs (all ranks): loss, accuracy, margin and each pair kind's losses.
void set_means(const StepSums& sums, double n, StepMetrics& m) {
  m.loss = sums.loss / n;
  m.accuracy = sums.correct / n;
  m.margin = sums.margin / n;
  for (int k = 0; k < 2; ++k) {
    const auto& s = sums.kind[k];
    if (s.count == 0) continue;
    const std::string kn = kKindNames[k];
    m.per_kind[kn + "/policy_pos"] = s.policy_pos / s.count;
    m.per_kind[kn + "/policy_neg"] = s.policy_neg / s.count;
    m.per_kind[kn + "/ref_pos"] = s.ref_pos / s.count;
    m.per_kind[kn + "/ref_neg"] = s.ref_neg / s.count;
  }
}

// The CPU and (when used) CUDA default generators' states, as uint8 tensors under rng.*.
std::map<std::string, torch::Tensor> rng_states(const torch::Device& device) {
  std::map<std::string, torch::Tensor> out;
  out["rng.torch_cpu"] = at::detail::getDefaultCPUGenerator().get_state();
  if (device.is_cuda()) {
    at::Generator g = at::globalContext().defaultGenerator(device);
    out["rng.torch_cuda"] = g.get_state();
  }
  return out;
}

}  // namespace

Trainer::Trainer(TrainConfig cfg, PolicyModel& model, PairSourceFactory sources, Communicator& comm,
                 torch::Device device)
    : cfg_(std::move(cfg)), model_(model), make_source_(std::move(sources)), comm_(comm), device_(device),
      read_ahead_(device.is_cuda()) {
  if (device_.is_cuda()) upload_stream_ = c10::cuda::getStreamFromPool(false, device_.index()).unwrap();
  const int64_t world = comm_.world_size();
  const int64_t per_rank = cfg_.data.global_batch / world;
  if (cfg_.data.global_batch % (world * cfg_.data.micro_batch) != 0)
    fail_hint("choose global_batch = micro_batch x accumulation x world size",
              "{}: data.global_batch {} is not divisible by micro_batch {} x world size {}", cfg_.file,
              cfg_.data.global_batch, cfg_.data.micro_batch, world);
  (void)per_rank;
  opt_ = std::make_unique<AdamW>(model_.adapter_parameters(), cfg_.optim);
  source_ = make_source_(comm_.rank(), comm_.world_size(), cfg_.data.global_batch, cfg_.data.seed, DataPosition{});
  // Every rank must start from the same adapters (gradients are averaged, never the weights): compare
  // a fingerprint of them across ranks (sum and sum of squares of the per-rank sums).
  if (world > 1) {
    double fp = 0;
    for (const auto& [name, p] : opt_->params()) fp += p.detach().to(torch::kFloat64).sum().item<double>() * (1 + 1e-3 * fp);
    const auto s = comm_.all_reduce_sum({fp, fp * fp});
    const double mean = s[0] / world, var = s[1] / world - mean * mean;
    if (var > 1e-18 * std::max(1.0, mean * mean))
      fail_hint("seed every rank alike (train.seed) before the adapters are created",
                "rank {}: the adapters differ across the {} ranks at the start (fingerprint {} vs mean {})", comm_.rank(),
                world, fp, mean);
  }
}

CheckpointData Trainer::checkpoint_data() const {
  CheckpointData d;
  d.step = step_;
  for (const auto& [name, p] : opt_->params()) d.adapter[name] = p.detach().to(torch::kCPU).clone();
  d.optimizer = opt_->state_dict();
  for (auto& [k, v] : rng_states(device_)) d.optimizer[k] = v;
  // The position of the next batch a step will train on (a batch read ahead is not trained on yet).
  const auto pos = ahead_ ? ahead_->position : source_->position();
  std::ostringstream cfg;
  cfg << cfg_.resolved;
  d.state = {{"data_position", {{"epoch", pos.epoch}, {"step", pos.step}}},
             {"seed", cfg_.train.seed},
             {"data_seed", cfg_.data.seed},
             {"world_size", comm_.world_size()},
             {"global_batch", cfg_.data.global_batch},
             {"micro_batch", cfg_.data.micro_batch},
             {"lr_next", learning_rate(cfg_.optim, step_, cfg_.train.steps)},
             {"schedule", {{"kind", cfg_.optim.schedule}, {"warmup_steps", cfg_.optim.warmup_steps},
                           {"total_steps", cfg_.train.steps}}},
             {"config", cfg.str()}};
  return d;
}

std::string Trainer::save() {
  std::string dir;
  if (comm_.rank() == 0) dir = save_checkpoint(cfg_.run.out_dir + "/checkpoints", checkpoint_data(), cfg_.run.keep_last);
  comm_.barrier();
  return dir;
}

void Trainer::resume(const std::string& dir) {
  auto ck = load_checkpoint(dir);
  // Adapters: exactly the same names and shapes.
  std::vector<std::string> problems;
  for (const auto& [name, p] : opt_->params()) {
    auto it = ck.adapter.find(name);
    if (it == ck.adapter.end()) problems.push_back("missing " + name);
    else if (it->second.sizes() != p.sizes())
      problems.push_back(fmt::format("{}: shape {} vs {}", name, fmt::join(it->second.sizes(), "x"), fmt::join(p.sizes(), "x")));
  }
  if (ck.adapter.size() != opt_->params().size())
    problems.push_back(fmt::format("{} adapter tensors in the checkpoint, {} in the model", ck.adapter.size(),
                                   opt_->params().size()));
  if (!problems.empty()) fail("{}: checkpoint does not match the model's adapters:\n  {}", dir, fmt::join(problems, "\n  "));
  const int64_t gb = ck.state.value("global_batch", int64_t{-1});
  if (gb != cfg_.data.global_batch)
    fail("{}: checkpoint was trained with global batch {}, the config says {}", dir, gb, cfg_.data.global_batch);
  {
    torch::NoGradGuard ng;
    for (const auto& [name, p] : opt_->params()) p.copy_(ck.adapter.at(name));
  }
  std::map<std::string, torch::Tensor> opt_state;
  for (auto& [k, v] : ck.optimizer)
    if (k.rfind("rng.", 0) != 0) opt_state[k] = v;
  opt_->load_state_dict(opt_state, dir + "/optimizer.safetensors");
  // RNG states.
  if (auto it = ck.optimizer.find("rng.torch_cpu"); it != ck.optimizer.end())
  {
    at::Generator g = at::detail::getDefaultCPUGenerator();
    g.set_state(it->second);
  }
  if (device_.is_cuda())
    if (auto it = ck.optimizer.find("rng.torch_cuda"); it != ck.optimizer.end())
    {
      at::Generator g = at::globalContext().defaultGenerator(device_);
      g.set_state(it->second);
    }
  step_ = ck.step;
  DataPosition pos;
  pos.epoch = ck.state.at("data_position").at("epoch").get<int64_t>();
  pos.step = ck.state.at("data_position").at("step").get<int64_t>();
  ahead_.reset();
  source_ = make_source_(comm_.rank(), comm_.world_size(), cfg_.data.global_batch, cfg_.data.seed, pos);
  if (comm_.rank() == 0) simu::log::info("resumed from {} at step {} (data epoch {}, batch {})", dir, step_, pos.epoch, pos.step);
}

std::vector<double> StepSums::pack() const {
  std::vector<double> v = {loss, correct, margin};
  for (const auto& k : kind) v.insert(v.end(), {k.count, k.policy_pos, k.policy_neg, k.ref_pos, k.ref_neg});
  return v;
}

StepSums StepSums::unpack(const std::vector<double>& v) {
  SIMU_CHECK(v.size() == 13, "step sums: {} values, 13 expected", v.size());
  StepSums s;
  s.loss = v[0];
  s.correct = v[1];
  s.margin = v[2];
  for (int k = 0; k < 2; ++k) s.kind[k] = {v[3 + 5 * k], v[4 + 5 * k], v[5 + 5 * k], v[6 + 5 * k], v[7 + 5 * k]};
  return s;
}

namespace {

// Micro-batches of `micro` pairs; within one, pairs with different condition lengths run as separate
// forwards (the model has no condition mask, so padding would change the result).
std::vector<std::vector<int64_t>> forward_groups(const std::vector<Pair>& pairs, int64_t micro) {
  const int64_t share = static_cast<int64_t>(pairs.size());
  std::vector<std::vector<int64_t>> groups;
  for (int64_t m0 = 0; m0 < share; m0 += micro) {
    std::map<int64_t, std::vector<int64_t>> by_len;
    // Inputs-mode pairs (no tokens yet) all give the embedder's one length: key -1.
    for (int64_t i = m0; i < std::min(share, m0 + micro); ++i)
      by_len[pairs[i].cond.defined() ? pairs[i].cond.size(0) : -1].push_back(i);
    for (auto& [len, idx] : by_len) groups.push_back(idx);
  }
  return groups;
}

}  // namespace

Trainer::~Trainer() = default;

namespace {

// Host tensors stacked into [n, ...] on the device. With an upload stream: into a pinned host buffer
// (kept in `held`; the caching host allocator also keeps it from reuse until the copy is done), copied
// asynchronously on that stream into memory allocated on it. Without one (reference path, CPU):
// stack(...).to(device), a synchronous copy from pageable memory on CUDA.
torch::Tensor stack_to(const std::vector<torch::Tensor>& parts, const torch::Device& device,
                       const c10::optional<c10::Stream>& stream, std::vector<torch::Tensor>& held) {
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

// Makes the current (compute) stream wait for a group's uploads, and keeps their device memory from
// reuse by the upload stream until the compute stream is past this point.
void wait_for_uploads(StagedGroup& g, const torch::Device& device) {
  if (!g.ready) return;
  const auto compute = c10::cuda::getCurrentCUDAStream(device.index());
  g.ready->block(compute);
  for (auto* t : g.device_tensors()) t->record_stream(compute);
}

}  // namespace

std::unique_ptr<StagedBatch> Trainer::read_batch(int64_t step) {
  auto b = std::make_unique<StagedBatch>();
  b->position = source_->position();
  b->step = step;
  const auto pairs = source_->next_batch();
  b->pairs = static_cast<int64_t>(pairs.size());
  const c10::optional<c10::Stream> stream = read_ahead_ ? upload_stream_ : c10::nullopt;
  for (const auto& group : forward_groups(pairs, cfg_.data.micro_batch)) {
    StagedGroup g;
    auto up = [&](const std::vector<torch::Tensor>& parts) { return stack_to(parts, device_, stream, g.host); };
    // Stack the pairs, draw their noise (per pair: independent of rank, micro-batch and read-ahead).
    std::vector<torch::Tensor> xp, xn, ts, ep, en, ws;
    for (int64_t i : group) {
      const Pair& p = pairs[i];
      auto nz = draw_pair_noise(cfg_.train.seed, step, p.id, p.x_pos.sizes(), cfg_.objective.t_mean, cfg_.objective.t_std);
      xp.push_back(p.x_pos);
      xn.push_back(p.x_neg);
      ts.push_back(nz.t);
      ep.push_back(nz.eps_pos);
      en.push_back(nz.eps_neg);
      ws.push_back(torch::tensor(static_cast<float>(cfg_.objective.weight_of(p.kind))));
      g.kinds.push_back(static_cast<int>(p.kind));
    }
    // Stored dtype (f16 or f32) across the bus, fp32 on the device: the host does no conversion work.
    g.x_pos = up(xp);
    g.x_neg = up(xn);
    g.t = up(ts);
    g.eps_pos = up(ep);
    g.eps_neg = up(en);
    g.w = up(ws);
    // The condition: the pairs' tokens, or the embedder's inputs (embedded in the step).
    if (pairs[group.front()].cond.defined()) {
      std::vector<torch::Tensor> cd;
      for (int64_t i : group) cd.push_back(pairs[i].cond);
      g.cond = up(cd);
    } else {
      for (const auto& [name, first] : pairs[group.front()].inputs) {
        std::vector<torch::Tensor> parts;
        for (int64_t i : group) {
          const auto it = pairs[i].inputs.find(name);
          SIMU_CHECK(it != pairs[i].inputs.end(), "pair {} lacks condition input '{}'", pairs[i].id, name);
          parts.push_back(it->second);
        }
        g.inputs[name] = up(parts);
      }
    }
    if (stream) {
      g.ready = std::make_shared<at::cuda::CUDAEvent>();
      g.ready->record(c10::cuda::CUDAStream(c10::cuda::CUDAStream::UNCHECKED, *stream));
    }
    b->groups.push_back(std::move(g));
  }
  return b;
}

torch::Tensor Trainer::forward_backward(StagedBatch& batch) {
  const double beta = cfg_.objective.beta;
  const bool bf16 = cfg_.train.precision == "bf16" && device_.is_cuda();
  std::vector<torch::Tensor> metric_terms;
  for (auto& g : batch.groups) {
    wait_for_uploads(g, device_);
    FmdpoInputs in;
    in.x_pos = g.x_pos.to(torch::kFloat32);
    in.x_neg = g.x_neg.to(torch::kFloat32);
    in.t = g.t;
    in.eps_pos = g.eps_pos;
    in.eps_neg = g.eps_neg;
    in.w = g.w;
    if (g.cond.defined()) {
      in.cond = g.cond.to(torch::kFloat32);
    } else {
      if (!embed_)
        fail_hint("set model.embedder_config (and model.embedder_weights) in the training config",
                  "{}: the pair cache holds condition inputs (cond_mode inputs) but no condition embedder is loaded",
                  cfg_.file);
      std::map<std::string, torch::Tensor> inputs;
      for (const auto& [name, v] : g.inputs) inputs[name] = v.to(torch::kFloat32);  // [m, ch, S, S]
      // The frozen embedder: no gradient, the step's precision policy.
      torch::NoGradGuard no_grad;
      models::Autocast ac(models::Precision::kBf16, bf16);
      in.cond = embed_(inputs).to(torch::kFloat32);  // [m, L, Cc]
    }
    FmdpoTerms terms;
    {
      // CUDA bf16 autocast when enabled (adapters stay fp32; matmuls in bf16); nests, restores.
      models::Autocast ac(models::Precision::kBf16, bf16);
      terms = fmdpo_terms(model_, in, beta, cfg_.train.activation_checkpointing);
    }
    // Rank-local mean over its share; the all-reduce averages the ranks -> global mean.
    auto weighted = in.w * terms.per_pair;  // [m]
    (weighted.sum() / static_cast<double>(batch.pairs)).backward();
    // Per-pair metric terms stay on the device until the last micro-batch (no host sync in between):
    // rows weighted loss, d_theta, d_ref, policy +/-, reference +/-; one column per pair.
    metric_terms.push_back(torch::stack({weighted, terms.d_theta, terms.d_ref, terms.loss_pos_policy, terms.loss_neg_policy,
                                         terms.loss_pos_ref, terms.loss_neg_ref})
                               .detach()
                               .to(torch::kFloat32));  // [7, m]
  }
  return metric_terms.empty() ? torch::Tensor() : torch::cat(metric_terms, 1);  // [7, pairs]
}

StepSums Trainer::metric_sums(const torch::Tensor& terms, const std::vector<int>& kinds) const {
  const double beta = cfg_.objective.beta;
  // One copy to the host, then sums in float64 pair by pair (in micro-batch order).
  StepSums sums;
  if (!terms.defined()) return sums;
  auto host = terms.to(torch::kCPU, torch::kFloat64).contiguous();  // [7, pairs]
  auto a = host.accessor<double, 2>();
  for (int64_t b = 0; b < host.size(1); ++b) {
    sums.loss += a[0][b];
    sums.correct += a[1][b] < a[2][b] ? 1.0 : 0.0;
    sums.margin += -beta / 2.0 * (a[1][b] - a[2][b]);
    auto& k = sums.kind[std::clamp(kinds[b], 0, 1)];
    k.count += 1.0;
    k.policy_pos += a[3][b];
    k.policy_neg += a[4][b];
    k.ref_pos += a[5][b];
    k.ref_neg += a[6][b];
  }
  return sums;
}

StepMetrics Trainer::step() {
  const auto began = Clock::now();
  // This step's batch: read ahead by the previous step, or read and staged now.
  StepTail tail;
  std::unique_ptr<StagedBatch> batch;
  if (ahead_) {
    SIMU_CHECK(ahead_->step == step_,
               "trainer: the batch read ahead holds the noise of step {}, not of step {} (a failed step cannot be "
               "retried; resume from a checkpoint)", ahead_->step + 1, step_ + 1);
    batch = std::move(ahead_);
  } else {
    batch = read_batch(step_);
    tail.seconds_data = seconds_since(began);
  }
  tail.compute_began = Clock::now();
  const bool on_device = device_update_ && device_.is_cuda();
  if (on_device) {
    tail.phase.emplace_back(cudaEventDefault);
    tail.phase.back().record();
  }
  SIMU_CHECK(batch->pairs == cfg_.data.global_batch / comm_.world_size(), "data source gave {} pairs, {} expected",
             batch->pairs, cfg_.data.global_batch / comm_.world_size());
  opt_->zero_grad();
  tail.terms = forward_backward(*batch);
  for (const auto& g : batch->groups) tail.kinds.insert(tail.kinds.end(), g.kinds.begin(), g.kinds.end());
  // Read-ahead: the next batch is read and staged, its copies issued, while this step's kernels run.
  if (read_ahead_) {
    const auto ahead_began = Clock::now();
    ahead_ = read_batch(step_ + 1);
    tail.seconds_ahead = seconds_since(ahead_began);
  }
  StepMetrics m = on_device ? finish_on_device(tail) : finish_on_host(tail);
  ++step_;
  heartbeat();
  m.step = step_;
  m.seconds_step = seconds_since(began);
  m.pairs_per_s = static_cast<double>(cfg_.data.global_batch) / std::max(m.seconds_step, 1e-9);
  return m;
}

std::vector<torch::Tensor> Trainer::adapter_grads() {
  std::vector<torch::Tensor> grads;
  for (auto& p : opt_->tensors()) {
    if (!p.grad().defined()) p.mutable_grad() = torch::zeros_like(p);
    grads.push_back(p.grad());
  }
  return grads;
}

void Trainer::stop_if_non_finite(double global_loss, double grad_norm) const {
  // A non-finite loss or gradient (global values: every rank takes the same branch) stops training
  // before the optimizer touches the adapters, so the last checkpoint stays the last good state.
  if (!std::isfinite(global_loss) || !std::isfinite(grad_norm))
    fail_hint("lower optim.lr or objective.beta, check the pair cache (pairs validate), then --resume latest",
              "{}: step {}: non-finite {} (loss {}, gradient norm {}); training stopped before this update, the "
              "adapters and the checkpoints in {}/checkpoints are unchanged",
              cfg_.file, step_ + 1, std::isfinite(global_loss) ? "gradient" : "loss", global_loss, grad_norm,
              cfg_.run.out_dir);
}

// The reference path: each phase waits for the device (its wall time is the phase's), the metrics and
// the gradient norm come to the host before the update, which runs only when both are finite.
StepMetrics Trainer::finish_on_host(StepTail& tail) {
  auto settle = [&] {
    if (device_.is_cuda()) torch::cuda::synchronize();
  };
  StepSums sums = metric_sums(tail.terms, tail.kinds);
  // Average gradients over ranks, clip, step.
  auto params = opt_->tensors();
  auto grads = adapter_grads();
  settle();
  StepMetrics m;
  m.seconds_data = tail.seconds_data + tail.seconds_ahead;
  m.seconds_compute = seconds_since(tail.compute_began) - tail.seconds_ahead;
  auto phase_began = Clock::now();
  comm_.all_reduce_mean(grads);
  // Metrics over all ranks (before the update: a non-finite loss must stop it on every rank alike).
  sums = StepSums::unpack(comm_.all_reduce_sum(sums.pack()));
  settle();
  m.seconds_allreduce = seconds_since(phase_began);
  phase_began = Clock::now();
  m.grad_norm = clip_grad_norm(params, cfg_.optim.clip_grad_norm);
  m.lr = learning_rate(cfg_.optim, step_, cfg_.train.steps);
  stop_if_non_finite(sums.loss / static_cast<double>(cfg_.data.global_batch), m.grad_norm);
  opt_->step(m.lr);
  settle();
  m.seconds_optimizer = seconds_since(phase_began);
  set_means(sums, static_cast<double>(cfg_.data.global_batch), m);
  return m;
}

// The fast path on CUDA: all-reduce, norm, clipping and AdamW are issued behind the backward with no
// host wait; the update is skipped on the device when the global loss or the norm is not finite; one
// copy at the end brings the metric terms, the norm and that flag to the host, which then stops
// training as the reference path does. Phase times come from CUDA events (device time).
StepMetrics Trainer::finish_on_device(StepTail& tail) {
  auto params = opt_->tensors();
  auto grads = adapter_grads();
  tail.phase.emplace_back(cudaEventDefault);
  tail.phase.back().record();
  // This rank's loss sum rides along with the gradients: their all-reduce makes its finiteness global.
  auto reduced = grads;
  reduced.push_back(tail.terms[0].sum().reshape({1}).to(grads.front().scalar_type()));  // [1]
  comm_.all_reduce_mean(reduced);
  tail.phase.emplace_back(cudaEventDefault);
  tail.phase.back().record();
  StepMetrics m;
  m.lr = learning_rate(cfg_.optim, step_, cfg_.train.steps);
  auto norm = clip_grad_norm_on_device(params, cfg_.optim.clip_grad_norm);  // [] float64
  auto skip = torch::logical_not(torch::isfinite(norm)).logical_or(torch::logical_not(torch::isfinite(reduced.back()[0])))
                  .to(torch::kFloat32);  // []
  opt_->step(m.lr, skip);
  tail.phase.emplace_back(cudaEventDefault);
  tail.phase.back().record();
  // The step's one wait: [7 x pairs] terms, then the norm and the skip flag, in float64.
  const int64_t n = tail.terms.numel();
  auto host = torch::cat({tail.terms.to(torch::kFloat64).flatten(), norm.reshape({1}), skip.to(torch::kFloat64).reshape({1})})
                  .to(torch::kCPU);  // [n + 2]
  StepSums sums = metric_sums(host.narrow(0, 0, n).view(tail.terms.sizes()), tail.kinds);
  sums = StepSums::unpack(comm_.all_reduce_sum(sums.pack()));
  m.grad_norm = host[n].item<double>();
  const double global_loss = sums.loss / static_cast<double>(cfg_.data.global_batch);
  // The device's flag and the host's sums see the same values; a flag without a non-finite host value
  // (a float32 loss sum overflowing) still stops, as a non-finite loss.
  const bool skipped = host[n + 1].item<double>() != 0;
  stop_if_non_finite(skipped && std::isfinite(m.grad_norm) && std::isfinite(global_loss) ? NAN : global_loss,
                     m.grad_norm);
  m.seconds_data = tail.seconds_data + tail.seconds_ahead;
  m.seconds_compute = tail.phase[0].elapsed_time(tail.phase[1]) * 1e-3;
  m.seconds_allreduce = tail.phase[1].elapsed_time(tail.phase[2]) * 1e-3;
  m.seconds_optimizer = tail.phase[2].elapsed_time(tail.phase[3]) * 1e-3;
  set_means(sums, static_cast<double>(cfg_.data.global_batch), m);
  return m;
}

void Trainer::run() {
  const bool lead = comm_.rank() == 0;
  const std::string out = cfg_.run.out_dir;
  std::unique_ptr<MetricsWriter> metrics;
  std::unique_ptr<TensorBoardWriter> tb;
  std::unique_ptr<Progress> progress;
  if (lead) {
    std::filesystem::create_directories(out);
    metrics = std::make_unique<MetricsWriter>(out + "/metrics.jsonl", step_ > 0 ? step_ : -1);
    tb = std::make_unique<TensorBoardWriter>(out + "/tensorboard");
    if (step_ > 0) tb->session_start(step_ + 1);  // a resumed run: hide what was logged after the checkpoint
    if (cfg_.run.progress)
      progress = std::make_unique<Progress>(cfg_.train.steps, step_, Progress::stderr_is_tty(), cfg_.run.log_every);
    simu::log::info("FM-DPO: {} steps from step {}, global batch {} = micro {} x accumulation {} x world {}",
                    cfg_.train.steps, step_, cfg_.data.global_batch, cfg_.data.micro_batch,
                    cfg_.data.global_batch / (cfg_.data.micro_batch * comm_.world_size()), comm_.world_size());
  }
  while (step_ < cfg_.train.steps) {
    simu::check_cancel();  // an embedding program's interrupt (common/cancel.h), between steps
    auto m = step();
    if (lead) {
      const auto sc = m.scalars();
      metrics->write(m.step, sc);
      tb->add_scalars(m.step, sc);
      if (progress) progress->update(m.step, m.loss, m.accuracy, m.lr, m.pairs_per_s);
    }
    const bool last = step_ == cfg_.train.steps;
    if (last || (cfg_.run.checkpoint_every > 0 && step_ % cfg_.run.checkpoint_every == 0)) {
      const auto dir = save();
      if (lead && !last) simu::log::debug("checkpoint {}", dir);
    }
  }
  if (progress) progress->finish();
  if (lead) {
    model_.export_peft(out + "/adapter");
    simu::log::info("done: {} steps; adapter (PEFT) in {}/adapter, checkpoints in {}/checkpoints", step_, out, out);
  }
  comm_.barrier();
}

}  // namespace simu::training
