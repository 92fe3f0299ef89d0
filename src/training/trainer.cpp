#include "training/trainer.h"

#include <ATen/CPUGeneratorImpl.h>
#include <ATen/cuda/CUDAEvent.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <sstream>

#include <fmt/ranges.h>

#include "common/cancel.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "common/timing.h"
#include "training/launcher.h"
#include "training/observe.h"

namespace simu::training {

std::map<std::string, double> StepMetrics::scalars() const {
  std::map<std::string, double> m{{"loss", loss},
                                  {"grad_norm", grad_norm},
                                  {"lr", lr},
                                  {rate_name, pairs_per_s},
                                  {"time/step_s", seconds_step},
                                  {"time/data_wait_s", seconds_data},
                                  {"time/compute_s", seconds_compute},
                                  {"time/allreduce_s", seconds_allreduce},
                                  {"time/optimizer_s", seconds_optimizer}};
  if (!std::isnan(accuracy)) m["accuracy"] = accuracy;
  if (!std::isnan(margin)) m["margin"] = margin;
  for (const auto& [k, v] : per_kind) m[k] = v;
  return m;
}

// ---- trainer ---------------------------------------------------------------------------------

struct StepTail {
  Clock::time_point compute_began;             // its forwards' start
  double seconds_data = 0, seconds_ahead = 0;  // reading this step's batch; reading the next one ahead
  std::unique_ptr<StagedBatch> batch;          // the step's batch (the objective's, read by metric_sums)
  torch::Tensor terms;                         // [K, samples] per-sample metric terms on the device
  std::vector<at::cuda::CUDAEvent> phase;      // device path: compute start, backward end, all-reduce end, update end
};

namespace {

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

Trainer::Trainer(TrainerConfig cfg, std::unique_ptr<Objective> objective, Communicator& comm, torch::Device device)
    : cfg_(std::move(cfg)), objective_(std::move(objective)), comm_(comm), device_(device), read_ahead_(device.is_cuda()) {
  if (device_.is_cuda()) upload_stream_ = c10::cuda::getStreamFromPool(false, device_.index()).unwrap();
  const int64_t world = comm_.world_size();
  if (cfg_.data.global_batch % (world * cfg_.data.micro_batch) != 0)
    fail_hint("choose global_batch = micro_batch x accumulation x world size",
              "{}: data.global_batch {} is not divisible by micro_batch {} x world size {}", cfg_.file,
              cfg_.data.global_batch, cfg_.data.micro_batch, world);
  opt_ = std::make_unique<AdamW>(objective_->parameters(), cfg_.optim);
  objective_->open_data(comm_.rank(), comm_.world_size(), cfg_.data.global_batch, cfg_.data.seed, DataPosition{});
  // Every rank must start from the same parameters (gradients are averaged, never the weights):
  // compare a fingerprint of them across ranks (sum and sum of squares of the per-rank sums).
  if (world > 1) {
    double fp = 0;
    for (const auto& [name, p] : opt_->params()) fp += p.detach().to(torch::kFloat64).sum().item<double>() * (1 + 1e-3 * fp);
    const auto s = comm_.all_reduce_sum({fp, fp * fp});
    const double mean = s[0] / world, var = s[1] / world - mean * mean;
    if (var > 1e-18 * std::max(1.0, mean * mean))
      fail_hint("seed every rank alike (train.seed) before the parameters are created",
                "rank {}: the trained parameters differ across the {} ranks at the start (fingerprint {} vs mean {})",
                comm_.rank(), world, fp, mean);
  }
}

Trainer::Trainer(TrainConfig cfg, PolicyModel& model, PairSourceFactory sources, Communicator& comm, torch::Device device)
    : Trainer(cfg, std::make_unique<FmdpoObjective>(cfg, model, std::move(sources), device), comm, device) {}

Trainer::~Trainer() = default;

void Trainer::set_condition_embedder(ConditionEmbedFn fn) {
  auto* fmdpo = dynamic_cast<FmdpoObjective*>(objective_.get());
  SIMU_CHECK(fmdpo != nullptr, "{}: a condition embedder for pair inputs applies to FM-DPO only, not to {}", cfg_.file,
             objective_->name());
  fmdpo->set_condition_embedder(std::move(fn));
}

CheckpointData Trainer::checkpoint_data() const {
  CheckpointData d;
  d.step = step_;
  d.params_file = objective_->params_file();
  for (const auto& [name, p] : opt_->params()) d.adapter[name] = p.detach().to(torch::kCPU).clone();
  d.optimizer = opt_->state_dict();
  for (auto& [k, v] : rng_states(device_)) d.optimizer[k] = v;
  d.extra = objective_->extra_state();
  // The position of the next batch a step will train on (a batch read ahead is not trained on yet).
  const auto pos = ahead_ ? ahead_->position : objective_->data_position();
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
  // Parameters: exactly the same names and shapes.
  std::vector<std::string> problems;
  if (ck.params_file != objective_->params_file())
    problems.push_back(fmt::format("it holds {}, {} trains {}", ck.params_file, objective_->name(), objective_->params_file()));
  for (const auto& [name, p] : opt_->params()) {
    auto it = ck.adapter.find(name);
    if (it == ck.adapter.end()) problems.push_back("missing " + name);
    else if (it->second.sizes() != p.sizes())
      problems.push_back(fmt::format("{}: shape {} vs {}", name, fmt::join(it->second.sizes(), "x"), fmt::join(p.sizes(), "x")));
  }
  if (ck.adapter.size() != opt_->params().size())
    problems.push_back(fmt::format("{} trained tensors in the checkpoint, {} in the model", ck.adapter.size(),
                                   opt_->params().size()));
  if (!problems.empty())
    fail("{}: checkpoint does not match the model's trained parameters:\n  {}", dir, fmt::join(problems, "\n  "));
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
  objective_->load_extra_state(ck.extra, dir);
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
  objective_->open_data(comm_.rank(), comm_.world_size(), cfg_.data.global_batch, cfg_.data.seed, pos);
  if (comm_.rank() == 0) simu::log::info("resumed from {} at step {} (data epoch {}, batch {})", dir, step_, pos.epoch, pos.step);
}

StepMetrics Trainer::step() {
  const auto began = Clock::now();
  // This step's batch: read ahead by the previous step, or read and staged now.
  StepTail tail;
  if (ahead_) {
    SIMU_CHECK(ahead_->step == step_,
               "trainer: the batch read ahead holds the noise of step {}, not of step {} (a failed step cannot be "
               "retried; resume from a checkpoint)", ahead_->step + 1, step_ + 1);
    tail.batch = std::move(ahead_);
  } else {
    tail.batch = objective_->read_batch(step_, read_ahead_ ? upload_stream_ : c10::nullopt);
    tail.seconds_data = seconds_since(began);
  }
  tail.compute_began = Clock::now();
  const bool on_device = device_update_ && device_.is_cuda();
  if (on_device) {
    tail.phase.emplace_back(cudaEventDefault);
    tail.phase.back().record();
  }
  SIMU_CHECK(tail.batch->samples == cfg_.data.global_batch / comm_.world_size(), "data source gave {} {}, {} expected",
             tail.batch->samples, objective_->sample_noun(), cfg_.data.global_batch / comm_.world_size());
  opt_->zero_grad();
  tail.terms = objective_->forward_backward(*tail.batch);
  // Read-ahead: the next batch is read and staged, its copies issued, while this step's kernels run.
  if (read_ahead_) {
    const auto ahead_began = Clock::now();
    ahead_ = objective_->read_batch(step_ + 1, upload_stream_);
    tail.seconds_ahead = seconds_since(ahead_began);
  }
  StepMetrics m = on_device ? finish_on_device(tail) : finish_on_host(tail);
  ++step_;
  objective_->after_update(step_);
  heartbeat();
  m.step = step_;
  m.seconds_step = seconds_since(began);
  m.pairs_per_s = static_cast<double>(cfg_.data.global_batch) / std::max(m.seconds_step, 1e-9);
  m.rate_name = objective_->sample_noun() + "_per_s";
  return m;
}

std::vector<torch::Tensor> Trainer::param_grads() {
  std::vector<torch::Tensor> grads;
  for (auto& p : opt_->tensors()) {
    if (!p.grad().defined()) p.mutable_grad() = torch::zeros_like(p);
    grads.push_back(p.grad());
  }
  return grads;
}

void Trainer::stop_if_non_finite(double global_loss, double grad_norm) const {
  // A non-finite loss or gradient (global values: every rank takes the same branch) stops training
  // before the optimizer touches the parameters, so the last checkpoint stays the last good state.
  if (!std::isfinite(global_loss) || !std::isfinite(grad_norm))
    fail_hint("lower optim.lr (FM-DPO: or objective.beta), check the cache (pairs validate / stage1_data validate), then "
              "--resume latest",
              "{}: step {}: non-finite {} (loss {}, gradient norm {}); training stopped before this update, the "
              "trained parameters and the checkpoints in {}/checkpoints are unchanged",
              cfg_.file, step_ + 1, std::isfinite(global_loss) ? "gradient" : "loss", global_loss, grad_norm,
              cfg_.run.out_dir);
}

// The reference path: each phase waits for the device (its wall time is the phase's), the metrics and
// the gradient norm come to the host before the update, which runs only when both are finite.
StepMetrics Trainer::finish_on_host(StepTail& tail) {
  auto settle = [&] {
    if (device_.is_cuda()) torch::cuda::synchronize();
  };
  // This rank's sums (one copy of the terms to the host).
  auto sums = objective_->metric_sums(tail.terms.defined() ? tail.terms.to(torch::kCPU, torch::kFloat64) : torch::Tensor(),
                                     *tail.batch);
  // Average gradients over ranks, clip, step.
  auto params = opt_->tensors();
  auto grads = param_grads();
  settle();
  StepMetrics m;
  m.seconds_data = tail.seconds_data + tail.seconds_ahead;
  m.seconds_compute = seconds_since(tail.compute_began) - tail.seconds_ahead;
  auto phase_began = Clock::now();
  comm_.all_reduce_mean(grads);
  // Metrics over all ranks (before the update: a non-finite loss must stop it on every rank alike).
  sums = comm_.all_reduce_sum(sums);
  settle();
  m.seconds_allreduce = seconds_since(phase_began);
  phase_began = Clock::now();
  m.grad_norm = clip_grad_norm(params, cfg_.optim.clip_grad_norm);
  m.lr = learning_rate(cfg_.optim, step_, cfg_.train.steps);
  stop_if_non_finite(sums.at(0) / static_cast<double>(cfg_.data.global_batch), m.grad_norm);
  opt_->step(m.lr);
  settle();
  m.seconds_optimizer = seconds_since(phase_began);
  objective_->set_metrics(sums, static_cast<double>(cfg_.data.global_batch), m);
  return m;
}

// The fast path on CUDA: all-reduce, norm, clipping and AdamW are issued behind the backward with no
// host wait; the update is skipped on the device when the global loss or the norm is not finite; one
// copy at the end brings the metric terms, the norm and that flag to the host, which then stops
// training as the reference path does. Phase times come from CUDA events (device time).
StepMetrics Trainer::finish_on_device(StepTail& tail) {
  auto params = opt_->tensors();
  auto grads = param_grads();
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
  // The step's one wait: [K x samples] terms, then the norm and the skip flag, in float64.
  const int64_t n = tail.terms.numel();
  auto host = torch::cat({tail.terms.to(torch::kFloat64).flatten(), norm.reshape({1}), skip.to(torch::kFloat64).reshape({1})})
                  .to(torch::kCPU);  // [n + 2]
  auto sums = objective_->metric_sums(host.narrow(0, 0, n).view(tail.terms.sizes()), *tail.batch);
  sums = comm_.all_reduce_sum(sums);
  m.grad_norm = host[n].item<double>();
  const double global_loss = sums.at(0) / static_cast<double>(cfg_.data.global_batch);
  // The device's flag and the host's sums see the same values; a flag without a non-finite host value
  // (a float32 loss sum overflowing) still stops, as a non-finite loss.
  const bool skipped = host[n + 1].item<double>() != 0;
  stop_if_non_finite(skipped && std::isfinite(m.grad_norm) && std::isfinite(global_loss) ? NAN : global_loss,
                     m.grad_norm);
  m.seconds_data = tail.seconds_data + tail.seconds_ahead;
  m.seconds_compute = tail.phase[0].elapsed_time(tail.phase[1]) * 1e-3;
  m.seconds_allreduce = tail.phase[1].elapsed_time(tail.phase[2]) * 1e-3;
  m.seconds_optimizer = tail.phase[2].elapsed_time(tail.phase[3]) * 1e-3;
  objective_->set_metrics(sums, static_cast<double>(cfg_.data.global_batch), m);
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
      progress = std::make_unique<Progress>(cfg_.train.steps, step_, Progress::stderr_is_tty(), cfg_.run.log_every,
                                            "acc", objective_->sample_noun());
    simu::log::info("{}: {} steps from step {}, global batch {} = micro {} x accumulation {} x world {}",
                    objective_->name(), cfg_.train.steps, step_, cfg_.data.global_batch, cfg_.data.micro_batch,
                    cfg_.data.global_batch / (cfg_.data.micro_batch * comm_.world_size()), comm_.world_size());
  }
  // This run's end: train.steps, or earlier (run.stop_at_step, run.stop_after_s: a checkpoint, no export).
  const int64_t end = cfg_.run.stop_at_step > 0 ? std::min(cfg_.run.stop_at_step, cfg_.train.steps) : cfg_.train.steps;
  const auto began = Clock::now();
  bool stopped = false;
  while (step_ < end && !stopped) {
    simu::check_cancel();  // an embedding program's interrupt (common/cancel.h), between steps
    auto m = step();
    if (lead) {
      const auto sc = m.scalars();
      metrics->write(m.step, sc);
      tb->add_scalars(m.step, sc);
      if (progress) progress->update(m.step, m.loss, m.accuracy, m.lr, m.pairs_per_s);
    }
    // Every rank takes rank 0's decision to stop on time (the clocks differ).
    if (cfg_.run.stop_after_s > 0)
      stopped = comm_.all_reduce_sum({lead && seconds_since(began) > cfg_.run.stop_after_s ? 1.0 : 0.0})[0] > 0;
    const bool last = step_ == cfg_.train.steps, pause = !last && (step_ == end || stopped);
    if (last || pause || (cfg_.run.checkpoint_every > 0 && step_ % cfg_.run.checkpoint_every == 0)) {
      const auto dir = save();
      if (lead && !last) simu::log::debug("checkpoint {}", dir);
    }
  }
  if (progress) progress->finish();
  if (lead && step_ < cfg_.train.steps) {
    simu::log::info("stopped at step {} of {} ({}); checkpoint in {}/checkpoints: continue with --resume latest", step_,
                    cfg_.train.steps, stopped ? fmt::format("run.stop_after_s {}", cfg_.run.stop_after_s) : "run.stop_at_step",
                    out);
  } else if (lead) {
    const std::string wrote = objective_->export_result(out);
    simu::log::info("done: {} steps; {}, checkpoints in {}/checkpoints", step_, wrote, out);
  }
  comm_.barrier();
}

}  // namespace simu::training
