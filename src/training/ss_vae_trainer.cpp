#include "training/ss_vae_trainer.h"

#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <sstream>

#include <fmt/ranges.h>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "common/timing.h"
#include "data/safetensors.h"
#include "models/precision.h"
#include "training/launcher.h"
#include "training/observe.h"

namespace simu::training {

namespace {

// The configs the loaders read (SSEncoderConfig / SSDecoderConfig::from), as JSON.
nlohmann::json encoder_json(const models::SSEncoderConfig& c) {
  return {{"in_channels", c.in_channels},         {"latent_channels", c.latent_channels},
          {"num_res_blocks", c.num_res_blocks},   {"channels", c.channels},
          {"num_res_blocks_middle", c.num_res_blocks_middle}, {"norm_type", c.norm_type},
          {"use_fp16", false}};
}
nlohmann::json decoder_json(const models::SSDecoderConfig& c) {
  return {{"out_channels", c.out_channels},       {"latent_channels", c.latent_channels},
          {"num_res_blocks", c.num_res_blocks},   {"channels", c.channels},
          {"num_res_blocks_middle", c.num_res_blocks_middle}, {"norm_type", c.norm_type},
          {"reshape_input_to_cube", false},       {"use_fp16", false}};
}

bool starts_with(const std::string& s, const std::string& prefix) { return s.rfind(prefix, 0) == 0; }

}  // namespace

std::map<std::string, double> SsVaeStepMetrics::scalars() const {
  return {{"loss", loss},           {"bce", bce},         {"dice", dice},
          {"l1", l1},               {"kl", kl},           {"iou", iou},
          {"grad_norm", grad_norm}, {"lr", lr},           {"shapes_per_s", shapes_per_s},
          {"time/step_s", seconds_step}, {"time/data_wait_s", seconds_data}};
}

void zero_residual_convs(torch::nn::Module& module) {
  torch::NoGradGuard no_grad;
  for (const auto& m : module.modules(/*include_self=*/true))
    if (auto* block = m->as<models::ResBlock3dImpl>())
      for (auto& p : block->conv2->parameters()) p.zero_();
}

struct SsVaeTrainer::Logs {
  std::unique_ptr<MetricsWriter> metrics;
  std::unique_ptr<TensorBoardWriter> tb;
  std::unique_ptr<Progress> progress;
};

SsVaeTrainer::SsVaeTrainer(SsVaeConfig cfg, std::shared_ptr<const ShapeSet> shapes, Communicator& comm,
                           torch::Device device)
    : cfg_(std::move(cfg)), shapes_(std::move(shapes)), comm_(comm), device_(device) {
  SIMU_CHECK(shapes_ && shapes_->resolution == cfg_.data.resolution,
             "{}: data.resolution {} but the shape set makes {}^3 grids", cfg_.file, cfg_.data.resolution,
             shapes_ ? shapes_->resolution : 0);
  const int64_t input_side = shapes_->input_occupancy ? shapes_->input_resolution : shapes_->resolution;
  SIMU_CHECK(input_side == cfg_.encoder_resolution(), "{}: the encoder reads {}^3 grids but the shape set makes {}^3 ones for it",
             cfg_.file, cfg_.encoder_resolution(), input_side);
  if (cfg_.data.global_batch % comm_.world_size() != 0)
    fail_hint("choose data.global_batch as a multiple of the number of ranks",
              "{}: data.global_batch {} is not divisible by the world size {}", cfg_.file, cfg_.data.global_batch,
              comm_.world_size());
  if (device_.is_cuda()) at::globalContext().setBenchmarkCuDNN(cfg_.train.cudnn_benchmark);
  // Both networks from one seed (every rank alike), the official init, then to the device.
  torch::manual_seed(cfg_.train.seed);
  encoder_ = models::SparseStructureEncoder(cfg_.model.encoder);
  decoder_ = models::SparseStructureDecoder(cfg_.model.decoder);
  zero_residual_convs(*encoder_);
  zero_residual_convs(*decoder_);
  if (frozen_encoder()) load_frozen_encoder();
  encoder_->to(device_);
  decoder_->to(device_);
  encoder_->train(!frozen_encoder());
  decoder_->train();
  opt_ = std::make_unique<AdamW>(named_weights(), cfg_.optim);
  if (cfg_.train.ema_rate > 0) {
    torch::NoGradGuard no_grad;
    for (const auto& [name, p] : named_weights()) ema_.emplace_back("ema." + name, p.detach().clone());
  }
  loader_ = std::make_unique<BatchLoader>(shapes_, loader_options(0));
  last_finish_ = Clock::now();
}

SsVaeTrainer::~SsVaeTrainer() = default;

LoaderOptions SsVaeTrainer::loader_options(int64_t start_step) const {
  LoaderOptions o;
  o.rank = comm_.rank();
  o.world = comm_.world_size();
  o.global_batch = cfg_.data.global_batch;
  o.start_step = start_step;
  o.noise_seed = cfg_.train.seed;
  const int64_t r = cfg_.latent_resolution();
  o.latent_shape = {cfg_.model.encoder.latent_channels, r, r, r};
  o.workers = static_cast<int>(cfg_.data.workers);
  o.prefetch = static_cast<int>(cfg_.data.prefetch);
  o.pin_memory = device_.is_cuda();
  return o;
}

void SsVaeTrainer::load_frozen_encoder() {
  const std::string dir = cfg_.model.frozen_encoder;
  auto loaded = models::load_ss_encoder(dir + "/ss_encoder.json", dir + "/ss_encoder.safetensors", torch::kCPU);
  // The loaded encoder must be the one the config describes (the latent the decoder learns to read).
  const auto got = encoder_json(loaded->config()), want = encoder_json(cfg_.model.encoder);
  if (got != want)
    fail_hint("copy model.encoder from " + dir + "/ss_encoder.json",
              "{}: model.frozen_encoder {}: its ss_encoder.json is {} but model.encoder says {}", cfg_.file, dir,
              got.dump(), want.dump());
  encoder_ = loaded;
  for (auto& p : encoder_->parameters()) p.set_requires_grad(false);
}

std::vector<std::pair<std::string, torch::Tensor>> SsVaeTrainer::named_weights() const {
  std::vector<std::pair<std::string, torch::Tensor>> out;
  if (!frozen_encoder())
    for (const auto& p : encoder_->named_parameters()) out.emplace_back("encoder." + p.key(), p.value());
  for (const auto& p : decoder_->named_parameters()) out.emplace_back("decoder." + p.key(), p.value());
  return out;
}

// ---- one step ----------------------------------------------------------------------------------

SsVaeTrainer::Pending SsVaeTrainer::issue_step() {
  const auto began = Clock::now();
  VaeBatch batch = loader_->next();
  Pending p;
  p.seconds_data = seconds_since(began);
  const bool cuda = device_.is_cuda();
  // Pinned batches copy asynchronously on CUDA (the host does not wait for the device here).
  const auto occ = (batch.occupancy.to(device_, /*non_blocking=*/cuda) > 0).to(torch::kFloat32);  // [b, 1, R, R, R]
  const auto input = batch.input.defined() ? (batch.input.to(device_, /*non_blocking=*/cuda) > 0).to(torch::kFloat32)
                                           : occ;                                               // [b, 1, Ri, Ri, Ri]
  const auto noise = batch.noise.to(device_, /*non_blocking=*/cuda);                              // [b, C, r, r, r]
  opt_->zero_grad();
  // Forward: the posterior (no graph when the encoder is frozen), a sample of it with the batch's
  // noise, its decode (bf16 autocast on CUDA).
  torch::Tensor mean, logvar, logits;
  {
    models::Autocast ac(models::Precision::kBf16, cfg_.train.precision == "bf16" && cuda);
    {
      torch::AutoGradMode grad(!frozen_encoder());
      std::tie(mean, logvar) = encoder_->posterior(input);  // float32
    }
    logits = decoder_->forward(models::sample_posterior(mean, logvar, noise));
  }
  const auto terms = ss_vae_terms(logits.to(torch::kFloat32), occ, mean, logvar, cfg_.loss);
  // This rank's mean; the all-reduce averages equal shares into the global batch's mean.
  terms.total.mean().backward();
  auto metrics = torch::stack({terms.total.mean(), terms.bce.mean(), terms.dice.mean(), terms.l1.mean(),
                               terms.kl.mean(), terms.iou.mean()})
                     .detach()
                     .to(torch::kFloat32);  // [6]
  // Gradients and metrics averaged over the ranks in one buffer.
  const auto params = opt_->tensors();
  std::vector<torch::Tensor> reduced;
  for (auto w : params) {
    if (!w.grad().defined()) w.mutable_grad() = torch::zeros_like(w);
    reduced.push_back(w.grad());
  }
  reduced.push_back(metrics);
  comm_.all_reduce_mean(reduced);
  p.step = step_ + 1;
  p.lr = learning_rate(cfg_.optim, step_, cfg_.train.steps);
  if (cuda) {
    // Device-side: clip, then AdamW and the EMA skipped where the loss or the norm is not finite.
    const auto norm = clip_grad_norm_on_device(params, cfg_.optim.clip_grad_norm);  // [] float64
    const auto skip =
        torch::logical_not(torch::isfinite(norm)).logical_or(torch::logical_not(torch::isfinite(metrics[0]))).to(torch::kFloat32);
    opt_->step(p.lr, skip);
    update_ema(skip);
    p.values = torch::cat({metrics.to(torch::kFloat64), norm.reshape({1}), skip.to(torch::kFloat64).reshape({1})});
  } else {
    // Host-side: a non-finite loss or norm stops training before the update.
    const double loss = metrics[0].item<double>();
    const double norm = clip_grad_norm(params, cfg_.optim.clip_grad_norm);
    if (!std::isfinite(loss) || !std::isfinite(norm))
      fail_hint("lower optim.lr or raise loss.lambda_kl, then --resume latest",
                "{}: step {}: non-finite {} (loss {}, gradient norm {}); training stopped before this update, the "
                "checkpoints in {}/checkpoints are unchanged",
                cfg_.file, p.step, std::isfinite(loss) ? "gradient" : "loss", loss, norm, cfg_.run.out_dir);
    opt_->step(p.lr);
    update_ema(torch::Tensor());
    p.values = torch::cat({metrics.to(torch::kFloat64), torch::tensor({norm, 0.0}, torch::kFloat64)});
  }
  ++step_;
  heartbeat();
  return p;
}

void SsVaeTrainer::update_ema(const torch::Tensor& skip) {
  if (ema_.empty()) return;
  torch::NoGradGuard no_grad;
  const double w = 1.0 - cfg_.train.ema_rate;
  const auto params = opt_->tensors();
  // ema += (1 - rate) * (p - ema); on CUDA the weight is zero where the step was skipped.
  const auto weight = skip.defined() ? (1 - skip) * w : torch::Tensor();
  for (size_t i = 0; i < ema_.size(); ++i) {
    if (weight.defined()) ema_[i].second.lerp_(params[i], weight);
    else ema_[i].second.lerp_(params[i], w);
  }
}

SsVaeStepMetrics SsVaeTrainer::finish(const Pending& p) {
  const auto v = p.values.to(torch::kCPU).contiguous();  // waits for the step on CUDA
  const auto a = v.accessor<double, 1>();
  SsVaeStepMetrics m;
  m.step = p.step;
  m.loss = a[0], m.bce = a[1], m.dice = a[2], m.l1 = a[3], m.kl = a[4], m.iou = a[5];
  m.grad_norm = a[6];
  m.lr = p.lr;
  m.seconds_data = p.seconds_data;
  if (a[7] != 0 || !std::isfinite(m.loss) || !std::isfinite(m.grad_norm))
    fail_hint("lower optim.lr or raise loss.lambda_kl, then --resume latest",
              "{}: step {}: non-finite loss {} or gradient norm {}: its update was skipped on the device and training "
              "stopped; the checkpoints in {}/checkpoints are unchanged",
              cfg_.file, m.step, m.loss, m.grad_norm, cfg_.run.out_dir);
  const auto now = Clock::now();
  m.seconds_step = std::chrono::duration<double>(now - last_finish_).count();
  last_finish_ = now;
  m.shapes_per_s = static_cast<double>(cfg_.data.global_batch) / std::max(m.seconds_step, 1e-9);
  return m;
}

SsVaeStepMetrics SsVaeTrainer::step() { return finish(issue_step()); }

// ---- checkpoints -------------------------------------------------------------------------------

CheckpointData SsVaeTrainer::checkpoint_data() const {
  CheckpointData d;
  d.step = step_;
  for (const auto& [name, p] : named_weights()) d.adapter[name] = p.detach().to(torch::kCPU).clone();
  d.optimizer = opt_->state_dict();
  for (const auto& [name, e] : ema_) d.optimizer[name] = e.to(torch::kCPU).clone();
  std::ostringstream cfg;
  cfg << cfg_.resolved;
  // A frozen encoder is not in the checkpoint: resume reloads it from model.frozen_encoder.
  // The data stream restarts at the step: its samples are a function of the step alone.
  d.state = {{"data_position", {{"epoch", 0}, {"step", step_}}},
             {"seed", cfg_.train.seed},
             {"data_seed", cfg_.data.seed},
             {"world_size", comm_.world_size()},
             {"global_batch", cfg_.data.global_batch},
             {"ema_rate", cfg_.train.ema_rate},
             {"lr_next", learning_rate(cfg_.optim, step_, cfg_.train.steps)},
             {"schedule", {{"kind", cfg_.optim.schedule}, {"warmup_steps", cfg_.optim.warmup_steps},
                           {"total_steps", cfg_.train.steps}}},
             {"config", cfg.str()}};
  return d;
}

std::string SsVaeTrainer::save() {
  std::string dir;
  if (comm_.rank() == 0) dir = save_checkpoint(cfg_.run.out_dir + "/checkpoints", checkpoint_data(), cfg_.run.keep_last);
  comm_.barrier();
  return dir;
}

void SsVaeTrainer::resume(const std::string& dir) {
  auto ck = load_checkpoint(dir);
  // The weights: exactly the model's names and shapes.
  std::vector<std::string> problems;
  const auto weights = named_weights();
  for (const auto& [name, p] : weights) {
    const auto it = ck.adapter.find(name);
    if (it == ck.adapter.end()) problems.push_back("missing " + name);
    else if (it->second.sizes() != p.sizes())
      problems.push_back(fmt::format("{}: shape {} vs {}", name, fmt::join(it->second.sizes(), "x"), fmt::join(p.sizes(), "x")));
  }
  if (ck.adapter.size() != weights.size())
    problems.push_back(fmt::format("{} weight tensors in the checkpoint, {} in the model", ck.adapter.size(), weights.size()));
  // The EMA: present exactly when this config keeps one.
  size_t ema_found = 0;
  for (const auto& [k, v] : ck.optimizer) ema_found += starts_with(k, "ema.") ? 1 : 0;
  if (ema_found != ema_.size())
    problems.push_back(fmt::format("{} EMA tensors in the checkpoint, {} expected with train.ema_rate {}", ema_found,
                                   ema_.size(), cfg_.train.ema_rate));
  if (!problems.empty())
    fail_hint("resume with the config the run was started with (model, train.ema_rate)",
              "{}: checkpoint does not match the VAE:\n  {}", dir, fmt::join(problems, "\n  "));
  const int64_t gb = ck.state.value("global_batch", int64_t{-1});
  if (gb != cfg_.data.global_batch)
    fail("{}: checkpoint was trained with global batch {}, the config says {}", dir, gb, cfg_.data.global_batch);
  {
    torch::NoGradGuard no_grad;
    for (const auto& [name, p] : weights) p.copy_(ck.adapter.at(name));
    for (auto& [name, e] : ema_) e.copy_(ck.optimizer.at(name));
  }
  std::map<std::string, torch::Tensor> opt_state;
  for (const auto& [k, v] : ck.optimizer)
    if (!starts_with(k, "ema.") && !starts_with(k, "rng.")) opt_state[k] = v;
  opt_->load_state_dict(opt_state, dir + "/optimizer.safetensors");
  step_ = ck.step;
  loader_.reset();  // stops the old stream before the new one starts
  loader_ = std::make_unique<BatchLoader>(shapes_, loader_options(step_));
  if (comm_.rank() == 0) simu::log::info("resumed from {} at step {}", dir, step_);
}

// ---- evaluation and export ----------------------------------------------------------------------

void SsVaeTrainer::swap_ema() {
  torch::NoGradGuard no_grad;
  const auto params = opt_->tensors();
  for (size_t i = 0; i < ema_.size(); ++i) {
    auto live = params[i].clone();
    params[i].copy_(ema_[i].second);
    ema_[i].second.copy_(live);
  }
}

IouTable SsVaeTrainer::evaluate(const std::vector<ShapeKey>& keys) {
  swap_ema();
  std::vector<double> iou;
  try {
    iou = reconstruction_iou(*encoder_, *decoder_, *shapes_, keys, cfg_.eval.batch, static_cast<int>(cfg_.data.workers),
                             cfg_.train.precision == "bf16");
  } catch (...) {
    swap_ema();
    throw;
  }
  swap_ema();
  return iou_table(keys, iou, shapes_->held_out_family);
}

void SsVaeTrainer::export_weights(const std::string& dir) const {
  const auto dtype = cfg_.model.export_dtype == "float16" ? torch::kFloat16 : torch::kFloat32;
  // The EMA weights when kept, else the live ones; names without the encoder./decoder. prefix.
  std::map<std::string, torch::Tensor> enc, dec;
  if (frozen_encoder())
    for (const auto& p : encoder_->named_parameters()) enc[p.key()] = p.value().detach().to(torch::kCPU, dtype).contiguous();
  const auto weights = named_weights();
  for (size_t i = 0; i < weights.size(); ++i) {
    const auto& [name, p] = weights[i];
    const auto value = (ema_.empty() ? p.detach() : ema_[i].second).to(torch::kCPU, dtype).contiguous();
    if (starts_with(name, "encoder.")) enc[name.substr(8)] = value;
    else dec[name.substr(8)] = value;
  }
  const std::string tmp = fmt::format("{}.tmp-{}", dir, ::getpid());
  fs::remove_tree(tmp);
  std::filesystem::create_directories(tmp);
  const std::map<std::string, std::string> meta = {{"format", "pt"}, {"step", std::to_string(step_)},
                                                   {"weights", ema_.empty() ? "live" : "ema"}};
  data::save_safetensors(tmp + "/ss_encoder.safetensors", enc, meta);
  data::save_safetensors(tmp + "/ss_decoder.safetensors", dec, meta);
  fs::atomic_write(tmp + "/ss_encoder.json", encoder_json(cfg_.model.encoder).dump(1) + "\n");
  fs::atomic_write(tmp + "/ss_decoder.json", decoder_json(cfg_.model.decoder).dump(1) + "\n");
  fs::replace_dir(tmp, dir);
}

// ---- the loop ----------------------------------------------------------------------------------

void SsVaeTrainer::log_scalars(int64_t step, const std::map<std::string, double>& scalars) {
  if (!logs_) return;
  logs_->metrics->write(step, scalars);
  logs_->tb->add_scalars(step, scalars);
}

void SsVaeTrainer::run() {
  const bool lead = comm_.rank() == 0;
  const std::string out = cfg_.run.out_dir;
  if (lead) {
    std::filesystem::create_directories(out);
    logs_ = std::make_unique<Logs>();
    logs_->metrics = std::make_unique<MetricsWriter>(out + "/metrics.jsonl", step_ > 0 ? step_ : -1);
    logs_->tb = std::make_unique<TensorBoardWriter>(out + "/tensorboard");
    if (step_ > 0) logs_->tb->session_start(step_ + 1);  // a resumed run: hide what was logged after the checkpoint
    if (cfg_.run.progress)
      logs_->progress = std::make_unique<Progress>(cfg_.train.steps, step_, Progress::stderr_is_tty(), cfg_.run.log_every,
                                                   "iou", "shapes");
    int64_t params = 0;
    for (const auto& [name, p] : named_weights()) params += p.numel();
    simu::log::info("SS-VAE: {} steps from step {}, global batch {} over {} rank(s), {}^3 -> {} x {}^3 -> {}^3, {:.2f} M "
                    "trained parameters{}, {}",
                    cfg_.train.steps, step_, cfg_.data.global_batch, comm_.world_size(), cfg_.encoder_resolution(),
                    cfg_.model.encoder.latent_channels, cfg_.latent_resolution(), cfg_.data.resolution, params / 1e6,
                    frozen_encoder() ? " (the decoder; encoder frozen from " + cfg_.model.frozen_encoder + ")" : "",
                    device_.str());
  }
  // A step's metrics are read after the next step is issued (the device never idles for the host),
  // except before a checkpoint, a validation and the end.
  std::optional<Pending> pending;
  auto drain = [&] {
    if (!pending) return;
    const auto m = finish(*pending);
    pending.reset();
    log_scalars(m.step, m.scalars());
    if (lead && logs_->progress) logs_->progress->update(m.step, m.loss, m.iou, m.lr, m.shapes_per_s);
  };
  // This run's end: train.steps, or earlier (run.stop_at_step, run.stop_after_s: a checkpoint, no export).
  const int64_t end = cfg_.run.stop_at_step > 0 ? std::min(cfg_.run.stop_at_step, cfg_.train.steps) : cfg_.train.steps;
  const auto began = Clock::now();
  bool stopped = false;
  while (step_ < end && !stopped) {
    auto p = issue_step();
    drain();
    pending = p;
    // Every rank takes rank 0's decision to stop on time (the clocks differ).
    if (cfg_.run.stop_after_s > 0)
      stopped = comm_.all_reduce_sum({lead && seconds_since(began) > cfg_.run.stop_after_s ? 1.0 : 0.0})[0] > 0;
    const bool last = step_ == cfg_.train.steps, pause = !last && (step_ == end || stopped);
    const bool checkpoint =
        last || pause || (cfg_.run.checkpoint_every > 0 && step_ % cfg_.run.checkpoint_every == 0);
    const bool validate = cfg_.eval.every > 0 && step_ % cfg_.eval.every == 0 && !shapes_->val.empty();
    if (checkpoint || validate || !device_.is_cuda()) drain();
    if (validate && lead) {
      const auto t = evaluate(shapes_->val);
      if (t.n_seen) log_scalars(step_, {{"val/iou_seen", t.mean_seen}});
    }
    if (checkpoint) save();
  }
  drain();
  if (lead && logs_->progress) logs_->progress->finish();
  if (step_ < cfg_.train.steps) {
    if (lead)
      simu::log::info("stopped at step {} of {} ({}); checkpoint in {}/checkpoints: continue with --resume latest", step_,
                      cfg_.train.steps,
                      stopped ? fmt::format("run.stop_after_s {}", cfg_.run.stop_after_s) : "run.stop_at_step", out);
    comm_.barrier();
    logs_.reset();
    return;
  }
  // The end: the exported weights and the test split's table (rank 0), then every rank leaves together.
  if (lead) {
    export_weights(out + "/weights");
    const auto table = evaluate(shapes_->test);
    nlohmann::json j = {{"step", step_}, {"split", "test"}, {"config", cfg_.file},
                        {"weights", ema_.empty() ? "live" : "ema"}, {"iou", table.to_json()}};
    fs::atomic_write(out + "/eval.json", j.dump(1) + "\n");
    std::map<std::string, double> sc;
    if (table.n_seen) sc["test/iou_seen"] = table.mean_seen;
    if (table.n_held_out) sc["test/iou_held_out"] = table.mean_held_out;
    if (!sc.empty()) log_scalars(step_, sc);
    simu::log::info("done: {} steps; weights in {}/weights, checkpoints in {}/checkpoints; test reconstruction IoU "
                    "(posterior mean, logits > 0):\n{}",
                    step_, out, out, table.markdown());
  }
  comm_.barrier();
  logs_.reset();
}

}  // namespace simu::training
