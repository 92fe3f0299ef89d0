// Tests the `lift` program end to end on the CPU with the small fixture models (resample/lift.h):
// a generated photo with two objects (one cut by the image border), depth as a 16-bit PNG + K JSON,
// or a MoGe-style point map with +inf holes; the outputs opened with the tools users open them in
// (assimp for GLB/OBJ, numpy for the occupancy, the probe's scene reader and the probe itself) and
// the two pose conventions checked against each other by independent math; the bad-input paths
// (missing weights, unreadable files, per-object errors, existing output directory).
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <torch/torch.h>

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include <cstdlib>
#include <filesystem>
#include <fstream>

#include "common/error.h"
#include "common/fs.h"
#include "data/depth_io.h"
#include "data/safetensors.h"
#include "models/generator.h"
#include "models/ss_decoder.h"
#include "pipeline/resample/lift.h"
#include "pipeline/physics/mesh.h"
#include "pipeline/physics/scene.h"
#include "test_util.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

namespace sp = simu::resample;
namespace sph = simu::physics;
using json = nlohmann::json;

namespace {

constexpr int kW = 160, kH = 120;
constexpr double kF = 150, kCx = 80, kCy = 60;

// Runs a command, output to `log`; returns its exit status and the output.
std::pair<int, std::string> run(const std::string& cmd, const std::string& log) {
  const int st = std::system((cmd + " > " + log + " 2>&1").c_str());
  std::ifstream f(log);
  std::string out((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  return {WIFEXITED(st) ? WEXITSTATUS(st) : -1, out};
}

json read_json(const std::string& path) { return json::parse(simu::fs::read_file(path)); }

#ifdef SIMU_HAVE_OPENCV
// The photo: a wall at 2 m; object 1 a box at 1.2 m inside the frame; object 2 at 1.5 m cut by the left
// border. Writes rgb.png, depth.png (mm), K.json, labels.png, per-object masks and a MoGe-style point map.
struct Photo {
  std::string dir, rgb, depth, K, labels, pointmap, masks_dir;
};
Photo make_photo(const std::string& dir) {
  Photo p{dir, dir + "/rgb.png", dir + "/depth.png", dir + "/K.json", dir + "/labels.png", dir + "/points.npy",
          dir + "/masks"};
  cv::Mat rgb(kH, kW, CV_8UC3, cv::Scalar(90, 110, 130)), depth(kH, kW, CV_16UC1, cv::Scalar(2000)),
      labels(kH, kW, CV_8UC1, cv::Scalar(0));
  for (int r = 0; r < kH; ++r)
    for (int c = 0; c < kW; ++c) {
      rgb.at<cv::Vec3b>(r, c) = cv::Vec3b(static_cast<uint8_t>(60 + r), static_cast<uint8_t>(40 + c), 120);
      if (c >= 60 && c < 100 && r >= 40 && r < 80) {  // object 1
        labels.at<uint8_t>(r, c) = 1;
        depth.at<uint16_t>(r, c) = 1200;
        rgb.at<cv::Vec3b>(r, c) = cv::Vec3b(30, 200, static_cast<uint8_t>(2 * c));
      }
      if (c < 30 && r >= 60 && r < 110) {  // object 2, touches the left border
        labels.at<uint8_t>(r, c) = 2;
        depth.at<uint16_t>(r, c) = 1500;
        rgb.at<cv::Vec3b>(r, c) = cv::Vec3b(200, 40, static_cast<uint8_t>(3 * r));
      }
    }
  EXPECT_TRUE(cv::imwrite(p.rgb, rgb));
  EXPECT_TRUE(cv::imwrite(p.depth, depth));
  EXPECT_TRUE(cv::imwrite(p.labels, labels));
  std::ofstream(p.K) << R"({"fx": 150, "fy": 150, "cx": 80, "cy": 60})";
  // Per-object masks, plus the bad ones: empty, wrong size, over a region without valid points.
  std::filesystem::create_directories(p.masks_dir);
  EXPECT_TRUE(cv::imwrite(p.masks_dir + "/a_box.png", (labels == 1)));
  EXPECT_TRUE(cv::imwrite(p.masks_dir + "/b_border.png", (labels == 2)));
  EXPECT_TRUE(cv::imwrite(p.masks_dir + "/c_empty.png", cv::Mat(kH, kW, CV_8UC1, cv::Scalar(0))));
  EXPECT_TRUE(cv::imwrite(p.masks_dir + "/d_wrongsize.png", cv::Mat(kH / 2, kW, CV_8UC1, cv::Scalar(255))));
  cv::Mat hole(kH, kW, CV_8UC1, cv::Scalar(0));
  hole(cv::Rect(120, 10, 30, 20)).setTo(255);
  EXPECT_TRUE(cv::imwrite(p.masks_dir + "/e_nodepth.png", hole));
  // MoGe-style point map of the same scene: OpenCV camera, +inf where the "hole" is.
  auto z = torch::from_blob(depth.ptr<uint16_t>(), {kH, kW}, torch::kInt16).to(torch::kFloat32) * 1e-3f;
  auto pm = simu::data::unproject_depth(z, {kF, kF, kCx, kCy});  // [H, W, 3]
  pm.slice(0, 10, 30).slice(1, 120, 150).fill_(INFINITY);
  simu::data::write_npy(p.pointmap, pm);
  return p;
}
#endif

// The occupancy grid's side: the fixture generator's shape grid times its decoder's upsampling.
int64_t fixture_resolution() {
  const auto g = simu::models::GeneratorConfig::from_official_file(simu::testing::fixture("ss_generator_small.json"));
  const auto d = simu::models::load_ss_decoder(simu::testing::fixture("ss_decoder_small.json"), "");
  return g.backbone.latent("shape").resolution * d->config().upsample_factor();
}

// The fixture decoder with random weights occupies no voxel: a copy whose output layer is 0 * x + 2
// occupies the whole grid (every shape then meshes to the canonical cube; poses still come from the
// sampled latents).
std::string full_decoder(const std::string& dir) {
  auto w = simu::data::load_safetensors(simu::testing::fixture("ss_decoder_small.safetensors"));
  EXPECT_TRUE(w.count("out_layer.2.weight") && w.count("out_layer.2.bias"));
  w["out_layer.2.weight"] = torch::zeros_like(w["out_layer.2.weight"]);
  w["out_layer.2.bias"] = torch::full_like(w["out_layer.2.bias"], 2.0);
  const std::string path = dir + "/ss_decoder_full.safetensors";
  simu::data::save_safetensors(path, w);
  return path;
}

// The lift command with the small fixture models (embedder: demo size, random init).
std::string lift_cmd(const std::string& decoder_weights) {
  const auto fix = [](const std::string& n) { return simu::testing::fixture(n); };
  return simu::testing::build_dir() + "/lift --device cpu --seed 3" +
         " --generator-config " + fix("ss_generator_small.json") + " --generator-weights " +
         fix("ss_generator_small.safetensors") + " --decoder-config " + fix("ss_decoder_small.json") +
         " --decoder-weights " + decoder_weights + " --embedder-config " + simu::testing::source_dir() +
         "/configs/demo_embedder_small.json";
}

Eigen::Matrix3d mat(const json& rows) {
  Eigen::Matrix3d m;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) m(r, c) = rows.at(r).at(c).get<double>();
  return m;
}
Eigen::Vector3d vec(const json& v) { return {v.at(0).get<double>(), v.at(1).get<double>(), v.at(2).get<double>()}; }

// Orthonormality error of a rotation decoded in fp32 from a sampled 6-D latent (tests/tolerance.h):
// Gram-Schmidt's ~20 roundings over the sine of the angle between the latent's two vectors, taken
// >= 0.05 (3 degrees: two random directions come that close with probability ~1e-3), plus a 3-term
// product. pose.json does not carry the latent, so the angle is an assumption here, not a measurement.
const double kRotation = simu::testing::gamma(20) / 0.05 + simu::testing::gamma(3);
// A unit quaternion extracted from that matrix in fp32 (~7 roundings per component, a division by
// 2 |q_i| >= 1), and its matrix written out again here: both ways.
const double kQuaternion = kRotation + 4 * simu::testing::gamma(7);

// Checks one lifted object's files: meshes through assimp, occupancy, both pose conventions.
void check_object_files(const std::string& out, const json& rep, int64_t resolution) {
  SCOPED_TRACE(rep.dump());
  ASSERT_TRUE(rep.at("ok").get<bool>());
  const std::string sdir = out + "/" + rep.at("samples").at(0).at("dir").get<std::string>();
  // Meshes: GLB and OBJ load through assimp and agree (canonical frame: AABB-centred, longest side 1).
  const auto glb = sph::read_mesh(sdir + "/mesh.glb");
  const auto obj = sph::read_mesh(sdir + "/mesh.obj");
  ASSERT_GT(glb.F.rows(), 0);
  EXPECT_EQ(glb.V.rows(), obj.V.rows());
  EXPECT_EQ(glb.F.rows(), obj.F.rows());
  // The files hold fp32 vertices (|c| <= 0.5): one rounding each, for the extent's two ends.
  const auto box = sph::mesh_aabb(obj);
  EXPECT_NEAR(box.size().maxCoeff(), 1.0, simu::testing::gamma(1));
  EXPECT_LT(box.center().norm(), std::sqrt(3.0) * simu::testing::gamma(1));
  // Occupancy: uint8 [R, R, R]; the fixture-made decoder occupies every voxel.
  const auto occ = simu::data::read_npy(sdir + "/occupancy.npy");
  EXPECT_EQ(occ.scalar_type(), torch::kUInt8);
  EXPECT_EQ(occ.sizes(), (std::vector<int64_t>{resolution, resolution, resolution}));
  EXPECT_EQ(occ.sum().item<int64_t>(), resolution * resolution * resolution);
  // Poses: SAM 3D's (quaternion, row vectors, PyTorch3D camera, voxel frame) and the scene's
  // (R, s, t on canonical vertices, OpenCV camera) must place every mesh vertex at the same point.
  const auto pose = read_json(sdir + "/pose.json");
  const auto& s3 = pose.at("sam3d");
  const auto q = s3.at("rotation_wxyz");
  const double w = q.at(0), x = q.at(1), y = q.at(2), z = q.at(3);
  EXPECT_NEAR(w * w + x * x + y * y + z * z, 1.0, 2 * kQuaternion);
  // Quaternion -> matrix (Hamilton, w first), written out by hand.
  Eigen::Matrix3d Rq;
  Rq << 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y), 2 * (x * y + w * z), 1 - 2 * (x * x + z * z),
      2 * (y * z - w * x), 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y);
  const Eigen::Vector3d T = vec(s3.at("translation")), S = vec(s3.at("scale"));
  const Eigen::Vector3d centre = vec(pose.at("canonical").at("centre"));
  const double factor = pose.at("canonical").at("factor");
  const Eigen::Matrix3d R = mat(pose.at("scene").at("R"));
  const Eigen::Vector3d t = vec(pose.at("scene").at("t")), s = vec(pose.at("scene").at("scale"));
  for (const auto& v : {R.array().isFinite().all(), t.array().isFinite().all(), s.array().isFinite().all(),
                        T.array().isFinite().all(), S.array().isFinite().all()})
    EXPECT_TRUE(v);
  EXPECT_LT((R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff(), kRotation);
  EXPECT_NEAR(R.determinant(), 1.0, 3 * kRotation);
  double worst = 0, extent = 0;
  for (int i = 0; i < obj.V.rows(); ++i) {
    const Eigen::Vector3d c = obj.V.row(i).transpose();
    const Eigen::Vector3d v = c / factor + centre;                          // voxel frame
    const Eigen::RowVector3d p_row = S.cwiseProduct(v).transpose() * Rq + T.transpose();  // PyTorch3D camera
    const Eigen::Vector3d p_cv(-p_row(0), -p_row(1), p_row(2));            // OpenCV camera = scene world
    const Eigen::Vector3d p_scene = R * s.cwiseProduct(c) + t;
    worst = std::max(worst, (p_cv - p_scene).norm());
    extent = std::max(extent, p_cv.norm());
    // The voxel frame of the mesh lies within the occupancy grid's cube (half a voxel of MC bevel),
    // up to the fp32 storage of c and the float64 return to the voxel frame.
    EXPECT_LE(v.cwiseAbs().maxCoeff(), 0.5 + 1.0 / resolution + simu::testing::gamma(3));
  }
  // The quaternion's matrix and the scene's R come from one fp32 rotation (kQuaternion between them),
  // on points up to the extent, plus float64 arithmetic.
  EXPECT_LT(worst, (kQuaternion + simu::testing::gamma(16, simu::testing::kFp64Unit)) * std::max(1.0, extent))
      << "the two pose conventions disagree";
}

}  // namespace

#ifdef SIMU_HAVE_OPENCV
// Depth PNG + K + label PNG: both objects lifted, every output file opened, probe loads and runs scene.json.
TEST(LiftCli, EndToEndDepthAndLabels) {
  const auto dir = simu::testing::temp_dir("lift_e2e");
  const auto photo = make_photo(dir);
  const auto dec = full_decoder(dir);
  const std::string out = dir + "/out";
  const auto [rc, log] = run(lift_cmd(dec) + " --image " + photo.rgb + " --masks " + photo.labels + " --depth " +
                                 photo.depth + " --intrinsics " + photo.K + " --out " + out + " --random-weights",
                             dir + "/lift.log");
  ASSERT_EQ(rc, 0) << log;
  // Random weights: the banner is on screen and in the report.
  EXPECT_NE(log.find("RANDOM WEIGHTS: no --embedder-weights"), std::string::npos) << log;
  const auto report = read_json(out + "/report.json");
  EXPECT_NE(report.at("warning").get<std::string>().find("RANDOM WEIGHTS"), std::string::npos);
  EXPECT_EQ(report.at("run").at("sampler").at("steps"), 25);  // the released inference settings
  EXPECT_EQ(report.at("run").at("sampler").at("cfg_strength"), 7.0);
  ASSERT_EQ(report.at("objects").size(), 2u);
  EXPECT_EQ(report.at("failed"), 0);
  EXPECT_EQ(report.at("sampling_calls"), 1);  // both objects in one batched call
  // Object 2 touches the border: its crop box leaves the image.
  const auto& o1 = report.at("objects").at(0);
  const auto& o2 = report.at("objects").at(1);
  EXPECT_EQ(o1.at("id"), "label_1");
  EXPECT_EQ(o2.at("id"), "label_2");
  EXPECT_GE(o1.at("crop_box").at("x1").get<int>(), 0);
  EXPECT_LT(o2.at("crop_box").at("x1").get<int>(), 0);
  for (const auto& o : report.at("objects")) check_object_files(out, o, fixture_resolution());
  // The scene file: the probe's reader loads it, poses equal pose.json's scene block.
  const auto scene = sph::load_scene(out + "/scene.json");
  ASSERT_EQ(scene.objects.size(), 2u);
  EXPECT_TRUE(scene.camera.valid());
  EXPECT_EQ(scene.camera.fx, kF);
  EXPECT_EQ(scene.camera.width, kW);
  for (size_t i = 0; i < 2; ++i) {
    const auto& so = scene.objects[i];
    EXPECT_TRUE(so.error.empty()) << so.error;
    EXPECT_TRUE(std::filesystem::exists(so.mesh_path)) << so.mesh_path;
    EXPECT_TRUE(std::filesystem::exists(so.mask_path)) << so.mask_path;
    const auto pose = read_json(out + "/" + report.at("objects").at(i).at("samples").at(0).at("dir").get<std::string>() +
                                "/pose.json");
    // (the scene reader projects R onto the nearest rotation: it moves by R's orthonormality error)
    EXPECT_LT((so.R - mat(pose.at("scene").at("R"))).cwiseAbs().maxCoeff(), kRotation);
    // t: a float64 JSON round trip (17 digits: exact) and the reader's float64 arithmetic.
    const Eigen::Vector3d t_file = vec(pose.at("scene").at("t"));
    EXPECT_LT((so.t - t_file).cwiseAbs().maxCoeff(), simu::testing::gamma(8, simu::testing::kFp64Unit) * (1 + t_file.norm()));
  }
  // Numpy opens the occupancy as uint8 [R, R, R].
  const std::string occ = out + "/" + o1.at("samples").at(0).at("dir").get<std::string>() + "/occupancy.npy";
  const int64_t R = fixture_resolution();
  const auto [prc, plog] = run(simu::testing::python_exe() + " -c \"import numpy as np; a = np.load('" + occ +
                                   "'); assert a.dtype == np.uint8 and a.shape == (" + std::to_string(R) + ", " +
                                   std::to_string(R) + ", " + std::to_string(R) + "), (a.dtype, a.shape)\"",
                               dir + "/numpy.log");
  EXPECT_EQ(prc, 0) << plog;
  // The probe reads scene.json directly and runs on it.
  const auto [qrc, qlog] = run(simu::testing::build_dir() + "/probe --scene " + out + "/scene.json --out " + dir +
                                   "/probe --no-coacd --set final.settle_time=0.2 --set evaluation.settle_time=0.2 --cache-dir " + dir + "/hulls",
                               dir + "/probe.log");
  EXPECT_EQ(qrc, 0) << qlog;
  EXPECT_TRUE(std::filesystem::exists(dir + "/probe/scene.xml")) << qlog;
  // probe --resample on a scene whose depth file is missing: an error naming the file, exit 1.
  {
    auto sj = read_json(out + "/scene.json");
    EXPECT_EQ(sj.at("depth").get<std::string>(), photo.depth);  // lift records its geometry input
    sj["depth"] = dir + "/gone.png";
    std::ofstream(dir + "/bad_scene.json") << sj.dump();
    // (mesh paths are relative to the scene file: put it beside the outputs)
    std::filesystem::copy_file(dir + "/bad_scene.json", out + "/bad_scene.json");
    const auto fix = [](const std::string& n) { return simu::testing::fixture(n); };
    const auto [brc, blog] =
        run(simu::testing::build_dir() + "/probe --scene " + out + "/bad_scene.json --out " + dir +
                "/probe_bad --no-coacd --resample --device cpu --generator-config " + fix("ss_generator_small.json") +
                " --generator-weights " + fix("ss_generator_small.safetensors") + " --decoder-config " +
                fix("ss_decoder_small.json") + " --decoder-weights " + dec + " --embedder-config " +
                simu::testing::source_dir() + "/configs/demo_embedder_small.json --random-weights",
            dir + "/probe_bad.log");
    EXPECT_EQ(brc, 1) << blog;
    EXPECT_NE(blog.find(dir + "/gone.png: the scene's depth file is not found"), std::string::npos) << blog;
    std::filesystem::remove(out + "/bad_scene.json");
  }
  // The output directory exists now: refused without --overwrite, replaced with it.
  const auto [rc2, log2] = run(lift_cmd(dec) + " --image " + photo.rgb + " --masks " + photo.labels + " --depth " +
                                   photo.depth + " --intrinsics " + photo.K + " --out " + out + " --random-weights",
                               dir + "/lift2.log");
  EXPECT_NE(rc2, 0);
  EXPECT_NE(log2.find(out + ": output directory exists"), std::string::npos) << log2;
  EXPECT_NE(log2.find("--overwrite"), std::string::npos) << log2;
  simu::fs::remove_tree(dir);
}

// MoGe point map (+inf holes, no K: fitted) + a directory of per-object masks with three bad ones:
// the good objects are written, the bad ones are named in the report, exit status 1. The sampler
// options given (--steps, --cfg-strength) are the ones the sampler runs with and the report records.
TEST(LiftCli, PointMapPerObjectMasksAndBadObjects) {
  const auto dir = simu::testing::temp_dir("lift_bad");
  const auto photo = make_photo(dir);
  const auto dec = full_decoder(dir);
  const std::string out = dir + "/out";
  std::filesystem::create_directories(out);  // exists: --overwrite replaces it
  std::ofstream(out + "/stale.txt") << "old run";
  const auto [rc, log] = run(lift_cmd(dec) + " --image " + photo.rgb + " --masks " + photo.masks_dir + " --pointmap " +
                                 photo.pointmap + " --out " + out + " --random-weights --overwrite --samples 2 --steps 4 --cfg-strength 2.5",
                             dir + "/lift.log");
  EXPECT_EQ(rc, 1) << log;
  // The sampler's own description (models::describe_sampler of the options it samples with).
  EXPECT_NE(log.find("steps 4"), std::string::npos) << log;
  EXPECT_NE(log.find("cfg 2.5 on"), std::string::npos) << log;
  EXPECT_FALSE(std::filesystem::exists(out + "/stale.txt"));
  const auto report = read_json(out + "/report.json");
  std::map<std::string, json> by_id;
  for (const auto& o : report.at("objects")) by_id[o.at("id").get<std::string>()] = o;
  ASSERT_EQ(by_id.size(), 5u) << report.dump(1);
  EXPECT_EQ(report.at("failed"), 3);
  EXPECT_EQ(report.at("run").at("sampler").at("steps"), 4);
  EXPECT_EQ(report.at("run").at("sampler").at("cfg_strength"), 2.5);
  for (const char* good : {"a_box", "b_border"}) {
    ASSERT_TRUE(by_id[good].at("ok").get<bool>()) << by_id[good].dump();
    EXPECT_EQ(by_id[good].at("samples").size(), 2u);
    check_object_files(out, by_id[good], fixture_resolution());
  }
  const std::map<std::string, std::string> want = {{"c_empty", "the mask is empty"},
                                                   {"d_wrongsize", "mask is 160x60 (W x H) but the image is 160x120"},
                                                   {"e_nodepth", "no valid point under its mask"}};
  for (const auto& [id, msg] : want) {
    const auto& o = by_id[id];
    EXPECT_FALSE(o.at("ok").get<bool>());
    const std::string err = o.at("error");
    EXPECT_NE(err.find("object '" + id + "'"), std::string::npos) << err;
    EXPECT_NE(err.find(msg), std::string::npos) << err;
    EXPECT_NE(log.find("object '" + id + "'"), std::string::npos) << "not on screen: " << id;
  }
  // K fitted to the point map equals the one it was made with.
  const auto scene = sph::load_scene(out + "/scene.json");
  EXPECT_EQ(scene.objects.size(), 2u);
  // Least squares of the pixel against r = x/z from the fp32 point map unprojected with K: each r
  // within gamma(4) |r| <= 1.3e-7 (|r| <= 80 / 150); f moves by at most f max|dr| / std(r) = 6e-5, the
  // centre by that times |mean r| plus f max|dr| (2e-5): 1e-3 px is 16 times the bound.
  EXPECT_NEAR(scene.camera.fx, kF, 1e-3);
  EXPECT_NEAR(scene.camera.cy, kCy, 1e-3);
  simu::fs::remove_tree(dir);
}

// Whole-run input errors name the flag or the file, before any model is loaded.
TEST(LiftCli, BadInputsNameFlagOrFile) {
  const auto dir = simu::testing::temp_dir("lift_inputs");
  const auto photo = make_photo(dir);
  const auto fix = [](const std::string& n) { return simu::testing::fixture(n); };
  const std::string base = simu::testing::build_dir() + "/lift --device cpu --embedder-config " +
                           simu::testing::source_dir() + "/configs/demo_embedder_small.json --generator-config " +
                           fix("ss_generator_small.json") + " --decoder-config " + fix("ss_decoder_small.json");
  const std::string good_in = " --image " + photo.rgb + " --masks " + photo.labels + " --depth " + photo.depth +
                              " --intrinsics " + photo.K + " --out " + dir + "/out";
  struct Case {
    std::string args, want;
  };
  const std::vector<Case> cases = {
      {good_in, "--generator-weights is missing"},
      {good_in + " --generator-weights " + fix("ss_generator_small.safetensors") + " --decoder-weights " +
           fix("ss_decoder_small.safetensors"),
       "--embedder-weights is missing"},
      {good_in + " --generator-weights " + dir + "/nope.safetensors --random-weights",
       dir + "/nope.safetensors: weight file not found (--generator-weights)"},
      {" --random-weights --image " + photo.rgb + " --masks " + photo.labels + " --depth " + dir +
           "/missing.png --intrinsics " + photo.K + " --out " + dir + "/out",
       dir + "/missing.png: depth file not found"},
      {" --random-weights --image " + dir + "/K.json --masks " + photo.labels + " --depth " + photo.depth +
           " --intrinsics " + photo.K + " --out " + dir + "/out",
       dir + "/K.json"},
      {" --random-weights --image " + photo.rgb + " --masks " + photo.labels + " --depth " + photo.depth + " --out " +
           dir + "/out",
       "needs the camera intrinsics"},
      {" --random-weights --image " + photo.rgb + " --masks " + dir + "/nolabels.png --pointmap " + photo.pointmap +
           " --out " + dir + "/out",
       dir + "/nolabels.png: label image not found"},
      {good_in + " --random-weights --precision fp8", "--precision must be"},
  };
  for (size_t i = 0; i < cases.size(); ++i) {
    const auto [rc, log] = run(base + cases[i].args, dir + "/case.log");
    EXPECT_NE(rc, 0) << "case " << i << ": " << log;
    EXPECT_NE(log.find(cases[i].want), std::string::npos) << "case " << i << ": want '" << cases[i].want << "' in:\n" << log;
    EXPECT_FALSE(std::filesystem::exists(dir + "/out")) << "case " << i;
  }
  simu::fs::remove_tree(dir);
}
#endif

// The SAM 3D -> scene conversion against a hand-built case: camera moved and turned in the world.
TEST(Lift, ScenePoseFromSam3dIndependentMath) {
  sph::Camera cam;
  cam.R_world_cam = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  cam.t_world_cam = Eigen::Vector3d(0.5, -1, 2);
  const Eigen::Matrix3d rot = Eigen::AngleAxisd(-1.1, Eigen::Vector3d(0.3, -1, 0.2).normalized()).toRotationMatrix();
  const Eigen::Vector3d s(0.2, 0.3, 0.25), tc(0.1, -0.2, 1.7);
  const auto p = sp::scene_pose_from_sam3d(rot, s, tc, cam);
  for (const Eigen::Vector3d c : {Eigen::Vector3d(0.5, 0.1, -0.3), Eigen::Vector3d(-0.2, 0.4, 0.0)}) {
    // PyTorch3D camera point -> OpenCV camera (negate x, y) -> world.
    Eigen::Vector3d p3d = rot * s.cwiseProduct(c) + tc;
    const Eigen::Vector3d cv_pt(-p3d.x(), -p3d.y(), p3d.z());
    const Eigen::Vector3d world = cam.R_world_cam * cv_pt + cam.t_world_cam;
    // Two float64 paths of ~20 operations on values up to |world| ~ 3.
    EXPECT_LT((p.R * p.scale.cwiseProduct(c) + p.t - world).norm(), 3 * simu::testing::two_paths(20, simu::testing::kFp64Unit));
  }
  // A product of rotations in float64: ~20 roundings.
  EXPECT_NEAR(p.R.determinant(), 1.0, simu::testing::gamma(20, simu::testing::kFp64Unit));
}

// Occupancy grid from voxel coordinates.
TEST(Lift, OccupancyGrid) {
  const auto g = sp::occupancy_grid(torch::tensor({{0, 1, 2}, {3, 3, 3}}, torch::kInt32), 4);
  EXPECT_EQ(g.sum().item<int64_t>(), 2);
  EXPECT_EQ(g[0][1][2].item<uint8_t>(), 1);
  EXPECT_EQ(g[3][3][3].item<uint8_t>(), 1);
  EXPECT_THROW(sp::occupancy_grid(torch::tensor({{0, 1, 4}}, torch::kInt32), 4), simu::Error);
}
