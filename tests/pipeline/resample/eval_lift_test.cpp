// Tests eval_lift (resample/eval_lift.h): the option parsers, the aggregates and paired deltas of
// summary.json on hand-made rows with known answers, the ground truth fed back as the prediction
// through the scenes and the whole metric path (IoU 1, F 1, errors 0), and the program end to end on
// the committed mesh folder tests/testdata/meshes with the small fixture models (random-weight
// embedder): it runs, every metric is in its range, sizes follow the files' units, the base rows do not
// change when a compare adapter is added (same objects and noise), --select render-compare keeps the
// lowest-scored of several samples, and bad inputs are errors naming the flag or the folder; --shard
// partitions a run's objects exactly.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <nlohmann/json.hpp>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>
#include <array>
#include <algorithm>

#include "common/error.h"
#include "common/fs.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/resample/eval_lift.h"
#include "pipeline/world/parts.h"
#include "pipeline/world/voxelize.h"
#include "test_util.h"

namespace sr = simu::resample;
using json = nlohmann::json;

namespace {

// Runs a command, output to `log`; returns its exit status and the output.
std::pair<int, std::string> run(const std::string& cmd, const std::string& log) {
  const int st = std::system((cmd + " > " + log + " 2>&1").c_str());
  std::ifstream f(log);
  std::string out((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  return {WIFEXITED(st) ? WEXITSTATUS(st) : -1, out};
}

json read_json(const std::string& path) { return json::parse(simu::fs::read_file(path)); }

std::string meshes_dir() { return simu::testing::source_dir() + "/tests/testdata/meshes"; }

// The program with the small fixture models (as scripts/demo.sh runs them), 2 sampling steps on the CPU.
std::string eval_cmd(const std::string& args) {
  const std::string fix = simu::testing::shared_dir() + "/fixtures/";
  return simu::testing::build_dir() + "/eval_lift --objects " + meshes_dir() + " --device cpu --steps 2 " +
         "--generator-config " + fix + "ss_generator_small.json --generator-weights " + fix +
         "ss_generator_small.safetensors --decoder-config " + simu::testing::source_dir() +
         "/configs/ss_decoder_small.yaml --decoder-weights " + fix + "ss_decoder_small.safetensors --embedder-config " +
         simu::testing::source_dir() + "/configs/demo_embedder_small.json --random-weights " + args;
}

// A metric row whose scores are all `v` (IoU, F-scores, errors).
simu::physics::ShapeMetrics metrics_of(double v) {
  simu::physics::ShapeMetrics m;
  m.iou = v;
  m.fscore = {{0.01, v, v, v}, {0.02, v, v, v}};
  m.chamfer = v, m.rot_err_deg = v, m.trans_err = v, m.scale_err_pct = v;
  return m;
}

}  // namespace

TEST(EvalLift, OptionParsers) {
  EXPECT_EQ(sr::parse_visible_range("40-70"), std::make_pair(0.4, 0.7));
  EXPECT_EQ(sr::parse_visible_range("0.4-0.7"), std::make_pair(0.4, 0.7));
  EXPECT_EQ(sr::parse_visible_range("0-100"), std::make_pair(0.0, 1.0));
  for (const char* bad : {"70-40", "40", "a-b", "50-150", "40-70x", "-5-20"})
    EXPECT_NE(simu::testing::error_of([&] { sr::parse_visible_range(bad); }).find("--visible"), std::string::npos) << bad;
  EXPECT_EQ(sr::visibility_bucket(1.0), "unoccluded");
  EXPECT_EQ(sr::visibility_bucket(0.999), "unoccluded");
  EXPECT_EQ(sr::visibility_bucket(0.99), "70-100%");
  EXPECT_EQ(sr::visibility_bucket(0.7), "70-100%");
  EXPECT_EQ(sr::visibility_bucket(0.69), "40-70%");
  EXPECT_EQ(sr::visibility_bucket(0.4), "40-70%");
  EXPECT_EQ(sr::visibility_bucket(0.39), "<40%");
  EXPECT_EQ(sr::depth_kinds("both"), (std::vector<std::string>{"clean", "corrupted"}));
  EXPECT_NE(simu::testing::error_of([] { sr::depth_kinds("noisy"); }).find("--depth"), std::string::npos);
  const auto files = sr::list_mesh_files(meshes_dir());
  ASSERT_EQ(files.size(), 5u);
  EXPECT_NE(files[0].find("box_cm.obj"), std::string::npos);  // sorted
  const std::string empty = simu::testing::temp_dir("eval_lift_empty");
  EXPECT_NE(simu::testing::error_of([&] { sr::list_mesh_files(empty); }).find(empty), std::string::npos);
}

// Hand-made rows: three objects in two buckets, compare = base + 0.1 on every score, one base lift failed.
// Means and medians are worked out by hand; the paired difference of every resample is exactly the
// shift where both models lifted, so its interval is a point.
// shape_iou's grid IoU, counted by hand on a 4^3 grid in the decoder's layout (flat (x R + y) R + z):
// the ground truth x in 0..2, y = 0, z in 0..1 (6 voxels); the sample x in 0..2, y = 0, z = 0 (3 voxels,
// all inside) -> 3 / 6. The same coordinates read in another axis order would give 2 / 7.
TEST(EvalLift, OccupancyIouInTheDecodersLayout) {
  const int64_t R = 4;
  std::vector<uint8_t> gt(R * R * R, 0);
  for (int64_t x = 0; x < 3; ++x)
    for (int64_t z = 0; z < 2; ++z) gt[size_t((x * R + 0) * R + z)] = 1;
  const auto coords = torch::tensor({0, 0, 0, 1, 0, 0, 2, 0, 0, 9, 0, 0}, torch::kInt32).reshape({4, 3});  // (9,0,0): outside, ignored
  EXPECT_DOUBLE_EQ(simu::resample::occupancy_iou(coords, gt, R), 0.5);
  EXPECT_DOUBLE_EQ(simu::resample::occupancy_iou(torch::zeros({0, 3}, torch::kInt32), std::vector<uint8_t>(R * R * R, 0), R), 1.0);
  EXPECT_DOUBLE_EQ(simu::resample::occupancy_iou(torch::zeros({0, 3}, torch::kInt32), gt, R), 0.0);
  EXPECT_THROW(simu::resample::occupancy_iou(coords, gt, 5), simu::Error);
}

// --shape-grid's pooling: fine voxels (R = 8) map to the coarse voxel containing them (S = 4), once each;
// the pooled shape of the world's filled voxelisation at 2S^3 is exactly its filled voxelisation at S^3
// for a box whose faces lie on coarse voxel boundaries (independent of the pooling code: both grids come
// from world::voxelize_filled); a side that does not divide R is refused naming the flag.
TEST(EvalLift, PoolCoordsToACoarserGrid) {
  const auto fine = torch::tensor({0, 0, 0, 1, 1, 1, 2, 0, 7, 3, 1, 6, 7, 7, 7}, torch::kInt32).reshape({5, 3});
  const auto pooled = simu::resample::pool_coords(fine, 8, 4);
  std::set<std::array<int64_t, 3>> got;
  for (int64_t i = 0; i < pooled.size(0); ++i) got.insert({pooled[i][0].item<int64_t>(), pooled[i][1].item<int64_t>(), pooled[i][2].item<int64_t>()});
  const std::set<std::array<int64_t, 3>> want = {{0, 0, 0}, {1, 0, 3}, {3, 3, 3}};
  EXPECT_EQ(got, want);
  EXPECT_EQ(pooled.size(0), 3);
  EXPECT_TRUE(torch::equal(simu::resample::pool_coords(fine, 8, 8), fine.to(torch::kInt64)));
  EXPECT_NE(simu::testing::error_of([&] { simu::resample::pool_coords(fine, 8, 3); }).find("--shape-grid"), std::string::npos);
  // A box spanning coarse voxels [1, 3) x [0, 4) x [1, 2) of a 4^3 grid over the unit cube [-0.5, 0.5]^3
  // (shrunk by 1e-6 so that the conservative voxelisation stops at the boundaries).
  const double e = 1e-6;
  const auto box = simu::world::box_part({0.5 - 2 * e, 1.0 - 2 * e, 0.25 - 2 * e}, {0.0, 0.0, -0.125});
  const auto g8 = simu::world::voxelize_filled(box, 8), g4 = simu::world::voxelize_filled(box, 4);
  std::vector<int32_t> c8;
  for (int x = 0; x < 8; ++x)
    for (int y = 0; y < 8; ++y)
      for (int z = 0; z < 8; ++z)
        if (g8[size_t((x * 8 + y) * 8 + z)]) c8.insert(c8.end(), {x, y, z});
  const auto coords8 = torch::tensor(c8, torch::kInt32).reshape({-1, 3});
  EXPECT_EQ(std::count(g4.begin(), g4.end(), 1), 2 * 4 * 1);
  EXPECT_DOUBLE_EQ(simu::resample::occupancy_iou(simu::resample::pool_coords(coords8, 8, 4), g4, 4), 1.0);
}

TEST(EvalLift, SummaryAggregatesAndPairedDeltas) {
  sr::EvalLiftResult r;
  r.depths = {"clean"};
  r.models = {"base", "compare"};
  const double vis[3] = {1.0, 0.5, 0.55};
  for (int i = 0; i < 3; ++i) {
    sr::EvalObject o;
    o.id = "scene/obj" + std::to_string(i);
    o.visible_fraction = vis[i];
    o.bucket = sr::visibility_bucket(vis[i]);
    r.objects.push_back(o);
    for (const char* model : {"base", "compare"}) {
      sr::EvalRow row;
      row.object = i, row.depth = "clean", row.model = model;
      row.ok = !(i == 2 && std::string(model) == "base");
      row.error = row.ok ? "" : "object scene/obj2: no usable sample";
      row.metrics = metrics_of(0.2 * (i + 1) + (std::string(model) == "compare" ? 0.1 : 0.0));
      r.rows.push_back(row);
    }
  }
  sr::EvalLiftOptions opt;
  opt.bootstrap_resamples = 500;
  const json s = sr::eval_summary(r, opt, {"", "adapter_dir"});
  const json& base = s["buckets"]["clean"]["base"];
  EXPECT_EQ(base["unoccluded"]["n"], 1);
  EXPECT_EQ(base["40-70%"]["n"], 2);
  EXPECT_EQ(base["40-70%"]["n_failed"], 1);
  EXPECT_EQ(base["<40%"]["n"], 0);
  EXPECT_TRUE(base["<40%"]["iou_mean"].is_null());
  // Failed lifts count 0 in IoU and F-score means: (0.4 + 0) / 2; and are left out of Chamfer and medians.
  EXPECT_NEAR(base["40-70%"]["iou_mean"].get<double>(), 0.2, 1e-15);
  EXPECT_NEAR(base["40-70%"]["chamfer_mean"].get<double>(), 0.4, 1e-15);
  EXPECT_NEAR(base["all"]["rot_err_deg_median"].get<double>(), 0.3, 1e-15);  // median of 0.2, 0.4
  EXPECT_EQ(s["models"]["compare"]["adapter"], "adapter_dir");
  // The unoccluded object lifted under both: every resample's difference is 0.1 (two roundings).
  const json& d = s["deltas"]["clean"]["unoccluded"]["iou_mean"];
  EXPECT_NEAR(d["delta"].get<double>(), 0.1, 1e-15);
  EXPECT_NEAR(d["ci95"][0].get<double>(), 0.1, 1e-15);
  EXPECT_NEAR(d["ci95"][1].get<double>(), 0.1, 1e-15);
  // In 40-70% the failed base row scores 0 against 0.7: IoU means 0.2 -> 0.6, delta 0.4.
  EXPECT_NEAR(s["deltas"]["clean"]["40-70%"]["iou_mean"]["delta"].get<double>(), 0.4, 1e-15);
  ASSERT_EQ(s["objects"].size(), 6u);
  EXPECT_EQ(s["objects"][4]["error"], "object scene/obj2: no usable sample");  // obj2's base row
  EXPECT_NE(sr::format_summary_table(s).find("40-70%"), std::string::npos);
}

// The ground truth fed back as the prediction through eval_lift's scenes and metric path: every row
// ideal (IoU and F exactly 1: the same voxels and a zero distance; Chamfer a few ulps of the object's
// coordinates; rotation: acos near 1, 1e-5 degrees, as in ShapeMetrics.GroundTruthAsPredictionIsPerfect).
TEST(EvalLift, GroundTruthAsPredictionIsPerfect) {
  sr::EvalLiftOptions opt;
  opt.objects_dir = meshes_dir();
  opt.gt_as_prediction = true;
  opt.pictures = false;
  opt.depth = "both";
  opt.metrics.samples = 2000;
  const auto r = sr::run_eval_lift(opt, {}, simu::testing::temp_dir("eval_lift_gt"));
  ASSERT_EQ(r.objects.size(), 5u);
  ASSERT_EQ(r.rows.size(), 10u);
  for (const auto& row : r.rows) {
    ASSERT_TRUE(row.ok) << row.error;
    EXPECT_EQ(row.metrics.iou, 1.0) << r.objects[row.object].id;
    EXPECT_EQ(row.metrics.fscore[0].f, 1.0);
    EXPECT_EQ(row.metrics.fscore[1].f, 1.0);
    EXPECT_LT(row.metrics.chamfer, 1e-12);
    EXPECT_LT(row.metrics.rot_err_deg, 1e-5);
    EXPECT_EQ(row.metrics.trans_err, 0.0);
    EXPECT_EQ(row.metrics.scale_err_pct, 0.0);
  }
}

// --shard I/N: the shards of a run hold exactly its objects, each once (world scenes dealt round robin,
// placed objects by index), with the same ground truth; the shard parser refuses malformed values.
TEST(EvalLift, ShardsPartitionTheWholeRun) {
  for (const char* source : {"test", "heldout"}) {
    sr::EvalLiftOptions opt;
    opt.world = source;
    opt.count = 7;
    opt.gt_as_prediction = true;
    opt.pictures = false;
    opt.metrics.samples = 500;
    const auto whole = sr::run_eval_lift(opt, {}, simu::testing::temp_dir("eval_lift_shard_whole"));
    std::map<std::string, double> seen;  // object -> GT longest side
    for (int i = 0; i < 3; ++i) {
      opt.shard_index = i;
      opt.shard_count = 3;
      const auto part = sr::run_eval_lift(opt, {}, simu::testing::temp_dir("eval_lift_shard_part"));
      for (const auto& o : part.objects) EXPECT_TRUE(seen.emplace(o.id, o.gt.size()).second) << source << " " << o.id;
    }
    ASSERT_EQ(seen.size(), whole.objects.size()) << source;
    for (const auto& o : whole.objects) {
      ASSERT_TRUE(seen.count(o.id)) << source << " " << o.id;
      EXPECT_EQ(seen[o.id], o.gt.size()) << o.id;
    }
  }
  EXPECT_EQ(sr::parse_shard("2/5"), std::make_pair(2, 5));
  for (const char* bad : {"5/5", "-1/2", "1", "1/0", "a/b", "1/2x"}) {
    try {
      sr::parse_shard(bad);
      ADD_FAILURE() << bad << " was accepted";
    } catch (const simu::Error& e) {
      EXPECT_NE(std::string(e.what()).find("--shard"), std::string::npos) << e.what();
    }
  }
}

#ifdef SIMU_HAVE_OPENCV
// The program on the committed meshes: the ground truth as the prediction over the whole folder (every
// aggregate ideal; the sizes follow the files' units); two of them lifted from clean and corrupted
// depth (every metric in range, pictures written); base against base + the fixture adapter on the
// clean depth (the base rows identical to the first run's: same objects, placements and noise); errors.
TEST(EvalLiftCli, ObjectsFolderDepthsAndCompareAdapter) {
  const std::string tmp = simu::testing::temp_dir("eval_lift_cli");
  // The hidden testing flag: no model runs (none is configured here).
  auto [st0, out0] = run(simu::testing::build_dir() + "/eval_lift --objects " + meshes_dir() +
                             " --gt-as-prediction --surface-samples 2000 --out " + tmp + "/gt",
                         tmp + "/gt.log");
  ASSERT_EQ(st0, 0) << out0;
  const json g = read_json(tmp + "/gt/summary.json");
  const json& all = g["buckets"]["clean"]["base"]["all"];
  EXPECT_EQ(all["n"], 5);
  EXPECT_EQ(all["iou_mean"], 1.0);
  EXPECT_EQ(all["fscore_1cm"], 1.0);
  EXPECT_EQ(all["fscore_2cm"], 1.0);
  EXPECT_EQ(all["scale_err_pct_median"], 0.0);
  EXPECT_EQ(all["trans_err_median"], 0.0);
  EXPECT_LT(all["chamfer_mean"].get<double>(), 1e-12);  // a few ulps of coordinates below 10 m
  EXPECT_LT(all["rot_err_deg_median"].get<double>(), 1e-5);  // acos near 1 (ShapeMetrics.GroundTruthAsPredictionIsPerfect)
  // The GT sizes follow the files' units (world::make_external_shape's guess): 12 cm written in cm, 9 cm
  // in mm, 15 cm in m, 10 cm in cm, 20 cm in m. The PLY, STL and GLB hold float32 coordinates: a side of
  // 0.2 m is off by up to 0.2 x 2^-24 = 1.2e-8 m; 2e-8.
  const std::map<std::string, double> size{{"box_cm.obj", 0.12},       {"cylinder_mm.stl", 0.09}, {"cone_m.ply", 0.15},
                                           {"l_bracket_cm.obj", 0.10}, {"wedge_m.glb", 0.20}};
  std::set<std::string> sources;
  for (const json& row : g["objects"]) {
    const std::string file = std::filesystem::path(row["source"].get<std::string>()).filename().string();
    sources.insert(file);
    EXPECT_NEAR(row["size_m"].get<double>(), size.at(file), 2e-8) << file;
    EXPECT_TRUE(std::filesystem::exists(tmp + "/gt/" + row["picture"].get<std::string>()));
  }
  EXPECT_EQ(sources.size(), 5u);

  // --oracle grid: no lift; the truth's occupancy at the fixture decoder's grid side, at the true pose.
  // Its shape IoU is 1 (the same voxels), its pose errors 0, its world IoU below 1 (a voxel
  // approximation of the mesh) yet well above chance (the committed meshes are boxes, cones, cylinders).
  // Moved inward by half a voxel (--surface-offset 0.5) the world IoU changes; the settings record it.
  for (const char* off : {"0", "0.5"}) {
    auto [st_o, out_o] = run(eval_cmd(std::string("--oracle grid --surface-offset ") + off +
                                      " --surface-samples 2000 --no-pictures --out " + tmp + "/oracle" + off),
                             tmp + "/oracle" + off + ".log");
    ASSERT_EQ(st_o, 0) << out_o;
    EXPECT_NE(out_o.find(std::string("meshes moved ") + off + " voxels inward"), std::string::npos) << out_o;
    const json o = read_json(tmp + "/oracle" + off + "/summary.json");
    EXPECT_EQ(o["settings"]["oracle"], "grid");
    ASSERT_EQ(o["objects"].size(), 5u);
    for (const json& row : o["objects"]) {
      ASSERT_TRUE(row["ok"].get<bool>()) << row.dump();
      EXPECT_EQ(row["shape_iou"].get<double>(), 1.0) << row["object"];
      EXPECT_LT(row["rot_err_deg"].get<double>(), 1e-5);
      EXPECT_EQ(row["trans_err"].get<double>(), 0.0);
      EXPECT_GT(row["iou"].get<double>(), 0.3) << row["object"];
      EXPECT_LT(row["iou"].get<double>(), 1.0) << row["object"];
    }
  }
  EXPECT_NE(read_json(tmp + "/oracle0/summary.json")["buckets"]["clean"]["base"]["all"]["iou_mean"],
            read_json(tmp + "/oracle0.5/summary.json")["buckets"]["clean"]["base"]["all"]["iou_mean"]);
  // --oracle pose: the fixture model's sampled shapes at the true pose (rotation and translation errors 0;
  // the scale error 0 up to rounding: both canonical meshes have longest side 1 and share the true scale).
  auto [st_p, out_p] = run(eval_cmd("--oracle pose --count 2 --seed 3 --surface-samples 2000 --no-pictures --out " + tmp +
                                    "/oracle_pose"),
                           tmp + "/oracle_pose.log");
  ASSERT_EQ(st_p, 0) << out_p;
  const json op = read_json(tmp + "/oracle_pose/summary.json");
  EXPECT_EQ(op["settings"]["oracle"], "pose");
  int scored = 0;
  for (const json& row : op["objects"]) {
    if (!row["ok"].get<bool>()) continue;
    ++scored;
    EXPECT_LT(row["rot_err_deg"].get<double>(), 1e-5) << row["object"];
    EXPECT_EQ(row["trans_err"].get<double>(), 0.0) << row["object"];
    EXPECT_LT(row["scale_err_pct"].get<double>(), 1e-9) << row["object"];
  }
  EXPECT_GT(scored, 0);  // both fixture lifts decode to a shape (seed 3)

  // Two objects lifted from clean and corrupted depth with the small fixture models.
  auto [st, out] = run(eval_cmd("--count 2 --depth both --seed 3 --surface-samples 2000 --out " + tmp + "/a"),
                       tmp + "/a.log");
  ASSERT_EQ(st, 0) << out;
  EXPECT_NE(out.find("RANDOM WEIGHTS"), std::string::npos);
  const json s = read_json(tmp + "/a/summary.json");
  EXPECT_EQ(s["settings"]["depth"], json({"clean", "corrupted"}));
  ASSERT_EQ(s["objects"].size(), 4u);  // 2 objects x 2 depths
  EXPECT_EQ(s["buckets"]["corrupted"]["base"]["all"]["n"], 2);
  for (const json& row : s["objects"]) {
    if (!row["ok"].get<bool>()) {
      EXPECT_NE(row["error"].get<std::string>().find(row["object"].get<std::string>()), std::string::npos) << row.dump();
      continue;
    }
    for (const char* k : {"iou", "fscore_1cm", "fscore_2cm", "precision_2cm", "recall_2cm"}) {
      EXPECT_GE(row[k].get<double>(), 0.0) << k;
      EXPECT_LE(row[k].get<double>(), 1.0) << k;
    }
    EXPECT_LE(row["fscore_1cm"].get<double>(), row["fscore_2cm"].get<double>());  // a 1 cm hit is a 2 cm hit
    EXPECT_GE(row["chamfer"].get<double>(), 0.0);
    EXPECT_TRUE(std::isfinite(row["chamfer"].get<double>()));
    EXPECT_GE(row["rot_err_deg"].get<double>(), 0.0);
    EXPECT_LE(row["rot_err_deg"].get<double>(), 180.0);
    EXPECT_GE(row["scale_err_pct"].get<double>(), 0.0);
    EXPECT_GE(row["trans_err"].get<double>(), 0.0);
    EXPECT_TRUE(std::filesystem::exists(tmp + "/a/" + row["picture"].get<std::string>()));
  }

  // Base against base + the fixture adapter, clean depth: deltas with their intervals, and the base rows
  // are the first run's (the same objects, placements and noise with and without a second model).
  const std::string adapter = simu::testing::shared_dir() + "/fixtures/lora_small";
  auto [st2, out2] = run(eval_cmd("--count 2 --seed 3 --surface-samples 2000 --no-pictures --compare-adapter " +
                                  adapter + " --out " + tmp + "/b"),
                         tmp + "/b.log");
  ASSERT_EQ(st2, 0) << out2;
  const json s2 = read_json(tmp + "/b/summary.json");
  ASSERT_EQ(s2["objects"].size(), 4u);  // 2 objects x 2 models
  const json& d = s2["deltas"]["clean"]["all"]["iou_mean"];
  EXPECT_EQ(d["resamples"], 10000);
  EXPECT_LE(d["ci95"][0].get<double>(), d["ci95"][1].get<double>());
  int matched = 0;
  for (const json& row : s["objects"]) {
    if (row["depth"] != "clean") continue;
    for (const json& row2 : s2["objects"])
      if (row2["object"] == row["object"] && row2["model"] == "base") {
        ++matched;
        EXPECT_EQ(row2.value("chamfer", -1.0), row.value("chamfer", -1.0)) << row["object"];
        EXPECT_EQ(row2.value("rot_err_deg", -1.0), row.value("rot_err_deg", -1.0)) << row["object"];
      }
  }
  EXPECT_EQ(matched, 2);

  // Best of 3 samples (--select render-compare after --align simuscene): every scored row lists its three
  // samples' scores and keeps the lowest (the first of equal ones); the settings say so.
  auto [st3, out3] = run(eval_cmd("--count 2 --seed 3 --samples 3 --select render-compare --align simuscene "
                                  "--surface-samples 2000 --no-pictures --out " + tmp + "/sel"),
                         tmp + "/sel.log");
  ASSERT_EQ(st3, 0) << out3;
  const json s3 = read_json(tmp + "/sel/summary.json");
  EXPECT_EQ(s3["settings"]["select"], "render-compare");
  int selected = 0;
  for (const json& row : s3["objects"]) {
    if (!row["ok"].get<bool>()) continue;
    ASSERT_EQ(row["sample_scores"].size(), 3u) << row.dump();
    const int k = row["sample"].get<int>();
    int best = -1;
    for (int i = 0; i < 3; ++i) {
      const json& v = row["sample_scores"][i];
      if (!v.is_null() && (best < 0 || v.get<double>() < row["sample_scores"][best].get<double>())) best = i;
    }
    EXPECT_EQ(k, best) << row.dump();
    ++selected;
  }
  EXPECT_GT(selected, 0);

  // Errors name the flag or the folder; an existing --out is refused.
  auto [e1, o1] = run(eval_cmd("--out " + tmp + "/a"), tmp + "/e1.log");
  EXPECT_EQ(e1, 1);
  EXPECT_NE(o1.find("--overwrite"), std::string::npos) << o1;
  auto [e2, o2] = run(eval_cmd("--visible 70-40 --out " + tmp + "/d"), tmp + "/e2.log");
  EXPECT_EQ(e2, 1);
  EXPECT_NE(o2.find("--visible"), std::string::npos) << o2;
  auto [e3, o3] = run(simu::testing::build_dir() + "/eval_lift --objects " + tmp + "/none --out " + tmp + "/e", tmp + "/e3.log");
  EXPECT_EQ(e3, 1);
  EXPECT_NE(o3.find(tmp + "/none"), std::string::npos) << o3;
  auto [e4, o4] = run(simu::testing::build_dir() + "/eval_lift --help", tmp + "/e4.log");
  EXPECT_EQ(e4, 0);
  EXPECT_NE(o4.find("--compare-adapter"), std::string::npos);
  EXPECT_EQ(o4.find("--gt-as-prediction"), std::string::npos);  // hidden
}
#endif
