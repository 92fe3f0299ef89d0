// Sparse-structure VAE training on synthetic occupancies (balls and boxes made here): the loss terms
// against independent math, the batch stream (ranks, workers, errors), a few CPU steps that learn,
// exact resume, 2 ranks == 1 rank, the non-finite stop, export -> loaders, the IoU table, the config.
#include <filesystem>
#include <future>
#include <mutex>

#include "common/error.h"
#include "common/fs.h"
#include "common/random.h"
#include "test_util.h"
#include "training/ss_vae_trainer.h"

using namespace simu::training;

namespace {

constexpr int64_t R = 16;

// A ball or a box of seeded size and centre in a side^3 grid (x-major flat index), in units of the
// 16^3 grid (a 32^3 grid holds the same shape at twice the detail).
std::vector<uint8_t> synthetic_occupancy_at(const ShapeKey& key, int64_t side) {
  uint64_t h = simu::splitmix64(key.seed);
  auto uniform = [&](double lo, double hi) {
    h = simu::splitmix64(h);
    return lo + (hi - lo) * static_cast<double>(h >> 11) / 9007199254740992.0;
  };
  const double cx = uniform(6, 10), cy = uniform(6, 10), cz = uniform(6, 10);
  const double a = uniform(2, 5), b = uniform(2, 5), c = uniform(2, 5);
  SIMU_CHECK(key.family == "ball" || key.family == "box", "no synthetic family '{}'", key.family);
  const double u = static_cast<double>(R) / static_cast<double>(side);  // 16^3 units per voxel
  std::vector<uint8_t> g(side * side * side, 0);
  for (int64_t x = 0; x < side; ++x)
    for (int64_t y = 0; y < side; ++y)
      for (int64_t z = 0; z < side; ++z) {
        const double dx = ((x + 0.5) * u - cx) / a, dy = ((y + 0.5) * u - cy) / b, dz = ((z + 0.5) * u - cz) / c;
        const bool in = key.family == "ball" ? dx * dx + dy * dy + dz * dz <= 1
                                             : std::abs(dx) <= 1 && std::abs(dy) <= 1 && std::abs(dz) <= 1;
        g[(x * side + y) * side + z] = in ? 1 : 0;
      }
  return g;
}

std::vector<uint8_t> synthetic_occupancy(const ShapeKey& key) { return synthetic_occupancy_at(key, R); }

std::shared_ptr<ShapeSet> synthetic_set() {
  auto s = std::make_shared<ShapeSet>();
  s->resolution = R;
  s->occupancy = synthetic_occupancy;
  s->train = [](int64_t i) { return ShapeKey{i % 2 ? "box" : "ball", static_cast<uint64_t>(1000 + i)}; };
  for (uint64_t k = 0; k < 4; ++k) {
    s->val.push_back({k % 2 ? "box" : "ball", 10 + k});
    s->test.push_back({k % 2 ? "box" : "ball", 20 + k});
  }
  s->held_out_family = "box";
  return s;
}

// A tiny VAE: 16^3 -> 4 x 8^3, one level of down/up-sampling (CPU 3-D convolutions are slow: keep it small).
SsVaeConfig tiny_config(const std::string& out, int64_t steps, int64_t global_batch = 4, double ema = 0.9,
                        std::vector<std::string> overrides = {}) {
  const std::string yaml = R"(
model:
  encoder: {in_channels: 1, latent_channels: 4, num_res_blocks: 1, channels: [4, 8], num_res_blocks_middle: 1}
  decoder: {out_channels: 1, latent_channels: 4, num_res_blocks: 1, channels: [8, 4], num_res_blocks_middle: 1}
loss: {bce: 1.0, dice: 1.0, l1: 0.5, lambda_kl: 0.01}
optim: {lr: 0.003, warmup_steps: 2, weight_decay: 0.0, clip_grad_norm: 1.0}
data: {resolution: 16, workers: 2, prefetch: 2}
train: {device: cpu, precision: fp32, seed: 3}
eval: {every: 0, batch: 3}
run: {checkpoint_every: 0, keep_last: 0, progress: false}
)";
  const std::string dir = simu::testing::temp_dir("ss_vae_cfg");
  simu::fs::atomic_write(dir + "/tiny.yaml", yaml);
  for (const auto& o : {"run.out_dir=" + out, "train.steps=" + std::to_string(steps),
                        "data.global_batch=" + std::to_string(global_batch), "train.ema_rate=" + std::to_string(ema)})
    overrides.push_back(o);
  return SsVaeConfig::load(dir + "/tiny.yaml", overrides);
}

// Every weight, EMA tensor and optimizer state of a trainer, by name.
std::map<std::string, torch::Tensor> everything(const SsVaeTrainer& t) {
  auto d = t.checkpoint_data();
  auto all = d.optimizer;
  for (auto& [k, v] : d.adapter) all["w." + k] = v;
  return all;
}

}  // namespace

// The per-sample terms against sums written out voxel by voxel in float64.
TEST(SsVae, TermsMatchIndependentMath) {
  torch::manual_seed(1);
  const auto logits = torch::randn({2, 1, 4, 4, 4}) * 3;
  const auto occ = (torch::rand({2, 1, 4, 4, 4}) < 0.4).to(torch::kFloat32);
  const auto mean = torch::randn({2, 3, 2, 2, 2}), logvar = torch::randn({2, 3, 2, 2, 2}) * 0.5;
  SsVaeLossConfig w;
  w.bce = 0.7, w.dice = 1.3, w.l1 = 0.2, w.lambda_kl = 0.05;
  const auto t = ss_vae_terms(logits, occ, mean, logvar, w);
  for (int64_t b = 0; b < 2; ++b) {
    double bce = 0, inter = 0, ps = 0, ys = 0, l1 = 0, kl = 0, i_and = 0, i_or = 0;
    const auto L = logits[b].flatten(), Y = occ[b].flatten();
    for (int64_t v = 0; v < 64; ++v) {
      const double x = L[v].item<double>(), y = Y[v].item<double>(), p = 1 / (1 + std::exp(-x));
      bce += -(y * std::log(p) + (1 - y) * std::log(1 - p));
      inter += p * y, ps += p, ys += y, l1 += std::abs(p - y);
      i_and += (x > 0 && y > 0.5), i_or += (x > 0 || y > 0.5);
    }
    const auto M = mean[b].flatten(), V = logvar[b].flatten();
    for (int64_t v = 0; v < 24; ++v) {
      const double m = M[v].item<double>(), lv = V[v].item<double>();
      kl += 0.5 * (m * m + std::exp(lv) - lv - 1);
    }
    bce /= 64, l1 /= 64, kl /= 24;
    const double dice = 1 - (2 * inter + 1) / (ps + ys + 1);
    // float32 sums of 64 terms of magnitude <= 4 (BCE of |logit| <= 12): 64 x 2^-24 x 4 relative ~ 1.5e-5.
    const double tol = 2e-5;
    EXPECT_NEAR(t.bce[b].item<double>(), bce, tol * std::max(1.0, bce));
    EXPECT_NEAR(t.dice[b].item<double>(), dice, tol);
    EXPECT_NEAR(t.l1[b].item<double>(), l1, tol);
    EXPECT_NEAR(t.kl[b].item<double>(), kl, tol * std::max(1.0, kl));
    EXPECT_NEAR(t.total[b].item<double>(), 0.7 * bce + 1.3 * dice + 0.2 * l1 + 0.05 * kl, 4 * tol * std::max(1.0, bce + kl));
    EXPECT_DOUBLE_EQ(t.iou[b].item<double>(), static_cast<double>(static_cast<float>(i_and) / static_cast<float>(i_or)));
  }
  // Both grids empty: IoU 1.
  EXPECT_EQ(occupancy_iou(-torch::ones({1, 1, 2, 2, 2}), torch::zeros({1, 1, 2, 2, 2})).item<float>(), 1.0f);
}

// A step's samples are its global-batch slice of the indexed stream: ranks split it, and neither the
// number of worker threads nor reading ahead changes a batch. The noise is sample_noise of the index.
TEST(SsVae, BatchStreamIsIndexedAndShardedByRank) {
  auto set = synthetic_set();
  LoaderOptions o;
  o.global_batch = 4;
  o.latent_shape = {4, 8, 8, 8};
  o.noise_seed = 9;
  const auto solo = BatchLoader::make(*set, o, 3);
  EXPECT_EQ(solo.index, (std::vector<int64_t>{12, 13, 14, 15}));
  for (int64_t j = 0; j < 4; ++j) {
    const auto g = synthetic_occupancy(set->train(12 + j));
    EXPECT_TRUE(torch::equal(solo.occupancy[j].flatten(), torch::from_blob((void*)g.data(), {R * R * R}, torch::kUInt8)));
    EXPECT_TRUE(torch::equal(solo.noise[j], sample_noise(9, 12 + j, {4, 8, 8, 8})));
  }
  // Two ranks: rank r holds rows [2r, 2r + 2) of the solo batch.
  for (int rank = 0; rank < 2; ++rank) {
    auto ro = o;
    ro.rank = rank, ro.world = 2;
    const auto part = BatchLoader::make(*set, ro, 3);
    EXPECT_TRUE(torch::equal(part.occupancy, solo.occupancy.narrow(0, 2 * rank, 2)));
    EXPECT_TRUE(torch::equal(part.noise, solo.noise.narrow(0, 2 * rank, 2)));
  }
  // The background loader with 3 workers from step 2: the same batches as made one by one.
  auto lo = o;
  lo.workers = 3, lo.prefetch = 2, lo.start_step = 2;
  BatchLoader loader(set, lo);
  for (int64_t step = 2; step < 5; ++step) {
    const auto b = loader.next();
    EXPECT_EQ(b.step, step);
    EXPECT_TRUE(torch::equal(b.occupancy, BatchLoader::make(*set, o, step).occupancy));
  }
  EXPECT_FALSE(torch::equal(sample_noise(9, 1, {8}), sample_noise(9, 2, {8})));
  EXPECT_FALSE(torch::equal(sample_noise(9, 1, {8}), sample_noise(10, 1, {8})));
}

// A shape that cannot be made fails the batch holding it, not the earlier ones, with its message.
TEST(SsVae, LoaderRethrowsAtTheFailingBatch) {
  auto set = std::make_shared<ShapeSet>(*synthetic_set());
  set->train = [](int64_t i) { return ShapeKey{i == 9 ? "teapot" : "ball", static_cast<uint64_t>(i)}; };
  LoaderOptions o;
  o.global_batch = 4;
  o.latent_shape = {1};
  o.prefetch = 3;
  BatchLoader loader(set, o);
  EXPECT_EQ(loader.next().step, 0);
  EXPECT_EQ(loader.next().step, 1);
  EXPECT_NE(simu::testing::error_of([&] { loader.next(); }).find("teapot"), std::string::npos);
}

// CPU steps on two fixed shapes (a ball and a box) fit them: past the start's plateau (zero-initialised
// residual branches) the loss falls below half and the training batch's IoU passes 0.6 (a PyTorch
// replica of this run reaches ~0.85 at step 50).
TEST(SsVae, StepsFitTwoShapesOnTheCpu) {
  auto comm = make_solo_communicator();
  auto set = std::make_shared<ShapeSet>(*synthetic_set());
  set->train = [](int64_t i) { return ShapeKey{i % 2 ? "box" : "ball", static_cast<uint64_t>(i % 2)}; };
  const int steps = 50;
  auto cfg = tiny_config(simu::testing::temp_dir("ss_vae_fit"), steps, 2, 0.0,
                         {"model.encoder.channels=[8, 16]", "model.decoder.channels=[16, 8]", "loss.lambda_kl=0.001",
                          "optim.lr=0.01"});
  SsVaeTrainer tr(cfg, set, *comm, torch::kCPU);
  std::vector<SsVaeStepMetrics> m;
  for (int s = 0; s < steps; ++s) m.push_back(tr.step());
  auto mean = [&](int a, int b, double SsVaeStepMetrics::*f) {
    double s = 0;
    for (int i = a; i < b; ++i) s += m[i].*f;
    return s / (b - a);
  };
  std::printf("loss %.4f -> %.4f, train IoU %.3f -> %.3f\n", mean(0, 5, &SsVaeStepMetrics::loss),
              mean(steps - 5, steps, &SsVaeStepMetrics::loss), mean(0, 5, &SsVaeStepMetrics::iou),
              mean(steps - 5, steps, &SsVaeStepMetrics::iou));
  EXPECT_LT(mean(steps - 5, steps, &SsVaeStepMetrics::loss), 0.5 * mean(0, 5, &SsVaeStepMetrics::loss));
  EXPECT_GT(mean(steps - 5, steps, &SsVaeStepMetrics::iou), 0.6);
  for (const auto& [k, v] : m.back().scalars()) EXPECT_TRUE(std::isfinite(v)) << k;
  EXPECT_EQ(m.back().step, steps);
}

// Stopped after 2 steps, checkpointed and resumed in a new trainer: weights, EMA and optimizer state
// after 5 steps are bit-identical to an uninterrupted run's.
TEST(SsVae, ResumeIsBitExact) {
  auto comm = make_solo_communicator();
  const auto set = synthetic_set();
  std::map<std::string, torch::Tensor> straight;
  {
    SsVaeTrainer a(tiny_config(simu::testing::temp_dir("ss_vae_a"), 5), set, *comm, torch::kCPU);
    for (int s = 0; s < 5; ++s) a.step();
    straight = everything(a);
  }
  const auto out = simu::testing::temp_dir("ss_vae_b");
  {
    SsVaeTrainer b(tiny_config(out, 5), set, *comm, torch::kCPU);
    b.step();
    b.step();
    b.save();
  }
  SsVaeTrainer c(tiny_config(out, 5), set, *comm, torch::kCPU);
  c.resume(latest_checkpoint(out + "/checkpoints").value());
  EXPECT_EQ(c.steps_done(), 2);
  for (int s = 0; s < 3; ++s) c.step();
  const auto resumed = everything(c);
  ASSERT_EQ(resumed.size(), straight.size());
  int ema = 0;
  for (const auto& [k, v] : straight) {
    ASSERT_TRUE(resumed.count(k)) << k;
    EXPECT_TRUE(torch::equal(resumed.at(k), v)) << k;
    ema += k.rfind("ema.", 0) == 0;
  }
  EXPECT_GT(ema, 0);
  // A config without the EMA cannot resume that checkpoint: the error says why.
  SsVaeTrainer d(tiny_config(out, 5, 4, 0.0), set, *comm, torch::kCPU);
  EXPECT_NE(simu::testing::error_of([&] { d.resume(latest_checkpoint(out + "/checkpoints").value()); }).find("EMA"),
            std::string::npos);
}

// Two ranks (threads, loopback TCPStore, Gloo) == one rank with the same global batch.
TEST(SsVae, TwoRanksMatchOneRank) {
  const auto set = synthetic_set();
  const int steps = 3;
  // AdamW in its linear regime (eps 1 >> sqrt(v)): an update is ~lr * m, so a rounding difference in a
  // gradient stays a difference of that size instead of Adam's normalisation amplifying it where a
  // gradient is near zero (a rank split changes the summation order, nothing else).
  auto config = [&](const std::string& name) {
    auto c = tiny_config(simu::testing::temp_dir(name), steps);
    c.optim.eps = 1.0;
    c.optim.lr = 0.1;
    return c;
  };
  std::map<std::string, torch::Tensor> solo;
  {
    auto comm = make_solo_communicator();
    SsVaeTrainer t(config("ss_vae_solo"), set, *comm, torch::kCPU);
    for (int s = 0; s < steps; ++s) t.step();
    solo = everything(t);
  }
  const int port = free_port();
  std::mutex build;  // the trainers seed and draw from the global generator while they build their networks
  auto rank_fn = [&](int rank) {
    DistEnv env;
    env.rank = rank, env.world_size = 2, env.master_port = port;
    auto comm = make_cpu_communicator(connect_store(env, std::chrono::seconds(20)), rank, 2, std::chrono::seconds(30));
    std::unique_ptr<SsVaeTrainer> t;
    {
      std::lock_guard<std::mutex> lock(build);
      t = std::make_unique<SsVaeTrainer>(config("ss_vae_duo"), set, *comm, torch::kCPU);
    }
    for (int s = 0; s < steps; ++s) t->step();
    return everything(*t);
  };
  auto f0 = std::async(std::launch::async, rank_fn, 0), f1 = std::async(std::launch::async, rank_fn, 1);
  const auto r0 = f0.get(), r1 = f1.get();
  double worst = 0;
  for (const auto& [k, v] : solo) {
    if (k.find(".step") != std::string::npos) {
      EXPECT_TRUE(torch::equal(r0.at(k), v)) << k;
      continue;
    }
    EXPECT_TRUE(torch::equal(r0.at(k), r1.at(k))) << "ranks disagree on " << k;
    worst = std::max(worst, (r0.at(k).to(torch::kFloat64) - v.to(torch::kFloat64)).abs().max().item<double>());
  }
  // The split sums the convolutions' and the mean's terms in another order: the float32 gradients differ
  // by ~2^-24 x a few hundred terms relative (< 1e-5 of |g| <= 1), times lr 0.1 over 3 steps < 3e-6;
  // the updated values (<= 1.01) round to float32 once more (one ulp, 1.2e-7). Bound 5e-6.
  EXPECT_LT(worst, 5e-6);
  std::printf("2 ranks vs 1: max |difference| %.3g\n", worst);
}

// A non-finite loss stops the CPU step before its update: the weights stay those of the last good step.
TEST(SsVae, NonFiniteLossStopsBeforeTheUpdate) {
  auto comm = make_solo_communicator();
  auto cfg = tiny_config(simu::testing::temp_dir("ss_vae_nan"), 4);
  cfg.optim.lr = 1e30;
  cfg.optim.warmup_steps = 0;
  cfg.optim.clip_grad_norm = 0;
  SsVaeTrainer t(cfg, synthetic_set(), *comm, torch::kCPU);
  std::string msg;
  std::map<std::string, torch::Tensor> before;
  for (int s = 0; s < 4 && msg.empty(); ++s) {
    before = everything(t);
    msg = simu::testing::error_of([&] { t.step(); });
  }
  ASSERT_NE(msg.find("non-finite"), std::string::npos) << msg;
  for (const auto& [k, v] : everything(t)) EXPECT_TRUE(torch::equal(v, before.at(k))) << k;
}

// The exported weights load with the official-layout loaders and reproduce the trainer's EMA networks;
// the end-of-run files are there.
TEST(SsVae, RunExportsLoadableWeightsAndTheTestTable) {
  auto comm = make_solo_communicator();
  const auto out = simu::testing::temp_dir("ss_vae_run");
  auto cfg = tiny_config(out, 3);
  cfg.eval.every = 2;
  SsVaeTrainer t(cfg, synthetic_set(), *comm, torch::kCPU);
  t.run();
  for (const char* f : {"/weights/ss_encoder.json", "/weights/ss_decoder.safetensors", "/eval.json", "/metrics.jsonl"})
    EXPECT_TRUE(std::filesystem::exists(out + f)) << f;
  auto enc = simu::models::load_ss_encoder(out + "/weights/ss_encoder.json", out + "/weights/ss_encoder.safetensors");
  auto dec = simu::models::load_ss_decoder(out + "/weights/ss_decoder.json", out + "/weights/ss_decoder.safetensors");
  // Exported = the EMA tensors (float32 export: the same bits).
  std::map<std::string, torch::Tensor> ema;
  for (const auto& [k, v] : t.ema()) ema[k] = v;
  for (const auto& p : enc->named_parameters()) EXPECT_TRUE(torch::equal(p.value(), ema.at("ema.encoder." + p.key()))) << p.key();
  for (const auto& p : dec->named_parameters()) EXPECT_TRUE(torch::equal(p.value(), ema.at("ema.decoder." + p.key()))) << p.key();
  // eval.json: the test table of the 4 test shapes (2 per family; "box" reported as held out).
  const auto j = nlohmann::json::parse(simu::fs::read_file(out + "/eval.json"));
  EXPECT_EQ(j.at("iou").at("seen").at("n").get<int>(), 2);
  EXPECT_EQ(j.at("iou").at("held_out").at("n").get<int>(), 2);
  EXPECT_EQ(j.at("step").get<int>(), 3);
  EXPECT_NE(simu::fs::read_file(out + "/metrics.jsonl").find("val/iou_seen"), std::string::npos);
  // A second fresh run into the same folder is refused without --overwrite.
  EXPECT_NE(simu::testing::error_of([&] { prepare_run_dir(cfg.file, out, ss_vae_run_outputs(), false, false, true); })
                .find("already holds"),
            std::string::npos);
}

// The table: per-family mean / median / min in first-seen order, the seen and held-out means.
TEST(SsVae, IouTableByFamily) {
  const std::vector<ShapeKey> keys = {{"a", 1}, {"b", 2}, {"a", 3}, {"c", 4}, {"a", 5}};
  const auto t = iou_table(keys, {0.5, 0.9, 0.7, 0.2, 0.6}, "c");
  ASSERT_EQ(t.rows.size(), 3u);
  EXPECT_EQ(t.rows[0].family, "a");
  EXPECT_EQ(t.rows[0].n, 3);
  EXPECT_DOUBLE_EQ(t.rows[0].mean, (0.5 + 0.7 + 0.6) / 3);
  EXPECT_DOUBLE_EQ(t.rows[0].median, 0.6);
  EXPECT_DOUBLE_EQ(t.rows[0].min, 0.5);
  EXPECT_TRUE(t.rows[2].held_out);
  EXPECT_EQ(t.n_seen, 4);
  EXPECT_DOUBLE_EQ(t.mean_seen, (0.5 + 0.9 + 0.7 + 0.6) / 4);
  EXPECT_DOUBLE_EQ(t.mean_held_out, 0.2);
  EXPECT_NE(t.markdown().find("| c (held out) | 1 | 0.200 |"), std::string::npos) << t.markdown();
}

// The miniature config reads, its sections fit (32^3 -> 8 x 8^3), and mismatched sections are errors
// naming the file and the keys.
TEST(SsVae, MiniatureConfig) {
  const auto path = simu::testing::source_dir() + "/configs/miniature/ss_vae.yaml";
  const auto cfg = SsVaeConfig::load(path);
  EXPECT_EQ(cfg.data.resolution, 32);
  EXPECT_EQ(cfg.latent_resolution(), 8);
  EXPECT_EQ(cfg.model.encoder.latent_channels, 8);
  EXPECT_EQ(cfg.model.decoder.upsample_factor(), 4);
  for (const auto& [set, key] : std::vector<std::pair<std::string, std::string>>{
           {"model.decoder.latent_channels=4", "latent_channels"},
           {"model.decoder.channels=[64, 32]", "up-sampling"},
           {"data.encoder_resolution=20", "encoder_resolution"},
           {"data.resolution=30", "resolution"},
           {"loss.dice=0", "loss"},
           {"train.ema_rate=1", "ema_rate"},
           {"data.workerz=2", "workerz"}}) {
    const auto msg = simu::testing::error_of([&] { SsVaeConfig::load(path, {set}); });
    EXPECT_NE(msg.find(key), std::string::npos) << set << ": " << msg;
    EXPECT_NE(msg.find("ss_vae.yaml"), std::string::npos) << set << ": " << msg;
  }
}

// A decoder trained on a frozen encoder's latent of a coarser grid (model.frozen_encoder,
// data.encoder_resolution): the encoder reads 8^3, the decoder learns the same shapes at 16^3; the
// encoder's weights never change, only the decoder is checkpointed and trained, the export carries the
// frozen encoder unchanged, and an encoder that differs from model.encoder is refused by name.
TEST(SsVae, FrozenEncoderDecoderLearnsAFinerGrid) {
  auto comm = make_solo_communicator();
  constexpr int64_t C = R / 2;  // the coarse side
  const auto two_shapes = [](int64_t i) { return ShapeKey{i % 2 ? "box" : "ball", static_cast<uint64_t>(i % 2)}; };
  // A small VAE at 8^3 (4 x 4^3 latent) fitted to the two shapes and exported: the frozen encoder.
  auto coarse = std::make_shared<ShapeSet>(*synthetic_set());
  coarse->resolution = C;
  coarse->occupancy = [](const ShapeKey& k) { return synthetic_occupancy_at(k, C); };
  coarse->train = two_shapes;
  const auto first = simu::testing::temp_dir("ss_vae_frozen_first");
  const std::vector<std::string> vae = {"data.resolution=8", "model.encoder.channels=[8, 16]",
                                        "model.decoder.channels=[16, 8]", "loss.lambda_kl=0.001", "optim.lr=0.01"};
  {
    SsVaeTrainer t(tiny_config(first, 60, 2, 0.0, vae), coarse, *comm, torch::kCPU);
    t.run();
  }
  auto enc8 = simu::models::load_ss_encoder(first + "/weights/ss_encoder.json", first + "/weights/ss_encoder.safetensors");
  // The fine set: 16^3 targets, the encoder's 8^3 grid of the same shape.
  auto set = std::make_shared<ShapeSet>(*synthetic_set());
  set->input_resolution = C;
  set->input_occupancy = [](const ShapeKey& k) { return synthetic_occupancy_at(k, C); };
  set->train = two_shapes;
  const int steps = 40;
  const auto out = simu::testing::temp_dir("ss_vae_frozen");
  const std::vector<std::string> fine = {"model.frozen_encoder=" + first + "/weights", "data.encoder_resolution=8",
                                         "model.encoder.channels=[8, 16]", "model.decoder.channels=[16, 8, 8]",
                                         "loss.lambda_kl=0.001", "optim.lr=0.01"};
  auto cfg = tiny_config(out, steps, 2, 0.0, fine);
  EXPECT_EQ(cfg.latent_resolution(), 4);
  SsVaeTrainer t(cfg, set, *comm, torch::kCPU);
  std::vector<SsVaeStepMetrics> m;
  for (int s = 0; s < steps; ++s) m.push_back(t.step());
  std::printf("frozen encoder: loss %.4f -> %.4f, 16^3 train IoU %.3f -> %.3f\n", m[0].loss, m.back().loss, m[0].iou,
              m.back().iou);
  EXPECT_LT(m.back().loss, 0.5 * m[0].loss);
  EXPECT_GT(m.back().iou, 0.6);
  // The encoder is the exported one, bit for bit, and nothing of it is trained or checkpointed.
  const auto live_enc = t.encoder()->named_parameters();
  for (const auto& p : enc8->named_parameters()) EXPECT_TRUE(torch::equal(live_enc[p.key()], p.value())) << p.key();
  for (const auto& [k, v] : t.checkpoint_data().adapter) EXPECT_EQ(k.rfind("decoder.", 0), 0u) << k;
  // The decoder maps the 4^3 latent to 16^3 logits.
  const auto latent = t.encoder()->posterior(torch::zeros({1, 1, C, C, C})).first;
  EXPECT_EQ(t.decoder()->forward(latent).sizes(), (std::vector<int64_t>{1, 1, R, R, R}));
  // The test table reads 8^3 inputs against 16^3 targets; the export carries the frozen encoder
  // unchanged (float32 export: the same bits) and the new decoder.
  const auto test = t.evaluate(set->test);
  EXPECT_EQ(test.n_seen + test.n_held_out, 4);
  t.export_weights(out + "/weights");
  auto enc = simu::models::load_ss_encoder(out + "/weights/ss_encoder.json", out + "/weights/ss_encoder.safetensors");
  for (const auto& p : enc8->named_parameters()) EXPECT_TRUE(torch::equal(enc->named_parameters()[p.key()], p.value())) << p.key();
  auto dec = simu::models::load_ss_decoder(out + "/weights/ss_decoder.json", out + "/weights/ss_decoder.safetensors");
  EXPECT_EQ(dec->config().upsample_factor(), 4);
  // An encoder config that is not the frozen one's is refused, naming the key and the folder.
  auto bad_sets = fine;
  bad_sets.push_back("model.encoder.channels=[8, 12]");
  auto bad = tiny_config(out + "_bad", 1, 2, 0.0, bad_sets);
  const auto msg = simu::testing::error_of([&] { SsVaeTrainer b(bad, set, *comm, torch::kCPU); });
  EXPECT_NE(msg.find("model.frozen_encoder"), std::string::npos) << msg;
  EXPECT_NE(msg.find("channels"), std::string::npos) << msg;
}

// run.stop_at_step ends a run early with a checkpoint and no export (as the FM-DPO trainer's), and a
// resumed run finishes it; run.stop_after_s takes the same path on time.
TEST(SsVae, RunStopsEarlyAndResumes) {
  auto comm = make_solo_communicator();
  const auto out = simu::testing::temp_dir("ss_vae_stop");
  {
    SsVaeTrainer t(tiny_config(out, 4, 4, 0.9, {"run.stop_at_step=2"}), synthetic_set(), *comm, torch::kCPU);
    t.run();
    EXPECT_EQ(t.steps_done(), 2);
  }
  EXPECT_FALSE(std::filesystem::exists(out + "/weights"));
  EXPECT_FALSE(std::filesystem::exists(out + "/eval.json"));
  SsVaeTrainer t(tiny_config(out, 4), synthetic_set(), *comm, torch::kCPU);
  t.resume(latest_checkpoint(out + "/checkpoints").value());
  EXPECT_EQ(t.steps_done(), 2);
  t.run();
  EXPECT_EQ(t.steps_done(), 4);
  EXPECT_TRUE(std::filesystem::exists(out + "/weights/ss_decoder.safetensors"));
  // A time limit reached after the first step stops there.
  const auto out2 = simu::testing::temp_dir("ss_vae_stop_s");
  SsVaeTrainer u(tiny_config(out2, 4, 4, 0.9, {"run.stop_after_s=1e-9"}), synthetic_set(), *comm, torch::kCPU);
  u.run();
  EXPECT_EQ(u.steps_done(), 1);
  EXPECT_FALSE(std::filesystem::exists(out2 + "/weights"));
}
