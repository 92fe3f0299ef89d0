// The training loop on a small stand-in policy: objective vs independent math, activation
// checkpointing, accumulation, 2 ranks == 1 rank, interrupted-and-resumed == uninterrupted, configs.
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <thread>
#include <future>
#include <limits>
#include <map>

#include "common/error.h"
#include "common/fs.h"
#include "flow_rounding.h"
#include "test_util.h"
#include "toy_policy.h"
#include "training/trainer.h"

using namespace simu::training;
using simu::testing::memory_source;
using simu::testing::toy_config;
using simu::testing::ToyPolicy;

namespace {

constexpr int64_t T = 6, C = 4, L = 3, Cc = 5, R = 2;

// Rounding of the toy policy (tests/tolerance.h): a prediction passes x W (C terms), the condition's
// mean and product (L + Cc), the adapter (C + R), sin, three sums, tanh and the scale (6).
constexpr double kChain = C + L + Cc + C + R + 6;
// A member's FM loss from two fp32 paths of the prediction (batched, or one row; or another rank's
// split): the square doubles it, the mean over T C elements adds its sum.
double loss_tol() { return simu::testing::fm_loss_bound(simu::testing::two_paths(kChain), T * C); }
// Adapters after a few AdamW steps from gradients that differ only in summation order (micro-batches
// in separate backward passes, or ranks averaged by the all-reduce): the forward, backward and
// 2 x global batch x T row sums give delta = two_paths(2 kChain + 2 * 8 * T) ~ 1.3e-5 relative per
// gradient. AdamW is invariant to the gradient's scale; for elements not near 0 it passes a relative
// gradient error to the update as at most 2 sqrt(k) delta lr at step k (Cauchy-Schwarz over the
// moments' weights): over 4 steps 12.3 delta lr ~ 1.6e-6 absolute at lr 0.01, ~3e-6 of these ~0.5-sized
// adapters; 1e-5 leaves a factor 3.
constexpr double kAdamSteps = 1e-5;

std::vector<torch::Tensor> adapter_values(ToyPolicy& m) { return {m.A.detach().clone(), m.B.detach().clone()}; }

}  // namespace

// fmdpo_terms against a float64 per-pair evaluation written out from the paper's formulas.
TEST(Fmdpo, TermsMatchIndependentMath) {
  ToyPolicy m(C, Cc, R, 1);
  torch::manual_seed(5);
  FmdpoInputs in;
  in.x_pos = torch::randn({3, T, C});
  in.x_neg = torch::randn({3, T, C});
  in.cond = torch::randn({3, L, Cc});
  in.w = torch::tensor({1.0f, 0.1f, 1.0f});
  in.t = torch::rand({3});
  in.eps_pos = torch::randn({3, T, C});
  in.eps_neg = torch::randn({3, T, C});
  const double beta = 3.0;
  auto terms = fmdpo_terms(m, in, beta);
  EXPECT_TRUE(m.enabled);
  double loss = 0, loss_abs = 0;
  for (int b = 0; b < 3; ++b) {
    auto L = [&](const torch::Tensor& x, const torch::Tensor& e, bool adapters) {
      m.enabled = adapters;
      const double t = in.t[b].item<double>();
      auto xt = ((1 - t) * e[b] + t * x[b]).unsqueeze(0);
      auto pred = m.predict_shape(xt, torch::tensor({t * 1000}).to(torch::kFloat32), in.cond[b].unsqueeze(0), torch::zeros({1}));
      m.enabled = true;
      return (pred[0].to(torch::kFloat64) - (x[b] - e[b]).to(torch::kFloat64)).pow(2).mean().item<double>();
    };
    const double lp = L(in.x_pos, in.eps_pos, true), ln = L(in.x_neg, in.eps_neg, true);
    const double rp = L(in.x_pos, in.eps_pos, false), rn = L(in.x_neg, in.eps_neg, false);
    const double dth = lp - ln, dre = rp - rn;
    const double z = -beta / 2 * (dth - dre);
    const double per = std::log1p(std::exp(-z));  // -log sigmoid(z)
    // Each loss within loss_tol() of its magnitude: the differences absolutely, the per-pair term
    // through its slope (flow_rounding.h).
    const double max_loss = std::max({lp, ln, rp, rn});
    const double pp_abs = simu::testing::dpo_per_pair_abs_bound(beta, loss_tol(), max_loss, per);
    EXPECT_NEAR(terms.per_pair[b].item<double>(), per, pp_abs);
    EXPECT_NEAR(terms.d_theta[b].item<double>(), dth, loss_tol() * (lp + ln));
    EXPECT_NEAR(terms.d_ref[b].item<double>(), dre, loss_tol() * (rp + rn));
    loss += in.w[b].item<double>() * per / 3;
    loss_abs += in.w[b].item<double>() * pp_abs / 3;
  }
  // The weighted mean of three: their errors and 4 roundings more.
  EXPECT_NEAR(terms.loss.item<double>(), loss, loss_abs + simu::testing::gamma(4) * loss);
  EXPECT_FALSE(terms.loss_pos_ref.requires_grad());
}

// draw_pair_noise: t is logit-normal with the configured mean and std, the two noises are standard
// normal and independent of each other and of t, and a draw depends on (seed, step, pair) alone.
TEST(Fmdpo, PairNoiseIsLogitNormalSeparateAndReproducible) {
  const int64_t n = 4000;
  for (const auto& [mean, std] : {std::pair{0.0, 1.0}, std::pair{0.5, 2.0}}) {
    std::vector<double> logit, t;
    torch::Tensor eps_p = torch::empty({n, 3, 2}), eps_n = torch::empty({n, 3, 2});
    for (int64_t i = 0; i < n; ++i) {
      auto nz = draw_pair_noise(11, 3, i, {3, 2}, mean, std);
      const double ti = nz.t.item<double>();
      ASSERT_GT(ti, 0.0);
      ASSERT_LT(ti, 1.0);
      t.push_back(ti);
      logit.push_back(std::log(ti / (1 - ti)));
      eps_p[i] = nz.eps_pos;
      eps_n[i] = nz.eps_neg;
    }
    auto lg = torch::tensor(logit, torch::kFloat64);
    // Standard errors: std/sqrt(n) = 0.016 (x std) for the mean, about 0.011 (x std) for the std: the
    // bounds are 3.8 and 4.5 of them.
    EXPECT_NEAR(lg.mean().item<double>(), mean, 0.06 * std) << "mean " << mean;
    EXPECT_NEAR(lg.std().item<double>(), std, 0.05 * std) << "std " << std;
    // 24,000 standard normal values: standard errors 0.0065 (mean) and 0.0046 (std); 0.03 is 4.6 and 6.5.
    for (auto* e : {&eps_p, &eps_n}) {
      EXPECT_NEAR(e->mean().item<double>(), 0.0, 0.03);
      EXPECT_NEAR(e->std().item<double>(), 1.0, 0.03);
    }
    // Correlations over 24,000 element pairs: |r| < 0.03 is 4.6 standard errors.
    auto corr = [](const torch::Tensor& a, const torch::Tensor& b) {
      auto x = a.flatten().to(torch::kFloat64), y = b.flatten().to(torch::kFloat64);
      x = x - x.mean();
      y = y - y.mean();
      return ((x * y).sum() / (x.norm() * y.norm())).item<double>();
    };
    EXPECT_LT(std::abs(corr(eps_p, eps_n)), 0.03) << "eps+ and eps- are not independent";
    auto tt = torch::tensor(t, torch::kFloat64).view({n, 1, 1}).expand({n, 3, 2});
    EXPECT_LT(std::abs(corr(eps_p, tt)), 0.03) << "eps+ depends on t";
  }
  // Same (seed, step, pair) -> same draw; any of the three changed -> another draw.
  auto a = draw_pair_noise(11, 3, 5, {4, 2}, 0, 1);
  auto b = draw_pair_noise(11, 3, 5, {4, 2}, 0, 1);
  EXPECT_TRUE(torch::equal(a.t, b.t) && torch::equal(a.eps_pos, b.eps_pos) && torch::equal(a.eps_neg, b.eps_neg));
  EXPECT_FALSE(torch::equal(a.eps_pos, a.eps_neg));
  for (const auto& c : {draw_pair_noise(12, 3, 5, {4, 2}, 0, 1), draw_pair_noise(11, 4, 5, {4, 2}, 0, 1),
                        draw_pair_noise(11, 3, 6, {4, 2}, 0, 1)})
    EXPECT_FALSE(torch::equal(a.eps_pos, c.eps_pos));
}

// Recomputing the policy forward in backward gives the same gradients.
TEST(Fmdpo, ActivationCheckpointingSameGradients) {
  ToyPolicy m(C, Cc, R, 2);
  torch::manual_seed(6);
  FmdpoInputs in{torch::randn({2, T, C}), torch::randn({2, T, C}), torch::randn({2, L, Cc}), torch::ones({2}),
                 torch::rand({2}), torch::randn({2, T, C}), torch::randn({2, T, C})};
  fmdpo_terms(m, in, 2.0, false).loss.backward();
  auto ga = m.A.grad().clone(), gb = m.B.grad().clone();
  m.A.mutable_grad() = torch::Tensor();
  m.B.mutable_grad() = torch::Tensor();
  auto t2 = fmdpo_terms(m, in, 2.0, true);
  t2.loss.backward();
  // The recompute runs the same operations on the same inputs: bit for bit.
  EXPECT_TRUE(torch::equal(m.A.grad(), ga)) << "A: rel err " << simu::testing::rel_err(m.A.grad(), ga);
  EXPECT_TRUE(torch::equal(m.B.grad(), gb)) << "B: rel err " << simu::testing::rel_err(m.B.grad(), gb);
}

// micro 1 x accumulation 4 == micro 4 x accumulation 1 (same global batch).
TEST(Trainer, AccumulationMatchesOneMicroBatch) {
  auto pairs = simu::testing::toy_pairs(16, T, C, L, Cc, 9);
  auto solo_comm = make_solo_communicator();
  Communicator& comm = *solo_comm;
  std::vector<std::vector<torch::Tensor>> results;
  for (int64_t micro : {1, 4}) {
    ToyPolicy m(C, Cc, R, 3);
    Trainer tr(toy_config(simu::testing::temp_dir("accum" + std::to_string(micro)), 3, 4, micro), m, memory_source(pairs), comm, torch::kCPU);
    for (int s = 0; s < 3; ++s) tr.step();
    results.push_back(adapter_values(m));
  }
  EXPECT_TRUE(simu::testing::close(results[1][0], results[0][0], kAdamSteps, "A"));
  EXPECT_TRUE(simu::testing::close(results[1][1], results[0][1], kAdamSteps, "B"));
}

// Two ranks (threads, TCPStore on loopback, Gloo all-reduce) == one rank with the same global batch.
TEST(Trainer, TwoRanksMatchOneRank) {
  auto pairs = simu::testing::toy_pairs(24, T, C, L, Cc, 10);
  const int steps = 4;
  std::vector<torch::Tensor> solo;
  {
    auto solo_comm = make_solo_communicator();
    Communicator& comm = *solo_comm;
    ToyPolicy m(C, Cc, R, 4);
    Trainer tr(toy_config(simu::testing::temp_dir("solo"), steps, 8, 2), m, memory_source(pairs), comm, torch::kCPU);
    for (int s = 0; s < steps; ++s) tr.step();
    solo = adapter_values(m);
  }
  const int port = free_port();
  std::string backends[2];
  auto rank_fn = [&](int rank) {
    DistEnv env;
    env.rank = rank;
    env.world_size = 2;
    env.master_port = port;
    auto comm = make_cpu_communicator(connect_store(env, std::chrono::seconds(20)), rank, 2, std::chrono::seconds(30));
    backends[rank] = comm->backend();
    ToyPolicy m(C, Cc, R, 4);
    Trainer tr(toy_config(simu::testing::temp_dir("duo" + std::to_string(rank)), steps, 8, 2), m, memory_source(pairs),
               *comm, torch::kCPU);
    for (int s = 0; s < steps; ++s) tr.step();
    return adapter_values(m);
  };
  auto f0 = std::async(std::launch::async, rank_fn, 0);
  auto f1 = std::async(std::launch::async, rank_fn, 1);
  auto r0 = f0.get(), r1 = f1.get();
  // The gradients really went through c10d ProcessGroupGloo (not the store fallback).
  EXPECT_TRUE(have_gloo()) << "this build has no gloo headers: install libgloo-dev and reconfigure";
  EXPECT_EQ(backends[0], "gloo");
  EXPECT_EQ(backends[1], "gloo");
  for (int i = 0; i < 2; ++i) {
    EXPECT_TRUE(torch::equal(r0[i], r1[i])) << "ranks disagree";
    EXPECT_TRUE(simu::testing::close(r0[i], solo[i], kAdamSteps, i ? "B" : "A"));
  }
  EXPECT_FALSE(torch::equal(solo[0], ToyPolicy(C, Cc, R, 4).A)) << "training did not move the adapter";
}

// Stopping at step 2 and resuming from the checkpoint gives bit-identical adapters, optimizer state
// and metrics to an uninterrupted run.
TEST(Trainer, ResumeIsBitExact) {
  auto pairs = simu::testing::toy_pairs(10, T, C, L, Cc, 11);  // 2 batches per epoch: crosses epochs
  auto solo_comm = make_solo_communicator();
  Communicator& comm = *solo_comm;
  const std::string out_a = simu::testing::temp_dir("resume_a"), out_b = simu::testing::temp_dir("resume_b");
  std::vector<StepMetrics> ma, mb;
  ToyPolicy a(C, Cc, R, 5);
  {
    Trainer tr(toy_config(out_a, 6, 4, 2), a, memory_source(pairs), comm, torch::kCPU);
    for (int s = 0; s < 6; ++s) ma.push_back(tr.step());
  }
  {
    ToyPolicy b0(C, Cc, R, 5);
    Trainer tr(toy_config(out_b, 6, 4, 2), b0, memory_source(pairs), comm, torch::kCPU);
    for (int s = 0; s < 2; ++s) mb.push_back(tr.step());
    tr.save();
    tr.step();  // work lost by the "crash"
  }
  ToyPolicy b(C, Cc, R, 5, 99);  // different adapter init: everything must come from the checkpoint
  Trainer tr(toy_config(out_b, 6, 4, 2), b, memory_source(pairs), comm, torch::kCPU);
  tr.resume(resolve_resume(out_b + "/checkpoints", "latest"));
  EXPECT_EQ(tr.steps_done(), 2);
  for (int s = 2; s < 6; ++s) mb.push_back(tr.step());
  EXPECT_TRUE(torch::equal(a.A, b.A) && torch::equal(a.B, b.B)) << "adapters differ";
  for (int s = 0; s < 6; ++s) {
    EXPECT_EQ(ma[s].loss, mb[s].loss) << "step " << s;
    EXPECT_EQ(ma[s].grad_norm, mb[s].grad_norm) << "step " << s;
  }
}

// One step's logged metrics against a float64 evaluation of every pair before the step, written out
// from the definitions: loss = mean(w per_pair), accuracy = share of pairs with d_theta < d_ref,
// margin = mean of -beta/2 (d_theta - d_ref), and per kind the mean policy / reference flow-matching
// losses of each member (kind 0 "completion", weight 1.0; kind 1 "preservation", weight 0.1).
TEST(Trainer, StepMetricsMatchIndependentMath) {
  auto pairs = simu::testing::toy_pairs(8, T, C, L, Cc, 14);
  auto cfg = toy_config(simu::testing::temp_dir("metrics_math"), 1, 8, 4);  // one batch = all 8 pairs
  ToyPolicy m(C, Cc, R, 9);
  const double beta = cfg.objective.beta;
  double loss = 0, correct = 0, margin = 0, max_loss = 0, min_abs_z = std::numeric_limits<double>::infinity();
  std::map<std::string, double> per_kind;
  std::map<int, double> count;
  for (const auto& p : *pairs) {
    auto nz = draw_pair_noise(cfg.train.seed, 0, p.id, p.x_pos.sizes(), 0.0, 1.0);
    const double t = nz.t.item<double>();
    auto L = [&](const torch::Tensor& x, const torch::Tensor& e, bool adapters) {
      torch::NoGradGuard ng;
      m.enabled = adapters;
      auto pred = m.predict_shape(((1 - t) * e + t * x).unsqueeze(0), torch::tensor({t * 1000}).to(torch::kFloat32),
                                  p.cond.unsqueeze(0), torch::zeros({1}));
      m.enabled = true;
      return (pred[0].to(torch::kFloat64) - (x - e).to(torch::kFloat64)).pow(2).mean().item<double>();
    };
    const double pp = L(p.x_pos, nz.eps_pos, true), pn = L(p.x_neg, nz.eps_neg, true);
    const double rp = L(p.x_pos, nz.eps_pos, false), rn = L(p.x_neg, nz.eps_neg, false);
    const double z = -beta / 2 * ((pp - pn) - (rp - rn));
    max_loss = std::max({max_loss, pp, pn, rp, rn});
    min_abs_z = std::min(min_abs_z, std::abs(z));
    const double w = p.kind == simu::data::PairKind::OcclusionCompletion ? 1.0 : 0.1;
    loss += w * std::log1p(std::exp(-z)) / 8;
    correct += (pp - pn) < (rp - rn) ? 1.0 / 8 : 0.0;
    margin += z / 8;
    const std::string kn = p.kind == simu::data::PairKind::OcclusionCompletion ? "completion" : "preservation";
    per_kind[kn + "/policy_pos"] += pp;
    per_kind[kn + "/policy_neg"] += pn;
    per_kind[kn + "/ref_pos"] += rp;
    per_kind[kn + "/ref_neg"] += rn;
    count[static_cast<int>(p.kind)] += 1;
  }
  auto solo_comm = make_solo_communicator();
  Communicator& comm = *solo_comm;
  Trainer tr(cfg, m, memory_source(pairs), comm, torch::kCPU);
  const auto sm = tr.step();
  // Per pair the four losses within loss_tol() (flow_rounding.h): the per-pair term, the margin z and
  // the accuracy's comparison move by at most beta/2 x 4 loss_tol() max_loss.
  const double z_abs = simu::testing::dpo_per_pair_abs_bound(beta, loss_tol(), max_loss, 0.0);
  EXPECT_NEAR(sm.loss, loss, z_abs + simu::testing::gamma(8 + 4) * loss);  // + the mean over 8 pairs
  // A share of 8 pairs: exact, as no pair's z is within its bound of 0 (checked).
  EXPECT_GT(min_abs_z, z_abs) << "a pair sits on the accuracy's edge: rounding could flip it";
  EXPECT_EQ(sm.accuracy, correct);
  EXPECT_NEAR(sm.margin, margin, z_abs + simu::testing::gamma(8) * std::abs(margin));
  ASSERT_EQ(sm.per_kind.size(), 8u);
  for (const auto& [k, v] : per_kind) {
    const double want = v / count[k.rfind("completion", 0) == 0 ? 0 : 1];
    ASSERT_TRUE(sm.per_kind.count(k)) << k;
    EXPECT_NEAR(sm.per_kind.at(k), want, (loss_tol() + simu::testing::gamma(8)) * want) << k;  // a mean of losses
  }
  // The same values reach the logged scalars under their documented names.
  const auto sc = sm.scalars();
  for (const char* k : {"loss", "accuracy", "margin", "grad_norm", "lr", "pairs_per_s", "completion/policy_pos",
                        "preservation/ref_neg"})
    EXPECT_TRUE(sc.count(k)) << k;
  EXPECT_EQ(sc.at("accuracy"), sm.accuracy);
}

// run(): metrics lines, TensorBoard file, checkpoints, exported adapter (rank 0 output layout).
TEST(Trainer, RunWritesOutputs) {
  auto pairs = simu::testing::toy_pairs(8, T, C, L, Cc, 12);
  auto solo_comm = make_solo_communicator();
  Communicator& comm = *solo_comm;
  const std::string out = simu::testing::temp_dir("run");
  ToyPolicy m(C, Cc, R, 6);
  Trainer tr(toy_config(out, 5, 4, 4), m, memory_source(pairs), comm, torch::kCPU);
  tr.run();
  std::ifstream in(out + "/metrics.jsonl");
  int lines = 0;
  for (std::string l; std::getline(in, l);) ++lines;
  EXPECT_EQ(lines, 5);
  auto cks = list_checkpoints(out + "/checkpoints");
  ASSERT_EQ(cks.size(), 3u);  // steps 2, 4 and the end (5)
  auto ck = load_checkpoint(cks.back());
  EXPECT_EQ(ck.step, 5);
  EXPECT_TRUE(torch::equal(ck.adapter.at("base_model.model.toy.lora_A.weight"), m.A));
  EXPECT_TRUE(ck.optimizer.count("base_model.model.toy.lora_A.weight.exp_avg"));
  EXPECT_TRUE(std::filesystem::exists(out + "/adapter/adapter_config.json"));
  bool tb = false;
  for (auto& e : std::filesystem::directory_iterator(out + "/tensorboard"))
    tb |= e.path().filename().string().rfind("events.out.tfevents.", 0) == 0;
  EXPECT_TRUE(tb);
}

// The step-time split: a data source that takes 60 ms per batch shows up as data wait, and the phases
// add up to no more than the step.
TEST(Trainer, StepTimeSplit) {
  auto pairs = simu::testing::toy_pairs(8, T, C, L, Cc, 13);
  struct Slow : PairSource {
    std::unique_ptr<PairSource> inner;
    std::vector<Pair> next_batch() override {
      std::this_thread::sleep_for(std::chrono::milliseconds(60));
      return inner->next_batch();
    }
    DataPosition position() const override { return inner->position(); }
  };
  auto slow = [pairs](int rank, int world, int64_t gb, uint64_t seed, DataPosition pos) -> std::unique_ptr<PairSource> {
    auto s = std::make_unique<Slow>();
    s->inner = std::make_unique<MemoryPairSource>(pairs, rank, world, gb, seed, pos);
    return s;
  };
  auto solo_comm = make_solo_communicator();
  Communicator& comm = *solo_comm;
  ToyPolicy m(C, Cc, R, 7);
  Trainer tr(toy_config(simu::testing::temp_dir("timing"), 2, 4, 2), m, slow, comm, torch::kCPU);
  const auto sm = tr.step();
  // sleep_for waits at least its 60 ms, on any load; 5 ms below it allows for the clock's granularity.
  EXPECT_GE(sm.seconds_data, 0.055);
  for (double v : {sm.seconds_compute, sm.seconds_allreduce, sm.seconds_optimizer}) EXPECT_GE(v, 0.0);
  // Disjoint intervals of one clock within the step; 1 ns for the float64 sum of four durations.
  EXPECT_LE(sm.seconds_data + sm.seconds_compute + sm.seconds_allreduce + sm.seconds_optimizer, sm.seconds_step + 1e-9);
  EXPECT_DOUBLE_EQ(sm.pairs_per_s, 4 / sm.seconds_step);  // the same division
  const auto sc = sm.scalars();
  for (const char* k : {"time/step_s", "time/data_wait_s", "time/compute_s", "time/allreduce_s", "time/optimizer_s"})
    EXPECT_TRUE(sc.count(k)) << k;
}

// Typos, wrong types and impossible batch splits are errors that name the file and the key.
TEST(TrainConfig, BadConfigsAreClearErrors) {
  const std::string dir = simu::testing::temp_dir("badcfg");
  auto expect_error = [&](const std::string& yaml, const std::string& needle) {
    std::ofstream(dir + "/c.yaml") << yaml;
    try {
      TrainConfig::load(dir + "/c.yaml");
      ADD_FAILURE() << "no error for: " << yaml;
    } catch (const simu::Error& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  expect_error("model: {config: x}\noptim: {lrr: 1}\n", "unknown key 'optim.lrr'");
  expect_error("model: {config: x}\noptim: {lr: fast}\n", "optim.lr");
  expect_error("optim: {lr: 1}\n", "missing required key 'model.config'");
  expect_error("model: {config: x}\ntrain: {precision: fp8}\n", "train.precision");
  // The FP8 frozen base: CUDA and bf16 only; its backward is fp8 or bf16.
  expect_error("model: {config: x}\ntrain: {fp8_base: true, device: cpu}\n", "key 'train.fp8_base'");
  expect_error("model: {config: x}\ntrain: {fp8_base: true, precision: fp32}\n", "key 'train.fp8_base'");
  expect_error("model: {config: x}\ntrain: {fp8_base_backward: e5m2}\n", "train.fp8_base_backward");
  expect_error("model: {config: x}\ntrain: {fp8_base_layers: mlp}\n", "train.fp8_base_layers");
  expect_error("model: {config: x}\noptim: {schedule: linear}\n", "optim.schedule");
  // Batch split checked against the world size when the trainer starts.
  auto cfg = toy_config(simu::testing::temp_dir("badsplit"), 1, 6, 4);
  auto solo_comm = make_solo_communicator();
  Communicator& comm = *solo_comm;
  ToyPolicy m(C, Cc, R, 1);
  try {
    Trainer tr(cfg, m, memory_source(simu::testing::toy_pairs(8, T, C, L, Cc, 1)), comm, torch::kCPU);
    ADD_FAILURE() << "no error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("global_batch 6 is not divisible by micro_batch 4"), std::string::npos) << e.what();
  }
}

// Values outside their domain are refused at load (they trained to a NaN loss and exported a NaN
// adapter with exit 0 before), each error naming the config file and the key; the lora: section's
// errors name the training config, not the model's.
TEST(TrainConfig, OutOfDomainValuesAreRefusedAtLoad) {
  const std::string dir = simu::testing::temp_dir("domain");
  const std::string file = dir + "/train.yaml";
  std::ofstream(file) << "model: {config: model.json}\nlora: {r: 2}\ndata: {cache: p.h5}\n";
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"optim.lr=1e308", "key 'optim.lr'"},
      {"optim.lr=.nan", "key 'optim.lr'"},
      {"optim.lr=-1", "key 'optim.lr'"},
      {"optim.eps=.inf", "key 'optim.eps'"},
      {"optim.betas=[0.9, 1.5]", "key 'optim.betas'"},
      {"optim.weight_decay=-0.1", "key 'optim.weight_decay'"},
      {"optim.min_lr_ratio=2", "key 'optim.min_lr_ratio'"},
      {"optim.clip_grad_norm=.nan", "key 'optim.clip_grad_norm'"},
      {"objective.beta=.inf", "key 'objective.beta'"},
      {"objective.beta=0", "key 'objective.beta'"},
      {"objective.weight_completion=-1", "key 'objective.weight_completion'"},
      {"objective.t_std=.nan", "key 'objective.t_std'"},
      {"lora.alpha=9223372036854775807", "key 'lora.alpha'"},
      {"lora.alpha=.inf", "key 'lora.alpha'"},
      {"lora.r=0", "key 'lora.r'"},
      {"lora.target_modules=(?=x)", "key 'lora.target_modules'"},
      {"lora.rr=3", "unknown key 'lora.rr'"},
      {"dist.timeout_s=.inf", "key 'dist.timeout_s'"},
      {"data.prefetch=100000", "key 'data.prefetch'"},
  };
  for (const auto& [set, needle] : cases) {
    try {
      TrainConfig::load(file, {set});
      ADD_FAILURE() << "no error for --set " << set;
    } catch (const simu::Error& e) {
      const std::string msg = e.what();
      EXPECT_EQ(msg.rfind(file, 0), 0u) << set << " -> " << msg;
      EXPECT_NE(msg.find(needle), std::string::npos) << set << " -> " << msg;
    }
  }
  EXPECT_NO_THROW(TrainConfig::load(file, {"optim.lr=1", "objective.beta=5000", "lora.alpha=1e6"}));
}

// Outputs of an earlier run are not overwritten by a fresh run unless --overwrite; data.cache unset
// is named.
TEST(TrainConfig, EarlierRunIsRefusedUnlessOverwrite) {
  const std::string out = simu::testing::temp_dir("prep");
  auto cfg = toy_config(out, 1, 4, 4);
  auto msg = [&](const std::function<void()>& f) {
    try {
      f();
    } catch (const simu::Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  EXPECT_NE(msg([&] { prepare_out_dir(cfg, false, false, true); }).find("key 'data.cache' is missing"), std::string::npos);
  cfg.data.cache = "p.h5";
  EXPECT_EQ(msg([&] { prepare_out_dir(cfg, false, false, true); }), "");  // nothing there yet
  std::filesystem::create_directories(out + "/checkpoints/step_00000001");
  std::ofstream(out + "/metrics.jsonl") << "{}\n";
  const auto m = msg([&] { prepare_out_dir(cfg, false, false, true); });
  EXPECT_NE(m.find("already holds an earlier run (checkpoints, metrics.jsonl)"), std::string::npos) << m;
  EXPECT_EQ(msg([&] { prepare_out_dir(cfg, true, false, true); }), "");  // --resume continues it
  EXPECT_EQ(msg([&] { prepare_out_dir(cfg, false, true, false); }), "");  // other ranks leave it to rank 0
  EXPECT_TRUE(std::filesystem::exists(out + "/checkpoints"));
  EXPECT_EQ(msg([&] { prepare_out_dir(cfg, false, true, true); }), "");
  EXPECT_FALSE(std::filesystem::exists(out + "/checkpoints"));
  EXPECT_FALSE(std::filesystem::exists(out + "/metrics.jsonl"));
}

// A non-finite loss stops training with an error naming the step, before the update: the adapters
// keep their values and the last checkpoint stays the newest.
TEST(Trainer, NonFiniteLossStopsBeforeTheUpdate) {
  auto pairs = simu::testing::toy_pairs(8, T, C, L, Cc, 21);
  auto solo_comm = make_solo_communicator();
  Communicator& comm = *solo_comm;
  const std::string out = simu::testing::temp_dir("nonfinite");
  ToyPolicy m(C, Cc, R, 6);
  auto cfg = toy_config(out, 6, 8, 8);  // every step sees all 8 pairs
  std::shared_ptr<std::vector<Pair>> poisoned = std::make_shared<std::vector<Pair>>(*pairs);
  Trainer tr(cfg, m, [&](int rank, int world, int64_t gb, uint64_t seed, DataPosition pos) -> std::unique_ptr<PairSource> {
    return std::make_unique<MemoryPairSource>(poisoned, rank, world, gb, seed, pos);
  }, comm, torch::kCPU);
  tr.step();
  tr.step();
  const auto dir = tr.save();  // checkpoint at step 2
  // From now on one pair holds NaN (as a corrupt cache or an overflowing objective would produce).
  (*poisoned)[3].x_pos = (*poisoned)[3].x_pos.clone();
  (*poisoned)[3].x_pos[0][0] = std::numeric_limits<float>::quiet_NaN();
  const auto before = adapter_values(m);
  std::string msg;
  try {
    tr.step();
  } catch (const simu::Error& e) {
    msg = e.what();
  }
  EXPECT_NE(msg.find("step 3: non-finite loss"), std::string::npos) << msg;
  EXPECT_NE(msg.find(cfg.file), std::string::npos) << msg;
  EXPECT_EQ(tr.steps_done(), 2);
  const auto after = adapter_values(m);
  EXPECT_TRUE(torch::equal(before[0], after[0]));
  EXPECT_TRUE(torch::equal(before[1], after[1]));
  const auto cks = list_checkpoints(out + "/checkpoints");
  ASSERT_FALSE(cks.empty());
  EXPECT_EQ(load_checkpoint(cks.back()).step, 2);
}

#include <set>

#include "data/pair_cache.h"
#include "lora/lora.h"
#include "models/generator.h"
#include "training/generator_policy.h"

// configs/lora64.yaml holds the paper's recipe (Sec. 3.4 and the supplementary fine-tuning details),
// and its target pattern wraps exactly the 120 shape-branch attention projections of the real
// 24-block model (built here at 64 channels: the module names do not depend on the width).
TEST(TrainConfig, Lora64IsThePapersRecipe) {
  const std::string file = simu::testing::source_dir() + "/configs/lora64.yaml";
  auto cfg = TrainConfig::load(file);
  simu::config::Reader lr(cfg.lora, file, "lora");
  auto lc = simu::lora::LoraConfig::from(lr);
  EXPECT_EQ(lc.r, 64);
  EXPECT_EQ(lc.alpha, 128.0);
  EXPECT_EQ(lc.dropout, 0.0);
  EXPECT_FALSE(lc.use_rslora);
  EXPECT_EQ(cfg.objective.beta, 500.0);
  EXPECT_EQ(cfg.objective.weight_of(simu::data::PairKind::OcclusionCompletion), 1.0);
  EXPECT_EQ(cfg.objective.weight_of(simu::data::PairKind::CleanPreservation), 0.1);
  EXPECT_EQ(cfg.objective.t_mean, 0.0);
  EXPECT_EQ(cfg.objective.t_std, 1.0);
  EXPECT_EQ(cfg.optim.lr, 1e-5);
  EXPECT_EQ(cfg.optim.warmup_steps, 300);
  EXPECT_EQ(cfg.optim.weight_decay, 0.01);
  EXPECT_EQ(cfg.optim.clip_grad_norm, 1.0);
  EXPECT_EQ(cfg.train.precision, "bf16");
  EXPECT_EQ(cfg.train.steps, 1500);
  EXPECT_EQ(cfg.data.global_batch, 16);
  EXPECT_FALSE(cfg.model.config.empty());
  EXPECT_FALSE(cfg.model.weights.empty());
  EXPECT_FALSE(cfg.data.cache.empty());
  const std::string b = "module.generator.backbone.reverse_fn.backbone.";
  auto gen = simu::models::load_generator(simu::testing::source_dir() + "/configs/stage1_real.yaml", "", torch::kCPU,
                                          {b + "model_channels=64", b + "cond_channels=64"});
  auto report = simu::lora::inject_lora(*gen, lc);
  std::set<std::string> want;
  for (int i = 0; i < 24; ++i)
    for (const char* proj : {"self_attn.to_qkv.shape", "self_attn.to_out.shape", "cross_attn.shape.to_q",
                             "cross_attn.shape.to_kv", "cross_attn.shape.to_out"})
      want.insert(fmt::format("reverse_fn.backbone.blocks.{}.{}", i, proj));
  EXPECT_EQ(report.layers, 120);
  EXPECT_EQ(std::set<std::string>(report.paths.begin(), report.paths.end()), want);
}

// The HDF5 cache as the trainer's source: this rank's share with record indices as ids, training
// steps over pairs whose condition lengths differ, and clear errors for a missing or truncated cache.
TEST(Trainer, PairCacheSourceAndBadCache) {
  const std::string dir = simu::testing::temp_dir("cache_src");
  const std::string path = dir + "/pairs.h5";
  simu::data::make_synthetic_cache(path, 8, {T, C}, {L, Cc}, 3, torch::kFloat32);
  auto factory = pair_cache_source(path, 2);
  auto src = factory(1, 2, 4, 0, DataPosition{});
  auto b = src->next_batch();
  ASSERT_EQ(b.size(), 2u);
  for (const auto& p : b) {
    EXPECT_GE(p.id, 0);
    EXPECT_LT(p.id, 8);
    EXPECT_EQ(p.x_pos.sizes(), (std::vector<int64_t>{T, C}));
    EXPECT_LE(p.cond.size(0), L);
  }
  EXPECT_EQ(src->position().step, 1);
  // Training over it (variable condition lengths run as separate forwards).
  auto solo_comm = make_solo_communicator();
  Communicator& comm = *solo_comm;
  ToyPolicy m(C, Cc, R, 8);
  Trainer tr(toy_config(simu::testing::temp_dir("cache_train"), 2, 4, 4), m, factory, comm, torch::kCPU);
  auto s = tr.step();
  EXPECT_TRUE(std::isfinite(s.loss) && s.loss > 0);
  // Missing and truncated caches.
  auto expect_error = [&](const std::string& bad) {
    try {
      auto s2 = factory(0, 1, 4, 0, DataPosition{});
      (void)s2;
      auto s3 = pair_cache_source(bad, 2)(0, 1, 4, 0, DataPosition{});
      s3->next_batch();
      ADD_FAILURE() << "no error for " << bad;
    } catch (const simu::Error& e) {
      EXPECT_NE(std::string(e.what()).find(bad), std::string::npos) << e.what();
    }
  };
  expect_error(dir + "/missing.h5");
  const std::string bytes = simu::fs::read_file(path);
  std::ofstream(dir + "/truncated.h5", std::ios::binary) << bytes.substr(0, bytes.size() / 3);
  expect_error(dir + "/truncated.h5");
}

// A run stopped early (run.stop_at_step, run.stop_after_s) writes a checkpoint and no export; resuming it with the full
// run gives the uninterrupted run's adapter bit for bit (the schedule stays over train.steps).
TEST(Trainer, StopAtStepThenResumeEqualsOneRun) {
  auto pairs = simu::testing::toy_pairs(8, T, C, L, Cc, 22);
  auto solo_comm = make_solo_communicator();
  Communicator& comm = *solo_comm;
  const std::string whole = simu::testing::temp_dir("stop_whole"), parts = simu::testing::temp_dir("stop_parts");
  ToyPolicy a(C, Cc, R, 8);
  Trainer(toy_config(whole, 5, 4, 2), a, memory_source(pairs), comm, torch::kCPU).run();
  auto first = toy_config(parts, 5, 4, 2);
  first.run.stop_at_step = 3;  // not a multiple of checkpoint_every (2): the stop itself checkpoints
  ToyPolicy b(C, Cc, R, 8);
  Trainer(first, b, memory_source(pairs), comm, torch::kCPU).run();
  EXPECT_EQ(load_checkpoint(*latest_checkpoint(parts + "/checkpoints")).step, 3);
  EXPECT_FALSE(std::filesystem::exists(parts + "/adapter")) << "a paused run exported";
  ToyPolicy c(C, Cc, R, 8, 99);
  Trainer tr(toy_config(parts, 5, 4, 2), c, memory_source(pairs), comm, torch::kCPU);
  tr.resume(resolve_resume(parts + "/checkpoints", "latest"));
  tr.run();
  EXPECT_TRUE(torch::equal(a.A, c.A) && torch::equal(a.B, c.B)) << "adapters differ";
  EXPECT_TRUE(std::filesystem::exists(parts + "/adapter/adapter_config.json"));
  // run.stop_after_s: any positive time has passed after the first step.
  const std::string timed = simu::testing::temp_dir("stop_timed");
  auto cfg = toy_config(timed, 5, 4, 2);
  cfg.run.stop_after_s = 1e-9;
  ToyPolicy d(C, Cc, R, 8);
  Trainer(cfg, d, memory_source(pairs), comm, torch::kCPU).run();
  EXPECT_EQ(load_checkpoint(*latest_checkpoint(timed + "/checkpoints")).step, 1);
}
