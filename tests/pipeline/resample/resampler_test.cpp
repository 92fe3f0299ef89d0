// Resampler on the small fixture generator + decoder: batching, seeding, decode chain, pose, meshes.
#include <ATen/CPUGeneratorImpl.h>

#include <fstream>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#endif

#include "common/error.h"
#include "data/safetensors.h"
#include "pipeline/resample/probe_resampler.h"
#include "models/cond_embedder.h"
#include "pipeline/resample/resampler.h"
#include "flow_rounding.h"
#include "test_util.h"

using namespace simu::physics;
using namespace simu::resample;

namespace {
ResamplerConfig small_config() {
  ResamplerConfig c;
  c.generator_config = simu::testing::fixture("ss_generator_small.json");
  c.generator_weights = simu::testing::fixture("ss_generator_small.safetensors");
  c.decoder_config = simu::testing::fixture("ss_decoder_small.json");
  c.decoder_weights = simu::testing::fixture("ss_decoder_small.safetensors");
  c.device = "cpu";
  c.steps = 2;  // official defaults otherwise (rescale_t 3, CFG 7 on [0, 500])
  c.num_samples = 2;
  c.decode_batch = 3;
  return c;
}
// The fixture generator's condition width (ss_generator_small.json).
int64_t cond_width() {
  return simu::models::GeneratorConfig::from_official_file(simu::testing::fixture("ss_generator_small.json"))
      .backbone.cond_channels;
}
std::vector<ResampleRequest> small_requests() {
  torch::manual_seed(11);
  std::vector<ResampleRequest> reqs(3);
  for (auto& r : reqs) r.cond = torch::randn({10, cond_width()});
  reqs[2].cond = torch::randn({6, cond_width()});  // a second condition length -> second group
  return reqs;
}
}  // namespace

// Every (object, sample) equals an unbatched sampling of that object with the same noise row, then the
// decoder, the official threshold, and the pose decode; meshes are closed and canonical.
TEST(Resampler, BatchedMatchesPerObjectChain) {
  auto cfg = small_config();
  cfg.empty_retries = 0;  // the first draw's chain for every row (retries: the EmptyDecode tests below)
  Resampler rs(cfg);
  EXPECT_EQ(rs.config().rescale_t, 3.0);
  EXPECT_EQ(rs.config().cfg_strength, 7.0);
  const auto reqs = small_requests();
  const auto res = rs.resample(reqs, 1234);
  ASSERT_EQ(res.objects.size(), 3u);
  EXPECT_EQ(res.sampling_calls, 2);  // two condition lengths
  std::printf("resample: sample %.3f s, decode %.3f s, mesh %.3f s\n", res.seconds_sample, res.seconds_decode, res.seconds_mesh);

  // Reference noise: the same seeded CPU generator, all rows in request order.
  auto rng = at::make_generator<at::CPUGeneratorImpl>(1234);
  const auto noise = rs.generator()->noise(3 * 2, rng, torch::kCPU);
  auto opt = rs.sample_options();
  EXPECT_EQ(opt.steps, 2);
  EXPECT_DOUBLE_EQ(opt.cfg_interval.second, 500.0);
  torch::NoGradGuard ng;
  // Batched against one object's sampling: two fp32 runs of the guided sampler (flow_rounding.h).
  const double latent_tol = simu::testing::flow_sample_bound(rs.generator()->config().backbone,
                                                             reqs[0].cond.size(0), opt.cfg_strength);
  for (int r = 0; r < 3; ++r)
    for (int s = 0; s < 2; ++s) {
      const auto& got = res.objects[r][s];
      simu::models::Latents x0;
      for (const auto& [k, v] : noise) x0[k] = v.slice(0, r * 2 + s, r * 2 + s + 1);
      const auto want = rs.generator()->sample(reqs[r].cond.unsqueeze(0), x0, opt);
      for (const auto& [k, v] : want)
        EXPECT_TRUE(simu::testing::close(got.latents.at(k), v, latent_tol, fmt::format("obj {} sample {} {}", r, s, k)));
      // Decode chain on this sample's latent: tokens -> grid -> decoder -> coords (logit > 0). The
      // batched decode and this one are two fp32 evaluations of the decoder: only a voxel whose logit is
      // within their rounding of 0 may fall on the other side.
      const auto logits = rs.decoder()->forward(simu::models::shape_tokens_to_grid(got.latents.at("shape")));
      const auto coords = simu::models::occupied_coords(logits).slice(1, 1, 4);
      if (coords.size(0) > 0) {
        ASSERT_TRUE(got.ok) << got.message;
        const auto grid = logits[0][0];  // [R, R, R]
        auto occupied = torch::zeros_like(grid, torch::kBool);
        if (got.coords.size(0) > 0) {
          const auto c = got.coords.to(torch::kLong);
          occupied.index_put_({c.select(1, 0), c.select(1, 1), c.select(1, 2)}, true);
        }
        const double edge = simu::testing::two_paths(simu::testing::decoder_chain(rs.decoder()->config())) *
                            grid.abs().max().item<double>();
        const auto flipped = occupied != (grid > 0);
        EXPECT_TRUE((grid.abs() <= edge).masked_select(flipped).all().item<bool>())
            << "obj " << r << " sample " << s << ": a voxel away from the threshold changed side";
        EXPECT_EQ(mesh_closedness_problem(got.mesh), "");
        // Canonical frame in float64: (V - centre) / extent, a few roundings of values <= 1.
        const double canon = simu::testing::gamma(8, simu::testing::kFp64Unit);
        const Eigen::Vector3d lo = got.mesh.V.colwise().minCoeff(), hi = got.mesh.V.colwise().maxCoeff();
        EXPECT_NEAR((hi - lo).maxCoeff(), 1.0, canon);
        EXPECT_NEAR((hi + lo).norm(), 0.0, canon);
        EXPECT_GT(mesh_signed_volume(got.mesh), 0.0);
      } else {
        EXPECT_FALSE(got.ok);
      }
      // Pose: proper rotation (fp32 Gram-Schmidt of the sampled 6-D latent: ~20 roundings over the
      // sine of the angle between its two vectors), and the canonical pose maps canonical points where
      // the voxel-frame pose does (float64, ~16 roundings of the terms' magnitudes).
      const double ortho = simu::testing::pose_rotation_bound(got.latents.at("6drotation_normalized"));
      EXPECT_NEAR(got.rotation.determinant(), 1.0, 3 * ortho);
      EXPECT_LT((got.rotation.transpose() * got.rotation - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff(), ortho);
      const Eigen::Vector3d pc(0.1, -0.3, 0.25);
      const Eigen::Vector3d pv = pc / got.canonical.factor + got.canonical.centre;
      const Eigen::Vector3d a = got.rotation * got.scale.cwiseProduct(pv) + got.translation;
      const Eigen::Vector3d b = got.rotation * got.scale_canonical.cwiseProduct(pc) + got.translation_canonical;
      const double terms = 1 + a.norm() + got.scale.cwiseProduct(pv).norm() + got.translation.norm();
      EXPECT_LT((a - b).norm(), simu::testing::gamma(16, simu::testing::kFp64Unit) * terms);
    }
  // The two samples of one object differ (different noise rows): beyond the sampler's rounding.
  EXPECT_GT(simu::testing::rel_err(res.objects[0][0].latents.at("shape"), res.objects[0][1].latents.at("shape")), latent_tol);
}

// Same seed -> same result; another seed -> another result.
TEST(Resampler, Seeded) {
  auto cfg = small_config();
  cfg.num_samples = 1;
  Resampler rs(cfg);
  const auto reqs = small_requests();
  const auto a = rs.resample(reqs, 7), b = rs.resample(reqs, 7), c = rs.resample(reqs, 8);
  EXPECT_TRUE(torch::equal(a.objects[1][0].latents.at("shape"), b.objects[1][0].latents.at("shape")));
  EXPECT_FALSE(torch::equal(a.objects[1][0].latents.at("shape"), c.objects[1][0].latents.at("shape")));
}

// Adapter: the PEFT fixture loads through the default loader (simu::lora::load_peft) and changes the
// shape; a custom loader receives the generator tree.
TEST(Resampler, AdapterLoads) {
  auto cfg = small_config();
  cfg.num_samples = 1;
  const auto reqs = small_requests();
  Resampler base(cfg);
  cfg.adapter_dir = simu::testing::fixture("lora_small");
  Resampler tuned(cfg);
  EXPECT_FALSE(base.has_adapter());
  EXPECT_TRUE(tuned.has_adapter());
  const auto a = base.resample({reqs[0]}, 5), b = tuned.resample({reqs[0]}, 5);
  // Further apart than two runs of one sampler could be (flow_rounding.h).
  EXPECT_GT(simu::testing::rel_err(b.objects[0][0].latents.at("shape"), a.objects[0][0].latents.at("shape")),
            simu::testing::flow_sample_bound(base.generator()->config().backbone, reqs[0].cond.size(0),
                                             base.sample_options().cfg_strength));
  std::string seen_dir;
  bool has_backbone = false;
  Resampler custom(cfg, [&](const std::string& dir, torch::nn::Module& gen) {
    seen_dir = dir;
    for (const auto& p : gen.named_parameters())
      if (p.key().rfind("reverse_fn.backbone.blocks.0.", 0) == 0) has_backbone = true;
  });
  EXPECT_EQ(seen_dir, cfg.adapter_dir);
  EXPECT_TRUE(has_backbone);
}

// Requests given as embedder inputs give the same result as requests carrying the embedder's tokens.
TEST(Resampler, EmbedsConditionInputs) {
  ResamplerConfig cfg = small_config();
  cfg.generator_config = simu::testing::source_dir() + "/configs/stage1_small.yaml";
  cfg.generator_weights = "";  // random init, as wide as the fixture embedder's tokens
  cfg.random_weights = true;
  cfg.generator_overrides = {fmt::format(
      "flow_model.cond_channels={}",
      simu::models::CondEmbedderConfig::load(simu::testing::fixture("cond_embedder_small.json")).embed_dims())};
  cfg.embedder_config = simu::testing::fixture("cond_embedder_small.json");
  cfg.embedder_weights = simu::testing::fixture("cond_embedder_small.safetensors");
  cfg.num_samples = 1;
  Resampler rs(cfg);
  auto io = simu::data::SafeTensorsFile::open(simu::testing::fixture("cond_embedder_small_io.safetensors"));
  std::vector<ResampleRequest> by_inputs(2), by_tokens(2);
  const auto fused = io.get("out.fused").clone();  // [2, L, 64], the official embedder output
  for (int i = 0; i < 2; ++i) {
    for (const auto& name : rs.embedder()->input_names()) by_inputs[i].inputs[name] = io.get("in." + name)[i].clone();
    by_tokens[i].cond = fused[i];
  }
  const auto conds = rs.conditions(by_inputs);
  // The port's and the official embedder: two fp32 evaluations (flow_rounding.h).
  const double cond_tol = simu::testing::two_paths(
      simu::testing::embedder_chain(simu::models::CondEmbedderConfig::load(cfg.embedder_config)));
  for (int i = 0; i < 2; ++i) EXPECT_TRUE(simu::testing::close(conds[i], fused[i], cond_tol, "embedded condition"));
  // Conditions that differ by that much move the samples by as much (first order: the condition enters
  // through normalised layers at gain ~1), plus two runs' rounding of the sampler.
  const auto a = rs.resample(by_inputs, 3), b = rs.resample(by_tokens, 3);
  const double shape_tol =
      cond_tol + simu::testing::flow_sample_bound(rs.generator()->config().backbone, fused.size(1), rs.sample_options().cfg_strength);
  for (int i = 0; i < 2; ++i)
    EXPECT_TRUE(simu::testing::close(a.objects[i][0].latents.at("shape"), b.objects[i][0].latents.at("shape"), shape_tol,
                                     "shape from inputs vs tokens"));
}

// Bad requests are reported with their index.
TEST(Resampler, RejectsWrongConditionWidth) {
  Resampler rs(small_config());
  std::vector<ResampleRequest> reqs(2);
  reqs[0].cond = torch::randn({10, cond_width()});
  reqs[1].cond = torch::randn({10, cond_width() - 1});
  try {
    rs.resample(reqs, 0);
    FAIL();
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("request 1"), std::string::npos) << e.what();
  }
}

// probe --resample with an unreadable depth file: every object fails with the file named (and the
// call returns normally), instead of a later "too few results".
TEST(Resampler, ProbeBadDepthFileIsAPerObjectErrorNamingTheFile) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "needs OpenCV";
#else
  Resampler rs(small_config());
  // A missing file is refused when the resampling function is made, naming it.
  Scene missing;
  missing.image_path = "/nonexistent/image.png";
  missing.depth_path = "/nonexistent/depth.png";
  try {
    (void)make_probe_resample_fn(rs, missing);
    ADD_FAILURE() << "no error for a missing image/depth file";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("/nonexistent/"), std::string::npos) << e.what();
  }
  // A depth file that exists but cannot be read fails every object with the file's and the object's name.
  const std::string dir = simu::testing::temp_dir("bad_depth");
  Scene scene;
  scene.image_path = dir + "/image.png";
  scene.depth_path = dir + "/depth.png";
  ASSERT_TRUE(cv::imwrite(scene.image_path, cv::Mat(8, 8, CV_8UC3, cv::Scalar(10, 20, 30))));
  std::ofstream(scene.depth_path) << "not a png";
  ProbeResampleRequest rq;
  rq.object_id = "cup";
  rq.modal_mask = cv::Mat::zeros(8, 8, CV_8UC1);
  auto fn = make_probe_resample_fn(rs, scene);
  const auto out = fn({rq, rq});
  ASSERT_EQ(out.size(), 2u);
  for (const auto& r : out) {
    EXPECT_FALSE(r.ok);
    EXPECT_NE(r.message.find(scene.depth_path), std::string::npos) << r.message;
    EXPECT_NE(r.message.find("cup"), std::string::npos) << r.message;
  }
#endif
}

// Missing weight files are an error naming the flag unless random weights are asked for (with a banner).
TEST(Resampler, MissingWeightsNameTheFlag) {
  ResamplerConfig c = small_config();
  c.decoder_weights = "";
  try {
    Resampler rs(c);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("--decoder-weights"), std::string::npos) << e.what();
  }
  c.random_weights = true;
  Resampler rs(c);
  EXPECT_NE(rs.random_weights_banner().find("RANDOM WEIGHTS"), std::string::npos);
  EXPECT_NE(rs.random_weights_banner().find("--decoder-weights"), std::string::npos);
  EXPECT_TRUE(Resampler(small_config()).random_weights_banner().empty());
}

namespace {
// Lowers every occupancy logit of the resampler's decoder by `shift`: the decoder ends in a convolution
// (out_layer.2) whose bias is added to every output voxel.
void lower_logits(Resampler& rs, double shift) {
  torch::NoGradGuard ng;
  auto params = rs.decoder()->named_parameters();
  ASSERT_TRUE(params.contains("out_layer.2.bias"));
  params["out_layer.2.bias"].sub_(shift);
}
}  // namespace

// The retry loop on a scripted attempt: only the rows that came out empty are drawn again, with the
// seeds of retry_noise_seed; a redraw that succeeds says "retried N times"; a row empty every time
// fails naming its attempts; 0 retries is one attempt, as before.
TEST(ResamplerRetry, RedrawsOnlyEmptyRowsWithDerivedSeeds) {
  // Row 0 is never empty, row 1 only on its first draw, row 2 on every draw.
  std::vector<ResampledShape> shapes(3);
  const std::vector<ResampledShape*> outs{&shapes[0], &shapes[1], &shapes[2]};
  std::vector<std::pair<std::vector<size_t>, uint64_t>> calls;
  auto attempt = [&](const std::vector<size_t>& rows, uint64_t noise_seed) {
    const size_t a = calls.size();
    calls.push_back({rows, noise_seed});
    for (size_t k : rows) {
      const bool empty = k == 2 || (k == 1 && a == 0);
      shapes[k].ok = !empty;
      shapes[k].coords = torch::zeros({empty ? 0 : 4, 3}, torch::kInt32);
    }
  };
  const uint64_t seed = 42;
  sample_with_retries(outs, seed, 2, attempt);
  ASSERT_EQ(calls.size(), 3u);
  EXPECT_EQ(calls[0].first, (std::vector<size_t>{0, 1, 2}));
  EXPECT_EQ(calls[1].first, (std::vector<size_t>{1, 2}));
  EXPECT_EQ(calls[2].first, (std::vector<size_t>{2}));
  EXPECT_EQ(calls[0].second, seed);
  EXPECT_EQ(calls[1].second, retry_noise_seed(seed, 1));
  EXPECT_EQ(calls[2].second, retry_noise_seed(seed, 2));
  EXPECT_NE(calls[1].second, seed);
  EXPECT_NE(calls[2].second, calls[1].second);
  EXPECT_TRUE(shapes[0].ok);
  EXPECT_EQ(shapes[0].retries, 0);
  EXPECT_EQ(shapes[0].message, "");
  EXPECT_TRUE(shapes[1].ok);
  EXPECT_EQ(shapes[1].retries, 1);
  EXPECT_NE(shapes[1].message.find("retried 1 time"), std::string::npos) << shapes[1].message;
  EXPECT_FALSE(shapes[2].ok);
  EXPECT_TRUE(empty_occupancy(shapes[2]));
  EXPECT_EQ(shapes[2].retries, 2);
  EXPECT_NE(shapes[2].message.find("in 3 attempts (retried 2 times"), std::string::npos) << shapes[2].message;

  // Retries off: one attempt, the empty rows stay failed without a retry note.
  calls.clear();
  shapes.assign(3, ResampledShape{});
  sample_with_retries(outs, seed, 0, attempt);
  EXPECT_EQ(calls.size(), 1u);
  EXPECT_FALSE(shapes[1].ok);
  EXPECT_EQ(shapes[1].retries, 0);
}

// Every logit far below 0 (the decoder's output bias lowered): every attempt is empty, each retry is
// one more sampling per condition length, and every sample fails naming its attempts.
TEST(Resampler, EmptyDecodesAreRetriedThenFail) {
  const auto reqs = small_requests();  // two condition lengths
  for (int retries : {0, 2}) {
    auto cfg = small_config();
    cfg.empty_retries = retries;
    Resampler rs(cfg);
    lower_logits(rs, 1e6);
    const auto res = rs.resample(reqs, 9);
    EXPECT_EQ(res.sampling_calls, 2 * (retries + 1)) << retries << " retries";
    for (const auto& samples : res.objects)
      for (const auto& got : samples) {
        EXPECT_FALSE(got.ok);
        EXPECT_TRUE(empty_occupancy(got));
        EXPECT_EQ(got.retries, retries);
        EXPECT_NE(got.message.find("no occupied voxel"), std::string::npos) << got.message;
        if (retries > 0)
          EXPECT_NE(got.message.find(fmt::format("in {} attempts", retries + 1)), std::string::npos) << got.message;
      }
  }
}

// A sample empty on its first draw and occupied on its first retry comes back ok, with retries 1, its
// note, and exactly the sample of the retry's noise (retry_noise_seed(seed, 1)).
TEST(Resampler, EmptyDecodeRetriedWithFreshNoiseSucceeds) {
  auto cfg = small_config();
  cfg.num_samples = 1;
  cfg.empty_retries = 0;
  const std::vector<ResampleRequest> req{small_requests()[0]};  // one row: a retry samples the same batch shape
  Resampler probe(cfg);
  // The first seed whose retry noise gives a larger largest logit than its own noise, by more than two
  // evaluations' rounding of the decoder (flow_rounding.h).
  const double edge = simu::testing::two_paths(simu::testing::decoder_chain(probe.decoder()->config()));
  auto largest_logit = [&](uint64_t s) {
    const auto res = probe.resample(req, s);
    const auto logits = probe.decode_logits(res.objects[0][0].latents.at("shape"));
    return std::make_pair(logits.max().item<double>(), logits.abs().max().item<double>());
  };
  uint64_t seed = 0;
  double shift = 0;
  for (uint64_t s = 1; s <= 20 && shift == 0; ++s) {
    const auto [first, first_abs] = largest_logit(s);
    const auto [retry, retry_abs] = largest_logit(retry_noise_seed(s, 1));
    const double mid = 0.5 * (first + retry);
    if (retry - first > 2 * edge * (std::max(first_abs, retry_abs) + std::abs(mid)) + 1e-12) seed = s, shift = mid;
  }
  ASSERT_NE(shift, 0.0) << "no seed in 1..20 whose retry draw decodes higher than its first draw";
  // Every logit lowered by the midpoint: the first draw is empty, the retry's is not.
  cfg.empty_retries = 2;
  Resampler rs(cfg);
  lower_logits(rs, shift);
  const auto res = rs.resample(req, seed);
  const auto& got = res.objects[0][0];
  ASSERT_TRUE(got.ok) << got.message;
  EXPECT_EQ(got.retries, 1);
  EXPECT_EQ(res.sampling_calls, 2);
  EXPECT_NE(got.message.find("retried 1 time"), std::string::npos) << got.message;
  // The retry's sample: the same single-row sampling from the retry seed's noise, bit for bit.
  const auto want = probe.resample(req, retry_noise_seed(seed, 1));
  EXPECT_TRUE(torch::equal(got.latents.at("shape"), want.objects[0][0].latents.at("shape")));
}
