// Sampler settings as released: a released ss_generator.yaml carries training-time sampler values
// (inference_steps 2, rescale_t 1, strength 2.0, no no_shortcut); every inference entry point must
// sample as the official inference pipeline does (25 steps, rescale_t 3, CFG 7 on t*1000 in [0, 500],
// add_flag, d = 0) unless the user overrides a value, and say which values it used. Checked against
// the official small generator's sampling (ss_generator_small_io.safetensors, made by the official
// code at 4 steps) through configs carrying the released values (tests/testdata/models/).
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "data/safetensors.h"
#include "models/generator.h"
#include "pipeline/resample/resampler.h"
#include "flow_rounding.h"
#include "test_util.h"

#include <nlohmann/json.hpp>

namespace sm = simu::models;

namespace {

std::string data(const std::string& name) { return simu::testing::source_dir() + "/tests/testdata/models/" + name; }

sm::Latents with_prefix(const std::map<std::string, torch::Tensor>& io, const std::string& prefix) {
  sm::Latents out;
  for (const auto& [k, v] : io)
    if (k.rfind(prefix, 0) == 0) out[k.substr(prefix.size())] = v;
  return out;
}

// max relative error over the latents against the fixture's `prefix` tensors.
double latents_err(const sm::Latents& got, const std::map<std::string, torch::Tensor>& io, const std::string& prefix) {
  double e = 0;
  for (const auto& [k, w] : with_prefix(io, prefix)) e = std::max(e, simu::testing::rel_err(got.at(k), w));
  return e;
}

// The step count the official code sampled the fixture with (ss_generator_small.json).
int fixture_steps() {
  std::ifstream in(simu::testing::fixture("ss_generator_small.json"));
  return nlohmann::json::parse(in).at("module").at("generator").at("backbone").at("inference_steps").get<int>();
}

// Two fp32 runs of the generator's sampler at guidance strength s (flow_rounding.h).
double sample_bound(const sm::Generator& gen, const torch::Tensor& cond, double s) {
  return simu::testing::flow_sample_bound(gen->config().backbone, cond.size(1), s);
}

}  // namespace

// The released yaml (real dimensions, config only): its own values are the training ones; the
// official inference values replace them, and the description names where each came from.
TEST(SamplerReleased, ReleasedYamlGivesOfficialInferenceValues) {
  const auto c = sm::GeneratorConfig::from_official_file(data("ss_generator_released.yaml"));
  EXPECT_EQ(c.inference_steps, 2);
  EXPECT_DOUBLE_EQ(c.rescale_t, 1.0);
  EXPECT_DOUBLE_EQ(c.cfg_strength, 2.0);
  EXPECT_FALSE(c.no_shortcut);
  EXPECT_EQ(c.backbone.model_channels, 1024);
  // What the yaml alone would do: 2 shortcut steps with CFG 2 (training-time values).
  const auto train = sm::SampleOptions::from(c);
  EXPECT_EQ(train.steps, 2);
  EXPECT_TRUE(train.shortcut);
  // What the official inference does.
  const auto o = sm::official_inference_options(c);
  EXPECT_EQ(o.steps, 25);
  EXPECT_DOUBLE_EQ(o.rescale_t, 3.0);
  EXPECT_DOUBLE_EQ(o.cfg_strength, 7.0);
  EXPECT_DOUBLE_EQ(o.cfg_interval.first, 0.0);
  EXPECT_DOUBLE_EQ(o.cfg_interval.second, 500.0);
  EXPECT_FALSE(o.shortcut);  // no_shortcut = true: d = 0
  EXPECT_EQ(o.unconditional_handling, "add_flag");
  EXPECT_EQ(o.solver, "euler");
  const auto text = sm::describe_sampler(o, c);
  std::printf("released yaml, no overrides: %s\n", text.c_str());
  EXPECT_NE(text.find("steps 25 (official inference)"), std::string::npos) << text;
  EXPECT_NE(text.find("rescale_t 3 (official inference)"), std::string::npos) << text;
  EXPECT_NE(text.find("cfg 7 on t*1000 in [0, 500]"), std::string::npos) << text;
  EXPECT_NE(text.find("d = 0 (no_shortcut)"), std::string::npos) << text;
  // An explicit user value wins and is labelled.
  sm::SamplerOverrides u;
  u.steps = 10;
  u.cfg_strength = 5.0;
  const auto ou = sm::official_inference_options(c, u);
  EXPECT_EQ(ou.steps, 10);
  EXPECT_DOUBLE_EQ(ou.cfg_strength, 5.0);
  EXPECT_DOUBLE_EQ(ou.rescale_t, 3.0);
  const auto tu = sm::describe_sampler(ou, c, u);
  EXPECT_NE(tu.find("steps 10 (user)"), std::string::npos) << tu;
  // Distillation (shortcut) mode: d = 1/steps, no CFG unless asked.
  sm::SamplerOverrides s;
  s.shortcut = true;
  const auto os = sm::official_inference_options(c, s);
  EXPECT_TRUE(os.shortcut);
  EXPECT_DOUBLE_EQ(os.cfg_strength, 0.0);
}

// The small generator written with the released sampler values: official_inference_options with only
// the step count set to the fixture's reproduces the official CFG sampling, and the shortcut
// override reproduces the official distillation sampling; the yaml's own values would not.
TEST(SamplerReleased, SmallGeneratorWithReleasedValuesSamplesAsTheOfficialInference) {
  torch::NoGradGuard ng;
  auto gen = sm::load_generator(data("ss_generator_small_released_sampler.yaml"),
                                simu::testing::fixture("ss_generator_small.safetensors"), torch::kCPU);
  const auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  const auto x0 = with_prefix(io, "in.sample.x0.");
  const auto cond = io.at("in.cond");
  sm::SamplerOverrides u;
  u.steps = fixture_steps();
  auto o = sm::official_inference_options(gen->config(), u);
  o.bf16_autocast = false;
  const double e_cfg = latents_err(gen->sample(cond, x0, o), io, "out.sample_cfg.");
  std::printf("official inference values (steps %d): max rel error vs official sample_cfg %.3g\n", *u.steps, e_cfg);
  // The port's and the official guided sampler: two fp32 runs (flow_rounding.h).
  const double cfg_tol = sample_bound(gen, cond, o.cfg_strength);
  EXPECT_LT(e_cfg, cfg_tol);
  u.shortcut = true;
  auto os = sm::official_inference_options(gen->config(), u);
  os.bf16_autocast = false;
  const double e_sc = latents_err(gen->sample(cond, x0, os), io, "out.sample_shortcut.");
  EXPECT_LT(e_sc, sample_bound(gen, cond, os.cfg_strength));
  // The yaml's training-time values (2 shortcut steps, rescale 1, CFG 2) give another result: further
  // from the official one than rounding can explain.
  auto train = sm::SampleOptions::from(gen->config());
  train.steps = *u.steps;
  train.bf16_autocast = false;
  const double e_train = latents_err(gen->sample(cond, x0, train), io, "out.sample_cfg.");
  std::printf("training-time values (steps %d): max rel error vs official sample_cfg %.3g\n", train.steps, e_train);
  EXPECT_GT(e_train, cfg_tol);
}

// The Resampler (probe --resample, build_pairs, lift) given the released sampler values: its options
// are the official ones (only `steps` changed by the test) and sample as the official code does.
TEST(SamplerReleased, ResamplerUsesOfficialInferenceValues) {
  simu::resample::ResamplerConfig c;
  c.generator_config = data("ss_generator_small_released_sampler.yaml");
  c.generator_weights = simu::testing::fixture("ss_generator_small.safetensors");
  c.decoder_config = simu::testing::fixture("ss_decoder_small.json");
  c.decoder_weights = simu::testing::fixture("ss_decoder_small.safetensors");
  c.device = "cpu";
  c.steps = fixture_steps();
  simu::resample::Resampler rs(c);
  const auto o = rs.sample_options();
  EXPECT_EQ(o.steps, c.steps);
  EXPECT_DOUBLE_EQ(o.rescale_t, 3.0);
  EXPECT_DOUBLE_EQ(o.cfg_strength, 7.0);
  EXPECT_DOUBLE_EQ(o.cfg_interval.second, 500.0);
  EXPECT_FALSE(o.shortcut);
  EXPECT_EQ(o.unconditional_handling, "add_flag");
  ASSERT_TRUE(rs.sampler_overrides().steps.has_value());
  EXPECT_FALSE(rs.sampler_overrides().cfg_strength.has_value());
  torch::NoGradGuard ng;
  const auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  const double e = latents_err(rs.generator()->sample(io.at("in.cond"), with_prefix(io, "in.sample.x0."), o), io,
                               "out.sample_cfg.");
  EXPECT_LT(e, sample_bound(rs.generator(), io.at("in.cond"), o.cfg_strength));  // two fp32 sampler runs
}

// sample_stage1 given the released sampler values: logs and records the official values (the file's
// metadata), the user's --steps marked as such.
TEST(SamplerReleased, SampleStage1CliRecordsOfficialValues) {
  const std::string exe = simu::testing::build_dir() + "/sample_stage1";
  if (!std::filesystem::exists(exe)) GTEST_SKIP() << "build the sample_stage1 target first (" << exe << ")";
  const auto dir = simu::testing::temp_dir("sample_stage1_released");
  const auto io = simu::data::load_safetensors(simu::testing::fixture("ss_generator_small_io.safetensors"));
  simu::data::save_safetensors(dir + "/cond.safetensors", std::map<std::string, torch::Tensor>{{"cond", io.at("in.cond")}});
  const std::string cmd = exe + " --config " + data("ss_generator_small_released_sampler.yaml") + " --weights " +
                          simu::testing::fixture("ss_generator_small.safetensors") + " --cond " + dir +
                          "/cond.safetensors --steps 3 --device cpu --out " + dir + "/lat.safetensors > " + dir +
                          "/log.txt 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << cmd;
  std::stringstream log;
  log << std::ifstream(dir + "/log.txt").rdbuf();
  EXPECT_NE(log.str().find("steps 3 (user), rescale_t 3 (official inference), cfg 7 on t*1000 in [0, 500]"),
            std::string::npos)
      << log.str();
  const auto f = simu::data::SafeTensorsFile::open(dir + "/lat.safetensors");
  EXPECT_EQ(f.metadata().at("steps"), "3");
  EXPECT_EQ(f.metadata().at("cfg_strength"), "7");
  EXPECT_EQ(f.metadata().at("rescale_t"), "3");
  EXPECT_EQ(f.metadata().at("cfg_interval"), "0 500");
  EXPECT_EQ(f.metadata().at("shortcut"), "0");
}
