// Stage-1 pretraining (train_stage1's objective and loop) on a tiny model on the CPU: the step's loss
// against an independent per-sample evaluation of the flow-matching formulas, the per-sample draws,
// 2 ranks == 1 rank, interrupted-and-resumed == uninterrupted (parameters, EMA, optimizer), learning a
// constant target, the export in the released layout, the official initialisation and bad configs.
#include <future>
#include <thread>

#include "models/cond_embedder.h"
#include "models/generator.h"
#include "stage1_fixture.h"
#include "training/stage1_data.h"

using namespace simu::training;
using simu::testing::tiny_objective;
using simu::testing::tiny_samples;
using simu::testing::tiny_stage1_config;

namespace {

// Every trained tensor of a trainer's model, cloned.
std::vector<torch::Tensor> weights_of(Trainer& tr) {
  std::vector<torch::Tensor> out;
  for (const auto& [name, p] : tr.objective().parameters()) out.push_back(p.detach().clone());
  return out;
}

}  // namespace

// One step's loss and metrics against a float64 evaluation of every sample alone, written out from
// the formulas: x_t = (1 - t) x0 + t x1, target x1 - x0, the condition times 0 when dropped, d = 0,
// loss = mean over samples of the sum over latents of mean((v - target)^2).
TEST(Stage1Objective, StepLossMatchesIndependentMath) {
  const auto out = simu::testing::temp_dir("s1_math");
  auto cfg = tiny_stage1_config(out, 1, 4, 2, "objective: {p_unconditional: 0.5}\n");
  auto samples = tiny_samples(6, 11);
  auto objective = tiny_objective(cfg, samples);
  // The same model, built apart (same seed), evaluated one sample at a time before the step.
  auto model = make_stage1_model(cfg.model.generator, cfg.model.embedder, "", torch::kCPU, cfg.train.seed);
  auto targets = make_shape_targets(cfg.targets, model->generator->config().backbone.latent("shape"), simu::testing::kTinyR,
                                    torch::kCPU, cfg.file);
  const auto& spec = model->generator->config().backbone;
  std::vector<std::vector<int64_t>> shapes;
  for (const auto& l : spec.latents) shapes.push_back({l.tokens(), l.in_channels});
  EpochOrder order(samples->size(), 0, 1, 4, cfg.data.seed, {});
  double loss = 0, dropped = 0;
  std::map<std::string, double> per_latent;
  for (int64_t row : order.next()) {
    torch::NoGradGuard ng;
    const auto draws = draw_sample(cfg.train.seed, 0, samples->ids[row], shapes, cfg.objective);
    std::map<std::string, torch::Tensor> inputs;
    for (const auto& [name, v] : samples->inputs) inputs[name] = v.narrow(0, row, 1);
    auto cond = model->embedder->forward(decode_inputs(inputs));
    if (draws.drop_condition) cond = cond * 0;
    dropped += draws.drop_condition ? 0.25 : 0.0;
    const double t = draws.t.item<double>();
    simu::models::Latents x_t, want;
    for (size_t l = 0; l < spec.latents.size(); ++l) {
      const auto& name = spec.latents[l].name;
      auto x1 = name == "shape" ? targets(samples->occupancy.narrow(0, row, 1))
                                : samples->pose.at(name).narrow(0, row, 1).unsqueeze(1);
      const auto x0 = draws.eps[l].unsqueeze(0);
      x_t[name] = (1 - t) * x0 + t * x1;
      want[name] = (x1 - x0).to(torch::kFloat64);
    }
    auto v = model->backbone()->forward(x_t, torch::tensor({static_cast<float>(t * 1000)}), cond, torch::zeros({1}));
    for (const auto& [name, w] : want) {
      const double mse = (v.at(name).to(torch::kFloat64) - w).pow(2).mean().item<double>();
      loss += mse / 4;
      per_latent["loss/" + name] += mse / 4;
    }
  }
  auto solo = make_solo_communicator();
  Trainer tr(cfg, std::move(objective), *solo, torch::kCPU);
  const auto m = tr.step();
  // fp32 forwards of 2-row vs 1-row batches: a few units of 2^-24 per product over ~10^2-term sums.
  EXPECT_NEAR(m.loss, loss, 1e-5 * loss);
  for (const auto& [k, v] : per_latent) EXPECT_NEAR(m.per_kind.at(k), v, 1e-5 * v) << k;
  EXPECT_EQ(m.per_kind.at("condition_dropped"), dropped);
  EXPECT_GT(dropped, 0.0) << "pick a seed where some condition is dropped";
  EXPECT_LT(dropped, 1.0);
  EXPECT_TRUE(std::isnan(m.accuracy));  // not FM-DPO's
  EXPECT_TRUE(m.scalars().count("samples_per_s"));
  EXPECT_FALSE(m.scalars().count("accuracy"));
}

// draw_sample: t logit-normal, dropout and shortcut at their rates, d in {1/2^i}, a draw a function of
// (seed, step, sample) alone.
TEST(Stage1Objective, DrawsAreSeededAndDistributed) {
  FlowObjectiveConfig c;
  c.t_mean = 0.5;
  c.t_std = 2.0;
  c.p_unconditional = 0.1;
  c.shortcut_fraction = 0.25;
  const int64_t n = 4000;
  std::vector<double> logit;
  double drops = 0, shortcuts = 0;
  std::set<float> ds;
  for (int64_t i = 0; i < n; ++i) {
    const auto s = draw_sample(5, 2, i, {{3, 2}}, c);
    const double t = s.t.item<double>();
    logit.push_back(std::log(t / (1 - t)));
    drops += s.drop_condition;
    shortcuts += s.d > 0;
    if (s.d > 0) ds.insert(s.d);
  }
  auto lg = torch::tensor(logit, torch::kFloat64);
  // Standard errors with n = 4000: 0.016 std for the mean, ~0.011 std for the std; rates: sqrt(p(1-p)/n)
  // = 0.0047 (p = 0.1) and 0.0068 (p = 0.25); 4.6 standard errors each.
  EXPECT_NEAR(lg.mean().item<double>(), 0.5, 0.08 * 2.0);
  EXPECT_NEAR(lg.std().item<double>(), 2.0, 0.05 * 2.0);
  EXPECT_NEAR(drops / n, 0.1, 0.022);
  EXPECT_NEAR(shortcuts / n, 0.25, 0.032);
  EXPECT_EQ(ds.size(), 8u);
  for (float d : ds) EXPECT_EQ(d, 1.0f / static_cast<float>(1 << static_cast<int>(std::lround(-std::log2(d)))));
  const auto a = draw_sample(5, 2, 7, {{3, 2}}, c), b = draw_sample(5, 2, 7, {{3, 2}}, c);
  EXPECT_TRUE(torch::equal(a.t, b.t) && torch::equal(a.eps[0], b.eps[0]));
  for (const auto& o : {draw_sample(6, 2, 7, {{3, 2}}, c), draw_sample(5, 3, 7, {{3, 2}}, c), draw_sample(5, 2, 8, {{3, 2}}, c)})
    EXPECT_FALSE(torch::equal(a.eps[0], o.eps[0]));
}

// Two ranks (threads, Gloo) == one rank with the same global batch: the first step's averaged
// gradients and every step's loss. (Not the weights themselves: the loss does not depend on a key
// bias, which adds the same q.b to every logit of a query, so those biases get gradients of pure
// rounding noise, which AdamW scales up to lr-sized steps whose sign depends on the summation order.)
// The two ranks agree exactly.
TEST(Stage1Train, TwoRanksMatchOneRank) {
  auto samples = tiny_samples(8, 12);
  const int steps = 3;
  const std::string extra = "objective: {p_unconditional: 0.3, shortcut_fraction: 0.3}\n";
  struct Run {
    std::vector<torch::Tensor> grads, weights;  // gradients after step 1, weights at the end
    std::vector<double> losses;
  };
  auto train = [&](Trainer& tr) {
    Run r;
    for (int s = 0; s < steps; ++s) {
      r.losses.push_back(tr.step().loss);
      if (s == 0)
        for (const auto& [name, p] : tr.objective().parameters()) r.grads.push_back(p.grad().clone());
    }
    r.weights = weights_of(tr);
    return r;
  };
  Run solo;
  {
    auto cfg = tiny_stage1_config(simu::testing::temp_dir("s1_solo"), steps, 4, 1, extra);
    auto comm = make_solo_communicator();
    Trainer tr(cfg, tiny_objective(cfg, samples), *comm, torch::kCPU);
    solo = train(tr);
  }
  // The ranks' models are made here, one after the other: their initialisation seeds the global
  // generator, which two threads must not share.
  std::vector<Stage1Config> cfgs;
  std::vector<std::unique_ptr<FlowObjective>> objectives;
  for (int rank = 0; rank < 2; ++rank) {
    cfgs.push_back(tiny_stage1_config(simu::testing::temp_dir("s1_duo" + std::to_string(rank)), steps, 4, 1, extra));
    objectives.push_back(tiny_objective(cfgs.back(), samples));
  }
  const auto names = objectives[0]->parameters();
  const int port = free_port();
  auto rank_fn = [&](int rank) {
    DistEnv env;
    env.rank = rank;
    env.world_size = 2;
    env.master_port = port;
    auto comm = make_cpu_communicator(connect_store(env, std::chrono::seconds(20)), rank, 2, std::chrono::seconds(60));
    Trainer tr(cfgs[rank], std::move(objectives[rank]), *comm, torch::kCPU);
    return train(tr);
  };
  auto f0 = std::async(std::launch::async, rank_fn, 0);
  auto f1 = std::async(std::launch::async, rank_fn, 1);
  const auto r0 = f0.get(), r1 = f1.get();
  ASSERT_EQ(r0.grads.size(), solo.grads.size());
  for (size_t i = 0; i < solo.grads.size(); ++i) {
    EXPECT_TRUE(torch::equal(r0.weights[i], r1.weights[i])) << "ranks disagree on " << names[i].first;
    // The same sums in another order (per-rank means averaged vs one accumulation over 4 micro-batches):
    // fp32 rounding, a few units of 2^-24 per addition, relative to each tensor's largest value.
    EXPECT_TRUE(simu::testing::close(r0.grads[i], solo.grads[i], 1e-5, names[i].first));
  }
  for (int s = 0; s < steps; ++s) {
    EXPECT_EQ(r0.losses[s], r1.losses[s]) << "step " << s;
    // The weights differ by rounding (and the key biases by noise the loss ignores): ~1e-6 of the loss.
    EXPECT_NEAR(r0.losses[s], solo.losses[s], 1e-5 * solo.losses[s]) << "step " << s;
  }
}

// Stopping after 2 steps and resuming from the checkpoint (into a model initialised differently)
// gives bit-identical parameters, EMA weights, optimizer state and metrics; the data crosses an epoch.
TEST(Stage1Train, ResumeIsBitExact) {
  auto samples = tiny_samples(10, 13);  // 2 global batches of 4 per epoch
  const std::string extra = "objective: {p_unconditional: 0.3, shortcut_fraction: 0.3}\nema: {decay: 0.9}\n";
  const auto out_a = simu::testing::temp_dir("s1_resume_a"), out_b = simu::testing::temp_dir("s1_resume_b");
  auto solo = make_solo_communicator();
  std::vector<StepMetrics> ma, mb;
  auto cfg_a = tiny_stage1_config(out_a, 6, 4, 2, extra);
  Trainer a(cfg_a, tiny_objective(cfg_a, samples), *solo, torch::kCPU);
  for (int s = 0; s < 6; ++s) ma.push_back(a.step());
  auto cfg_b = tiny_stage1_config(out_b, 6, 4, 2, extra);
  {
    Trainer b0(cfg_b, tiny_objective(cfg_b, samples), *solo, torch::kCPU);
    for (int s = 0; s < 2; ++s) mb.push_back(b0.step());
    b0.save();
    b0.step();  // work lost by the "crash"
  }
  // Another initialisation (model seed 99): everything must come from the checkpoint.
  Trainer b(cfg_b, tiny_objective(cfg_b, samples, nullptr, /*model_seed=*/99), *solo, torch::kCPU);
  b.resume(resolve_resume(out_b + "/checkpoints", "latest"));
  EXPECT_EQ(b.steps_done(), 2);
  for (int s = 2; s < 6; ++s) mb.push_back(b.step());
  const auto wa = weights_of(a), wb = weights_of(b);
  for (size_t i = 0; i < wa.size(); ++i) EXPECT_TRUE(torch::equal(wa[i], wb[i])) << "weights differ at " << i;
  const auto ea = a.objective().extra_state(), eb = b.objective().extra_state();
  ASSERT_EQ(ea.size(), wa.size());
  for (const auto& [k, v] : ea) EXPECT_TRUE(torch::equal(v, eb.at(k))) << k;
  const auto oa = a.optimizer().state_dict(), ob = b.optimizer().state_dict();
  for (const auto& [k, v] : oa) EXPECT_TRUE(torch::equal(v, ob.at(k))) << k;
  for (int s = 0; s < 6; ++s) {
    EXPECT_EQ(ma[s].loss, mb[s].loss) << "step " << s;
    EXPECT_EQ(ma[s].grad_norm, mb[s].grad_norm) << "step " << s;
    EXPECT_EQ(ma[s].per_kind, mb[s].per_kind) << "step " << s;
  }
}

// Every sample with the same targets x1 = 2 (all latents): x_t = (1 - t) x0 + 2 t, target 2 - x0. A
// predictor that ignores x_t can at best output the target's mean 2, with loss Var(x0) = 1 per latent
// (5 over the 5 latents); predicting 0 costs 1 + 2^2 = 5 per latent (25). Training must start above
// half that gap (15) and, within 30 steps, go below 5: it learned the mean and uses x_t (the exact
// velocity (2 - x_t) / (1 - t) has loss 0).
TEST(Stage1Train, LearnsAConstantTarget) {
  const auto out = simu::testing::temp_dir("s1_const");
  auto cfg = tiny_stage1_config(out, 30, 8, 8, "objective: {p_unconditional: 0.0}\n");
  cfg.optim.lr = 0.02;
  auto samples = tiny_samples(8, 14);
  for (auto& [name, v] : samples->pose) v.fill_(2.0);
  const simu::training::ShapeTargetFn constant = [](const torch::Tensor& occ) {
    return torch::full({occ.size(0), 8, 4}, 2.0, torch::kFloat32);  // the tiny model's shape latent [2^3, 4]
  };
  auto solo = make_solo_communicator();
  Trainer tr(cfg, tiny_objective(cfg, samples, constant), *solo, torch::kCPU);
  std::vector<double> losses;
  for (int s = 0; s < 30; ++s) losses.push_back(tr.step().loss);
  EXPECT_GT(losses.front(), 15.0);
  double last = 0;
  for (int s = 25; s < 30; ++s) last += losses[s] / 5;
  EXPECT_LT(last, 5.0) << "first " << losses.front() << ", last 5 mean " << last;
}

// run(): the export in the released layout, which the programs' loaders read (generator and embedder
// from one file), holding the EMA weights; metrics and checkpoints (model.safetensors, extra.safetensors).
TEST(Stage1Train, RunExportsTheReleasedLayout) {
  const auto out = simu::testing::temp_dir("s1_run");
  auto cfg = tiny_stage1_config(out, 3, 4, 4);
  auto samples = tiny_samples(8, 15);
  auto solo = make_solo_communicator();
  Trainer tr(cfg, tiny_objective(cfg, samples), *solo, torch::kCPU);
  tr.run();
  const auto file = out + "/model/ss_generator.safetensors";
  ASSERT_TRUE(std::filesystem::exists(file));
  EXPECT_TRUE(std::filesystem::exists(out + "/model/generator.yaml"));
  EXPECT_TRUE(std::filesystem::exists(out + "/model/embedder.json"));
  auto gen = simu::models::load_generator(cfg.model.generator, file, torch::kCPU);
  auto emb = simu::models::load_cond_embedder(cfg.model.embedder, file, "auto", torch::kCPU);
  const auto& ema = static_cast<FlowObjective&>(tr.objective()).ema();
  std::map<std::string, torch::Tensor> loaded;
  for (const auto& kv : gen->named_parameters()) loaded[std::string(kGeneratorPrefix) + kv.key()] = kv.value();
  for (const auto& kv : emb->named_parameters()) loaded[std::string(simu::models::kOfficialCondEmbedderPrefix) + kv.key()] = kv.value();
  ASSERT_EQ(loaded.size(), ema.size());
  for (const auto& [name, e] : ema) EXPECT_TRUE(torch::equal(loaded.at(name), e)) << name;
  const auto cks = list_checkpoints(out + "/checkpoints");
  ASSERT_EQ(cks.size(), 2u);  // step 2 and the end
  EXPECT_TRUE(std::filesystem::exists(cks.back() + "/model.safetensors"));
  EXPECT_TRUE(std::filesystem::exists(cks.back() + "/extra.safetensors"));
  EXPECT_EQ(load_checkpoint(cks.back()).params_file, "model.safetensors");
}

// The official initialisation: adaLN modulation zero (every block starts as the identity), the
// timestep embedder N(0, 0.02), the d embedder's last weight zero, other Linears xavier-uniform
// (inside +-sqrt(6 / (fan_in + fan_out))) with zero bias.
TEST(Stage1Model, OfficialInitialisation) {
  const auto out = simu::testing::temp_dir("s1_init");
  simu::testing::write_tiny_stage1_models(out);
  auto model = make_stage1_model(out + "/generator.yaml", out + "/embedder.json", "", torch::kCPU, 3);
  auto bb = model->backbone();
  for (const auto& b : *bb->blocks) {
    auto* blk = b->as<simu::models::MOTBlockImpl>();
    EXPECT_EQ(blk->ada_linear->weight.abs().max().item<float>(), 0.0f);
    EXPECT_EQ(blk->ada_linear->bias.abs().max().item<float>(), 0.0f);
    const auto& w = blk->mlp[0]->fc1->weight;  // [64, 32]
    EXPECT_LE(w.abs().max().item<double>(), std::sqrt(6.0 / (64 + 32)));
    EXPECT_EQ(blk->mlp[0]->fc1->bias.abs().max().item<float>(), 0.0f);
  }
  // 32 x 256 values of N(0, 0.02): the sample std within 5% (standard error 0.6%).
  EXPECT_NEAR((*bb->t_embedder->mlp)[0]->as<simu::models::LinearImpl>()->weight.std().item<double>(), 0.02, 0.001);
  EXPECT_EQ((*bb->d_embedder->mlp)[2]->as<simu::models::LinearImpl>()->weight.abs().max().item<float>(), 0.0f);
  for (const auto& p : model->parameters()) EXPECT_TRUE(p.requires_grad());
  EXPECT_FALSE(bb->fused_kernels());
  const auto counts = count_parameters(model);
  EXPECT_GT(counts.flow, 0);
  EXPECT_GT(counts.embedder, 0);
}

// Typos, impossible values and options that do not apply are errors naming the file and the key.
TEST(Stage1Config, BadConfigsAreClearErrors) {
  const auto out = simu::testing::temp_dir("s1_badcfg");
  const auto good = tiny_stage1_config(out, 1, 4, 4);
  auto expect_error = [&](const std::string& set, const std::string& needle) {
    try {
      Stage1Config::load(good.file, {set});
      ADD_FAILURE() << "no error for --set " << set;
    } catch (const simu::Error& e) {
      EXPECT_EQ(std::string(e.what()).rfind(good.file, 0), 0u) << e.what();
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  expect_error("objective.p_uncond=0.1", "unknown key 'objective.p_uncond'");
  expect_error("objective.p_unconditional=1.0", "objective.p_unconditional");
  expect_error("objective.t_std=0", "objective.t_std");
  expect_error("ema.decay=1.0", "ema.decay");
  expect_error("export.dtype=int8", "export.dtype");
  expect_error("dataset.split=training", "dataset.split");
  expect_error("targets.kind=encoder", "targets.encoder_config");
  expect_error("model.generatr=x", "unknown key 'model.generatr'");
  expect_error("data.prefetch=4", "key 'data.prefetch'");
  try {
    Stage1Config::load(good.file, {"train.fp8_base=true", "train.device=cuda", "train.precision=bf16"});
    ADD_FAILURE() << "no error for train.fp8_base";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("train.fp8_base"), std::string::npos) << e.what();
  }
  // Not in the config file alone: the objective checks the config against the model.
  auto cfg = Stage1Config::load(good.file, {"objective.latent_weights={shap: 2.0}"});
  try {
    tiny_objective(cfg, tiny_samples(4, 1));
    ADD_FAILURE() << "no error for an unknown latent";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("objective.latent_weights.shap"), std::string::npos) << e.what();
  }
}
