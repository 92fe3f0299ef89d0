// bench_fmdpo: FM-DPO training-step throughput on GPU with the real-size Stage-1 generator (random
// weights) and LoRA r 64 on the 120 shape-branch projections, synthetic pairs in memory.
//
// For each micro-batch m (accumulation 1): step time, pairs/s, MFU, peak memory.
// MFU = model FLOPs per step / (step time x world x peak FLOP/s), model FLOPs per pair =
//   policy forward+backward (3 x G) + reference forward (1 x G) = 4 G, with G the forward the step
//   runs for one pair (step_pair_forward_flops: both members' shape stream, the shared condition's
//   key/value projections once; matrix products, 2 per MAC). The header also prints the full model's
//   forward per member F = models::flow_forward_flops(config, 1, cond_len) (pose stream included),
//   which the step no longer runs.
// That is the usual convention (backward = 2 x forward). With the base frozen the step needs less:
// "needed" counts what it must compute (needed_pair_flops below): no weight gradients of the base,
// no gradient into the condition, only the shape stream backpropagated, the LoRA products, and no
// recomputation. Its utilisation is the lower, conservative figure.
// Peak FLOP/s: --peak-tflops (default 989.4 = H100/H200 SXM dense bf16; scripts/gpu_bench.sh passes
// the machine's measured bf16 matmul rate instead).
// With --nproc-per-node 2 every rank first measures alone (world 1, no all-reduce), then all ranks
// train together; scaling efficiency = pairs/s together / sum of pairs/s alone.
// --cond-len takes several lengths (default 7528,2800: the released embedder's 7,528 tokens first, the
// headline, then 2,800); --fp8-base off,on,all adds rows with the opt-in FP8 frozen base (train.fp8_base:
// e4m3 GEMMs for the frozen base products, models/fp8_linear.h; on = the LoRA-wrapped projections
// (base fp8), all = every frozen Linear, MLPs included (base fp8all)) on the same policy and adapters;
// MFU and "needed" of those rows stay against the bf16 peak (the same FLOPs, done faster).
// --cond-mode inputs (or tokens,inputs for both in one run): the pairs carry the condition
// embedder's inputs at the released sizes (images and masks 518 px, point maps 518 px) and the
// released embedder (CondEmbedderConfig::sam3d_stage1, random weights) makes the tokens inside the
// step, as train_fmdpo does for an inputs-mode cache (no_grad, bf16 autocast). "embed" is the
// embedder's share of the step, timed with a device synchronisation before and after each embedder
// call (those two waits are in the step time too); MFU and "needed" count the flow model only.
#include <cstdlib>
#include <cstring>

#include <c10/cuda/CUDACachingAllocator.h>
#include <c10/cuda/CUDAFunctions.h>
#include <fmt/ranges.h>

#include "common/cli.h"
#include "common/error.h"
#include "common/log.h"
#include "gpu_profile.h"
#include "models/cond_embedder.h"
#include "models/mlp_epilogue.h"
#include "training/distributed.h"
#include "training/launcher.h"
#include "training/generator_policy.h"
#include "training/trainer.h"

#include "models/generator.h"

using namespace simu::training;

namespace {

struct Row {
  std::string mode = "tokens";
  int64_t cond_len = 0;
  std::string base = "bf16";  // the frozen base's GEMMs: bf16, fp8 (LoRA-wrapped layers) or fp8all
  int64_t micro = 0;
  int world = 1;
  double step_s = 0, pairs_s = 0, mfu = 0, needed_util = 0, peak_gib = 0, embed_share = 0;
};

// The condition embedder of --cond-mode inputs and its timing: wall seconds inside it (between device
// synchronisations) while `timing` is on.
struct TimedEmbedder {
  simu::models::CondEmbedder embedder{nullptr};
  bool timing = false;
  bool sync = true;  // --embed-timing off: no synchronisations (they stall the step's CPU/GPU overlap)
  double seconds = 0;
  ConditionEmbedFn fn() {
    return [this](const std::map<std::string, torch::Tensor>& inputs) {
      if (!sync) return embedder->forward(inputs);
      torch::cuda::synchronize();
      const auto t0 = std::chrono::steady_clock::now();
      auto out = embedder->forward(inputs);
      torch::cuda::synchronize();
      if (timing) seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      return out;
    };
  }
};

// n synthetic pairs: random latents [T, C] and either condition tokens [cond_len, Cc] or the six
// embedder inputs at 518 px (images uniform in [0, 1], binary masks, normal point maps).
std::shared_ptr<std::vector<Pair>> synthetic_pairs(int64_t n, int64_t T, int64_t C, int64_t cond_len, int64_t Cc,
                                                   bool inputs) {
  auto pairs = std::make_shared<std::vector<Pair>>();
  torch::manual_seed(1);
  for (int64_t i = 0; i < n; ++i) {
    Pair p{i, static_cast<simu::data::PairKind>(i % 2), torch::randn({T, C}), torch::randn({T, C}), torch::Tensor()};
    if (inputs) {
      const int64_t S = 518;
      p.inputs = {{"image", torch::rand({3, S, S})},
                  {"rgb_image", torch::rand({3, S, S})},
                  {"mask", (torch::rand({1, S, S}) > 0.5).to(torch::kFloat32)},
                  {"rgb_image_mask", (torch::rand({1, S, S}) > 0.5).to(torch::kFloat32)},
                  {"pointmap", torch::randn({3, S, S})},
                  {"rgb_pointmap", torch::randn({3, S, S})}};
    } else {
      p.cond = torch::randn({cond_len, Cc});
    }
    pairs->push_back(std::move(p));
  }
  return pairs;
}

// The forward the FM-DPO step runs for one pair (matrix products, 2 per multiply-add): the shape
// stream alone for both members (GeneratorPolicy asks for the shape latent only, so the pose stream
// and its blocks are skipped) and the condition's key/value projections once (both members share the
// pair's condition). Per member and block: self qkv + out, attention over its own T keys, cross q +
// out, attention over Lc keys, MLP; plus the latent's input/output layers and the block's adaLN row.
double step_pair_forward_flops(const simu::models::FlowModelConfig& c, double T, double Lc) {
  const double C = static_cast<double>(c.model_channels), Cc = static_cast<double>(c.cond_channels);
  const double hidden = std::floor(C * c.mlp_ratio), in = static_cast<double>(c.in_channels);
  double block = 2 * T * C * 3 * C + 2 * T * C * C + 2 * 2 * T * T * C;  // self qkv + out + attention
  block += 2 * T * C * C + 2 * T * C * C + 2 * 2 * T * Lc * C;         // cross q + out + attention
  block += 2 * 2 * T * C * hidden;                                      // MLP
  const double ada = (c.share_mod ? 1.0 : static_cast<double>(c.num_blocks)) * 2 * C * 6 * C;
  const double member = c.num_blocks * block + 2 * 2 * T * C * in + ada;
  const double kv = c.num_blocks * 2 * Lc * Cc * 2 * C;
  return 2 * member + kv;
}

// Matrix-product FLOPs one FM-DPO pair needs with the base frozen and LoRA of rank r on the shape
// stream's five attention projections (self qkv/out, cross q/kv/out): policy forward (G + LoRA),
// policy backward, reference forward (G), with G = step_pair_forward_flops.
// Policy backward, shape stream only (the protected stream attends to itself, so nothing else reaches
// the scored output; the timestep and the condition take no gradient): the input gradient of every
// linear layer it passes through except the condition's key/value projection, 2x the attention
// products (dP = dO V^T, dV = P^T dO, dQ = dS K, dK = dS^T Q; flash recomputation not counted), and
// the LoRA products: gradients of A and B, and of the LoRA input where that input takes a gradient.
// The condition's key/value LoRA runs once per pair (shared condition), forward and backward.
double needed_pair_flops(const simu::models::FlowModelConfig& c, double T, double Lc, double r, double G) {
  const double C = static_cast<double>(c.model_channels), Cc = static_cast<double>(c.cond_channels);
  const double hidden = std::floor(C * c.mlp_ratio), out = static_cast<double>(c.out_channels);
  // LoRA forward of one projection over n tokens: x A^T (in -> r), then B (r -> out).
  auto lora_fwd = [&](double n, double in, double o) { return 2 * n * (in * r + r * o); };
  // Its backward: dB, d(xA^T), dA, plus dx when the input takes a gradient.
  auto lora_bwd = [&](double n, double in, double o, bool dx) { return 2 * n * (r * o + o * r + in * r + (dx ? r * in : 0)); };
  const double lora_f = 2 * (lora_fwd(T, C, 3 * C) + 3 * lora_fwd(T, C, C)) + lora_fwd(Lc, Cc, 2 * C);
  const double lora_b = 2 * (lora_bwd(T, C, 3 * C, true) + 3 * lora_bwd(T, C, C, true)) + lora_bwd(Lc, Cc, 2 * C, false);
  double block_bwd = 0;
  block_bwd += 2 * T * C * 3 * C + 2 * T * C * C;  // self qkv + out, input gradients
  block_bwd += 2 * (2 * 2 * T * T * C);            // self attention over its own T keys
  block_bwd += 2 * 2 * T * C * C;                  // cross q + out (kv reads the condition: none)
  block_bwd += 2 * (2 * 2 * T * Lc * C);           // cross attention over Lc keys
  block_bwd += 2 * 2 * T * C * hidden;             // MLP fc1 + fc2
  const double policy_bwd = 2 * (c.num_blocks * block_bwd + 2 * T * C * out) + c.num_blocks * lora_b;  // + output layer
  return (G + c.num_blocks * lora_f) + policy_bwd + G;
}

// Rates of the rows measured alone (world 1), 0 elsewhere: summed over ranks for the scaling.
std::vector<double> alone_rates(const std::vector<Row>& rows) {
  std::vector<double> alone;
  for (auto& r : rows) alone.push_back(r.world == 1 ? r.pairs_s : 0.0);
  return alone;
}

void print_header(const std::string& generator, const simu::models::FlowModelConfig& fc, int64_t T, int64_t L,
                  const std::string& mode, bool checkpointing, double full_flops, double fwd_flops, double needed_flops,
                  double peak_tflops) {
  fmt::print("bench_fmdpo: {} ({} blocks, {} ch, {} shape tokens), cond {} tokens ({}), LoRA r64 shape branch, bf16 autocast{}\n",
             generator, fc.num_blocks, fc.model_channels, T, L,
             mode == "inputs" ? "made in the step by the released condition embedder, random weights" : "in the pairs",
             checkpointing ? ", activation checkpointing" : "");
  fmt::print("forward the step runs per pair G = {:.3f} TFLOP (shape stream of both members, the shared condition's K/V "
             "once; the full model's forward is F = {:.3f} TFLOP per member); model FLOPs per pair 4G (policy fwd+bwd 3G, "
             "reference fwd G); peak {} TFLOP/s\n",
             fwd_flops / 1e12, full_flops / 1e12, peak_tflops);
  fmt::print("needed FLOPs per pair with the base frozen = {:.3f} TFLOP = {:.2f}G (no base weight gradients, shape stream "
             "backward only, LoRA products counted)\n",
             needed_flops / 1e12, needed_flops / fwd_flops);
}

// The table (rank 0); alone[i] = the summed world-1 rate of the setting before row i.
void print_rows(const std::vector<Row>& rows, const std::vector<double>& alone, int rank) {
  if (rank != 0) return;
  fmt::print("{:>6} {:>5} {:>6} {:>5} {:>5} {:>10} {:>9} {:>7} {:>8} {:>10} {:>8} {:>7}\n", "mode", "cond", "base", "micro",
             "world", "step [ms]", "pairs/s", "MFU", "needed", "peak GiB", "scaling", "embed");
  for (size_t i = 0; i < rows.size(); ++i) {
    const auto& r = rows[i];
    std::string scaling = "-";
    if (r.world > 1 && i > 0) scaling = fmt::format("{:.1f}%", 100.0 * r.pairs_s / alone[i - 1]);
    const std::string embed = r.embed_share >= 0 ? fmt::format("{:.1f}%", 100.0 * r.embed_share) : "-";
    fmt::print("{:>6} {:>5} {:>6} {:>5} {:>5} {:>10.1f} {:>9.2f} {:>6.1f}% {:>7.1f}% {:>10.2f} {:>8} {:>7}\n", r.mode,
               r.cond_len, r.base, r.micro, r.world, r.step_s * 1e3, r.pairs_s, 100 * r.mfu, 100 * r.needed_util, r.peak_gib, scaling, embed);
  }
}

// Command-line settings.
struct Options {
  std::string generator = "configs/stage1_real.yaml";
  std::vector<int64_t> micros = {1, 2, 4};
  int steps = 10, warmup = 3, nproc = 0;
  // The released embedder's tokens per object (4 x 1,370 + 2 x 1,024) first, then 2,800.
  std::vector<int64_t> cond_lens = {7528, 2800};
  std::vector<std::string> fp8_base = {"off"};  // off / on / all: rows without / with the FP8 frozen base
  double peak_tflops = 989.4;
  bool checkpointing = false, profile = false, embed_timing = true;
  bool read_ahead = true;  // Trainer::set_read_ahead (off: the plain upload at each step's start)
  bool device_update = true;  // Trainer::set_device_update (off: the host waits for metrics and norm first)
  bool mlp_epilogue = true;   // models::mlp_epilogue::set_enabled (off: the ATen fc1, GELU, fc2 of the MLP)
  std::vector<int> lt_algo_ranks;  // models::mlp_epilogue::set_algo_ranks (GELU_AUX_BIAS, DGELU; empty: the default)
  std::vector<std::string> modes = {"tokens"};
};

// What every setting shares: the policy and its initial adapters, the communicators, the embedder.
struct Bench {
  Options o;
  DistEnv env;
  torch::Device device{torch::kCUDA};
  std::unique_ptr<PolicyModel> policy;
  std::vector<torch::Tensor> initial_adapters;
  std::unique_ptr<Communicator> solo, together;
  TimedEmbedder timed;
};

// One setting (mode, micro-batch, communicator): warm-up, timed steps, the row. fwd/needed: FLOPs per pair.
Row measure_setting(Bench& b, const PairSourceFactory& source, Communicator& comm, const std::string& mode, int64_t m,
                    double fwd_flops, double needed_flops, int64_t cond_len, const std::string& base) {
  const auto& o = b.o;
  TrainConfig cfg;
  cfg.model.config = o.generator;
  cfg.objective.beta = 500;
  cfg.optim.warmup_steps = 0;
  cfg.data.global_batch = m * comm.world_size();
  cfg.data.micro_batch = m;
  cfg.train.steps = o.warmup + o.steps;
  cfg.train.precision = "bf16";
  cfg.train.activation_checkpointing = o.checkpointing;
  cfg.train.device = "cuda";
  cfg.run.progress = false;
  {
    torch::NoGradGuard ng;
    auto params = b.policy->adapter_parameters();
    for (size_t i = 0; i < params.size(); ++i) params[i].second.copy_(b.initial_adapters[i]);
  }
  Trainer tr(cfg, *b.policy, source, comm, b.device);
  tr.set_read_ahead(o.read_ahead);
  tr.set_device_update(o.device_update);
  simu::models::mlp_epilogue::set_enabled(o.mlp_epilogue);
  if (!o.lt_algo_ranks.empty()) simu::models::mlp_epilogue::set_algo_ranks(o.lt_algo_ranks[0], o.lt_algo_ranks[1]);
  const bool inputs = mode == "inputs";
  if (inputs) tr.set_condition_embedder(b.timed.fn());
  for (int s = 0; s < o.warmup; ++s) tr.step();
  b.together->barrier();
  torch::cuda::synchronize();
  c10::cuda::CUDACachingAllocator::resetPeakStats(b.env.local_rank);
  b.timed.seconds = 0;
  b.timed.timing = true;
  const auto t0 = std::chrono::steady_clock::now();
  for (int s = 0; s < o.steps; ++s) tr.step();
  torch::cuda::synchronize();
  const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() / o.steps;
  b.timed.timing = false;
  const auto stats = c10::cuda::CUDACachingAllocator::getDeviceStats(b.env.local_rank);
  Row r;
  r.mode = mode;
  r.cond_len = cond_len;
  r.base = base;
  r.micro = m;
  r.world = comm.world_size();
  r.step_s = secs;
  r.pairs_s = cfg.data.global_batch / secs;
  r.mfu = 4.0 * fwd_flops * cfg.data.global_batch / (secs * r.world * o.peak_tflops * 1e12);
  r.needed_util = needed_flops * cfg.data.global_batch / (secs * r.world * o.peak_tflops * 1e12);
  r.peak_gib = stats.allocated_bytes[0].peak / double(1 << 30);
  r.embed_share = inputs && o.embed_timing ? b.timed.seconds / o.steps / secs : -1.0;
  if (o.profile && m == o.micros.front() && &comm == b.solo.get() && b.env.rank == 0) {
    const auto title = fmt::format("FM-DPO step ({}), micro-batch {}", mode, m);
    simu::bench::print_gpu_kernel_profile(title, [&] { tr.step(); }, 25);
    simu::bench::print_gpu_op_profile(title, [&] { tr.step(); }, 40);
  }
  b.together->barrier();
  return r;
}

// Every base (bf16, fp8) and micro-batch size of one condition mode and length, alone and (with several
// ranks) together. L: condition tokens per pair (tokens mode).
void measure_mode(Bench& b, const std::string& mode, int64_t cond_len, std::vector<Row>& rows) {
  const auto gcfg = simu::models::GeneratorConfig::from_official_file(b.o.generator);
  const auto& fc = gcfg.backbone;
  int64_t T = 0;
  for (const auto& s : fc.latents)
    if (s.name == "shape") T = s.tokens();
  const bool inputs = mode == "inputs";
  const int64_t L = inputs ? b.timed.embedder->num_tokens() : cond_len;
  // Synthetic pairs: enough for every setting.
  const int64_t n_pairs = 4 * 8 * std::max<int>(b.o.nproc, b.env.world_size);
  auto pairs = synthetic_pairs(n_pairs, T, fc.in_channels, L, fc.cond_channels, inputs);
  PairSourceFactory source = [pairs](int rank, int world, int64_t gb, uint64_t seed, DataPosition pos) -> std::unique_ptr<PairSource> {
    return std::make_unique<MemoryPairSource>(pairs, rank, world, gb, seed, pos);
  };
  const double full_flops = simu::models::flow_forward_flops(fc, 1, L);
  const double fwd_flops = step_pair_forward_flops(fc, static_cast<double>(T), static_cast<double>(L));
  const double needed_flops = needed_pair_flops(fc, static_cast<double>(T), static_cast<double>(L), 64, fwd_flops);
  if (b.env.rank == 0)
    print_header(b.o.generator, fc, T, L, mode, b.o.checkpointing, full_flops, fwd_flops, needed_flops, b.o.peak_tflops);
  for (const auto& fp8 : b.o.fp8_base) {
    // Switched off first: "all" after "on" re-quantises every layer of its scope.
    set_policy_fp8_base(*b.policy, false, simu::models::Fp8Backward::kFp8, "bench_fmdpo");
    if (fp8 != "off")
      set_policy_fp8_base(*b.policy, true, simu::models::Fp8Backward::kFp8, "bench_fmdpo --fp8-base",
                          fp8 == "all" ? simu::lora::Fp8Scope::kAll : simu::lora::Fp8Scope::kAdapted);
    const std::string base = fp8 == "off" ? "bf16" : fp8 == "on" ? "fp8" : "fp8all";
    for (int64_t m : b.o.micros)
      for (Communicator* comm : {b.solo.get(), b.together.get()}) {
        if (comm == b.together.get() && b.env.world_size == 1) continue;
        rows.push_back(measure_setting(b, source, *comm, mode, m, fwd_flops, needed_flops, L, base));
      }
  }
  set_policy_fp8_base(*b.policy, false, simu::models::Fp8Backward::kFp8, "bench_fmdpo");
}

// One rank's benchmark: the real-size policy (random base weights, LoRA r 64 / alpha 128 on the
// shape projections), the released embedder when inputs mode is asked for, every mode and setting.
void run_rank(const Options& o) {
  Bench b;
  b.o = o;
  b.env = DistEnv::from_environment();
  simu::log::set_rank(b.env.rank);
  c10::cuda::set_device(static_cast<c10::DeviceIndex>(b.env.local_rank));
  b.device = torch::Device(torch::kCUDA, b.env.local_rank);
  YAML::Node lora = YAML::Load(
      "{r: 64, alpha: 128, dropout: 0.0, target_modules: "
      "'.*blocks\\.\\d+\\.(self_attn\\.(to_qkv|to_out)\\.shape|cross_attn\\.shape\\.(to_q|to_kv|to_out))$'}");
  torch::manual_seed(0);
  b.policy = make_generator_policy(o.generator, "", lora, "", b.device);
  // Every setting starts from these adapters: GPU training is not bit-reproducible across GPUs, so
  // ranks that trained alone first no longer hold identical adapters for the multi-rank setting.
  for (auto& [name, p] : b.policy->adapter_parameters()) b.initial_adapters.push_back(p.detach().clone());
  if (std::find(o.modes.begin(), o.modes.end(), "inputs") != o.modes.end()) {
    b.timed.embedder = simu::models::CondEmbedder(simu::models::CondEmbedderConfig::sam3d_stage1());
    b.timed.sync = o.embed_timing;
    b.timed.embedder->to(b.device);
    b.timed.embedder->eval();
    for (auto& p : b.timed.embedder->parameters()) p.set_requires_grad(false);
  }
  b.solo = Communicator::create(DistEnv{}, b.device, std::chrono::minutes(10));
  b.together = Communicator::create(b.env, b.device, std::chrono::minutes(10));
  std::vector<Row> rows;
  for (const auto& mode : o.modes) {
    if (mode == "inputs") measure_mode(b, mode, 0, rows);  // the embedder's own length
    else
      for (int64_t L : o.cond_lens) measure_mode(b, mode, L, rows);
  }
  print_rows(rows, b.together->all_reduce_sum(alone_rates(rows)), b.env.rank);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"FM-DPO training-step benchmark (GPU, real-size generator with random weights)"};
  Options o;
  app.add_option("--generator", o.generator, "generator config (official layout)")->capture_default_str();
  app.add_option("--micro", o.micros, "micro-batch sizes")->delimiter(',')->capture_default_str();
  app.add_option("--steps", o.steps, "timed steps per setting")->capture_default_str();
  app.add_option("--warmup", o.warmup, "untimed steps per setting")->capture_default_str();
  app.add_option("--cond-len", o.cond_lens,
                 "condition tokens per pair (1024 channels) in tokens mode, one table block each (7528: the released "
                 "embedder's)")
      ->delimiter(',')
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--fp8-base", o.fp8_base,
                 "off, on, all: rows with the bf16 frozen base, the opt-in FP8 frozen base on the LoRA-wrapped layers "
                 "(train.fp8_base), on every frozen Linear (fp8_base_layers all); needs compute capability >= 8.9")
      ->delimiter(',')
      ->check(CLI::IsMember({"off", "on", "all"}))
      ->capture_default_str();
  app.add_option("--peak-tflops", o.peak_tflops, "device peak dense bf16 TFLOP/s for MFU")->capture_default_str();
  app.add_flag("--activation-checkpointing", o.checkpointing, "recompute the policy forward in backward");
  app.add_option("--nproc-per-node", o.nproc, "ranks (GPUs) to start (0: this process alone)")->capture_default_str();
  app.add_option("--embed-timing", o.embed_timing,
                 "time the embedder of inputs mode (a device synchronisation before and after it; off: no syncs, no embed column)")
      ->capture_default_str();
  app.add_flag("--profile", o.profile, "print the GPU kernels of one step (first micro-batch size, one rank) by time");
  app.add_option("--mlp-epilogue", o.mlp_epilogue,
                 "the frozen MLP's GELU in cuBLASLt epilogues (GELU_AUX_BIAS forward, DGELU backward; off: ATen's "
                 "fc1, GELU and fc2, the reference path)")
      ->capture_default_str();
  app.add_option("--lt-algo-ranks", o.lt_algo_ranks,
                 "the cuBLASLt heuristic ranks the epilogue products run, GELU_AUX_BIAS then DGELU "
                 "(mlp_epilogue::set_algo_ranks; default: the library's)")
      ->expected(2)->delimiter(',')->check(CLI::Range(0, 15));
  app.add_option("--device-update", o.device_update,
                 "the trainer's device-side update: all-reduce, clipping and AdamW issued behind the backward with "
                 "no host wait (off: the reference path, which reads the metrics and the norm first)")
      ->capture_default_str();
  app.add_option("--read-ahead", o.read_ahead,
                 "the trainer's read-ahead: the next batch staged in pinned memory and uploaded on a side stream "
                 "while a step runs (off: each step's batch stacked and copied at its start, the reference path)")
      ->capture_default_str();
  app.add_option("--cond-mode", o.modes,
                 "tokens (condition tokens in the pairs, --cond-len of them) and/or inputs (the released embedder's "
                 "inputs; its random-weight embedder runs in the step), e.g. tokens,inputs")
      ->delimiter(',')
      ->check(CLI::IsMember({"tokens", "inputs"}))
      ->capture_default_str();
  simu::cli::CommonOptions common;
  return simu::cli::run(app, argc, argv, common, [&]() -> int {
    SIMU_CHECK(common.sets.empty(), "bench_fmdpo: --set has no config to apply to (got --set {})", common.sets.front());
    if (!torch::cuda::is_available()) {
      fmt::print("bench_fmdpo: skipped: needs a CUDA device (none here)\n");
      return 0;
    }
    if (o.nproc > 1 && !std::getenv("RANK")) {
      std::vector<std::string> args;
      for (int i = 1; i < argc; ++i) {
        if (std::strcmp(argv[i], "--nproc-per-node") == 0) { ++i; continue; }
        args.push_back(argv[i]);
      }
      launch_local_ranks(o.nproc, args, std::chrono::seconds(1200));
      return 0;
    }
    run_rank(o);
    return 0;
  });
}
