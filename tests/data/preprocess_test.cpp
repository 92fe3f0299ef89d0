// Stage-1 condition preprocessing: real image + mask files (drawn with OpenCV, written to disk, read
// back) through preprocess and the condition embedder, checked against expectations computed here
// by hand from the documented algorithm (crop box, padding, token counts, normalised ranges).
#include <algorithm>
#include <array>
#include <cstdio>
#include <filesystem>
#include <cmath>
#include <vector>

#include "common/error.h"
#include "data/preprocess.h"
#include "models/cond_embedder.h"
#include "models/pose.h"
#include "data/safetensors.h"
#include "common/config.h"
#include "models/weights.h"
#include "test_util.h"

#include <fstream>
#include <nlohmann/json.hpp>

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#endif

namespace sd = simu::data;

namespace {

// Scene: 320 x 240 image, grey-blue gradient background, a red filled rectangle x 100..199,
// y 60..119 (inclusive) = the object, and a green disc elsewhere (not in the mask).
constexpr int kW = 320, kH = 240;
constexpr int kX0 = 100, kX1 = 199, kY0 = 60, kY1 = 119;

// Synthetic camera-space point map: plane z = 2 + 0.01 u, pinhole f = 300, centre (160, 120);
// columns 180..184 of the object have no depth (NaN).
torch::Tensor make_pointmap() {
  auto pm = torch::empty({3, kH, kW});
  auto a = pm.accessor<float, 3>();
  for (int v = 0; v < kH; ++v)
    for (int u = 0; u < kW; ++u) {
      const float z = 2.0f + 0.01f * u;
      a[0][v][u] = (u - 160.0f) / 300.0f * z;
      a[1][v][u] = (v - 120.0f) / 300.0f * z;
      a[2][v][u] = z;
      if (u >= 180 && u <= 184 && v >= kY0 && v <= kY1) a[0][v][u] = a[1][v][u] = a[2][v][u] = NAN;
    }
  return pm;
}

// torch.nanmedian semantics: lower median of the non-NaN values.
double lower_median(std::vector<double> v) {
  v.erase(std::remove_if(v.begin(), v.end(), [](double x) { return std::isnan(x); }), v.end());
  std::sort(v.begin(), v.end());
  return v[(v.size() - 1) / 2];
}

#ifdef SIMU_HAVE_OPENCV
struct SceneFiles {
  std::string image, mask, crop_mask;
};

SceneFiles write_scene(const std::string& dir) {
  cv::Mat img(kH, kW, CV_8UC3);
  for (int v = 0; v < kH; ++v)
    for (int u = 0; u < kW; ++u) img.at<cv::Vec3b>(v, u) = cv::Vec3b(static_cast<uchar>(100 + u / 4), 90, 80);  // BGR
  cv::rectangle(img, cv::Point(kX0, kY0), cv::Point(kX1, kY1), cv::Scalar(0, 0, 255), cv::FILLED);
  cv::circle(img, cv::Point(260, 190), 25, cv::Scalar(0, 255, 0), cv::FILLED);
  cv::Mat mask = cv::Mat::zeros(kH, kW, CV_8UC1);
  cv::rectangle(mask, cv::Point(kX0, kY0), cv::Point(kX1, kY1), cv::Scalar(255), cv::FILLED);
  // Auxiliary (amodal) crop mask: the object extended down to y = 179.
  cv::Mat crop = mask.clone();
  cv::rectangle(crop, cv::Point(kX0, kY0), cv::Point(kX1, 179), cv::Scalar(255), cv::FILLED);
  SceneFiles f{dir + "/image.png", dir + "/mask.png", dir + "/crop_mask.png"};
  EXPECT_TRUE(cv::imwrite(f.image, img));
  EXPECT_TRUE(cv::imwrite(f.mask, mask));
  EXPECT_TRUE(cv::imwrite(f.crop_mask, crop));
  return f;
}
#endif

}  // namespace

TEST(Preprocess, ImageMaskPointmapFromDiskThroughEmbedder) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "built without OpenCV";
#else
  const auto files = write_scene(simu::testing::temp_dir("preprocess_scene"));
  const auto pm = make_pointmap();
  // The "default" preset: 518 px, box factor 1.0, padding 0.1, bicubic, background removal.
  const auto cfg = sd::PreprocessConfig::preset_named("default");
  auto out = sd::prepare_condition_inputs_from_files(files.image, files.mask, pm, cfg);

  // Crop box by hand: w = 199-100 = 99, h = 119-60 = 59 -> side int(99 * 1.0) = 99, half 49;
  // centre (149.5, 89.5) -> x [int(100.5), int(198.5)) = [100, 198), y [int(40.5), int(138.5)) = [40, 138).
  EXPECT_EQ(out.crop_box.x1, 100);
  EXPECT_EQ(out.crop_box.x2, 198);
  EXPECT_EQ(out.crop_box.y1, 40);
  EXPECT_EQ(out.crop_box.y2, 138);
  EXPECT_EQ(out.crop_extend, 9);  // int(98 * 0.1)

  // Shapes.
  const std::vector<std::pair<std::string, std::vector<int64_t>>> shapes = {
      {"image", {1, 3, 518, 518}},    {"rgb_image", {1, 3, 518, 518}}, {"mask", {1, 1, 518, 518}},
      {"rgb_image_mask", {1, 1, 518, 518}}, {"pointmap", {1, 3, 518, 518}}, {"rgb_pointmap", {1, 3, 518, 518}}};
  for (const auto& [k, s] : shapes) {
    ASSERT_TRUE(out.tensors.count(k)) << k;
    EXPECT_EQ(out.tensors.at(k).sizes(), torch::IntArrayRef(s)) << k;
  }

  // Cropped mask: binary; the object covers columns [9, 9+98) (cut at the box edge x = 198) and
  // rows [29, 89) of the 116 x 116 padded crop -> area fraction 98*60/116^2.
  auto mask = out.tensors.at("mask");
  EXPECT_TRUE(((mask == 0) | (mask == 1)).all().item<bool>());
  // Nearest resampling moves each edge of the object by at most one output pixel: the fraction by
  // at most 2/518 (98 + 60)/116 = 0.0053.
  EXPECT_NEAR(mask.mean().item<double>(), 98.0 * 60.0 / (116.0 * 116.0), 0.01);
  // Object centre in output pixels: ((9+49) / 116 * 518, (29+30) / 116 * 518) ~ (259, 263).
  EXPECT_EQ(mask[0][0][263][259].item<float>(), 1.f);
  EXPECT_EQ(mask[0][0][5][5].item<float>(), 0.f);

  // Cropped image: background removed (exact zeros far from the object), the object is red.
  auto image = out.tensors.at("image");
  EXPECT_EQ(image[0].slice(1, 0, 100).abs().max().item<float>(), 0.f);  // rows above the object
  // Inside a uniform region (> 2 source pixels from its edge): the bicubic weights of each pass sum to
  // 1; two separable passes of 4 products and sums: gamma(16) of values <= 1, absolute.
  const double interior = simu::testing::gamma(16);
  EXPECT_NEAR(image[0][0][263][259].item<float>(), 1.0, interior);
  EXPECT_NEAR(image[0][1][263][259].item<float>(), 0.0, interior);
  EXPECT_GE(image.min().item<float>(), -0.2f);  // bicubic overshoot only
  EXPECT_LE(image.max().item<float>(), 1.2f);

  // Full image: 320 x 240 padded 40 rows top and bottom -> 320 x 320 -> 518; the padding is black.
  auto rgb = out.tensors.at("rgb_image");
  EXPECT_EQ(rgb[0].slice(1, 0, 60).abs().max().item<float>(), 0.f);  // 40/320*518 = 64.75 rows
  // Red object centre (149.5, 89.5) -> ((89.5+40)/320*518, 149.5/320*518) = (209.6, 242.0).
  EXPECT_NEAR(rgb[0][0][210][242].item<float>(), 1.0, interior);
  auto full_mask = out.tensors.at("rgb_image_mask");
  // Nearest resampling: each edge within one output pixel, 2/518 (100 + 60)/320 = 0.0019.
  EXPECT_NEAR(full_mask.mean().item<double>(), 100.0 * 60.0 / (320.0 * 320.0), 0.005);

  // Point map normalisation: shift = lower median per axis over object pixels with depth, scale =
  // lower median over all pixels of max |p - shift| (computed here with plain loops).
  auto a = pm.accessor<float, 3>();
  std::vector<double> xs, ys, zs;
  for (int v = kY0; v <= kY1; ++v)
    for (int u = kX0; u <= kX1; ++u) xs.push_back(a[0][v][u]), ys.push_back(a[1][v][u]), zs.push_back(a[2][v][u]);
  const double sx = lower_median(xs), sy = lower_median(ys), sz = lower_median(zs);
  std::vector<double> md;
  for (int v = 0; v < kH; ++v)
    for (int u = 0; u < kW; ++u) {
      if (std::isnan(a[2][v][u])) {
        md.push_back(NAN);
        continue;
      }
      md.push_back(std::max({std::abs(a[0][v][u] - sx), std::abs(a[1][v][u] - sy), std::abs(a[2][v][u] - sz)}));
    }
  const double scale = lower_median(md);
  // A lower median is one of the fp32 values themselves: exact.
  EXPECT_EQ(out.pointmap_shift[0].item<double>(), sx);
  EXPECT_EQ(out.pointmap_shift[1].item<double>(), sy);
  EXPECT_EQ(out.pointmap_shift[2].item<double>(), sz);
  // The median of max |p - shift|, each difference rounded once in fp32 (an order statistic moves by
  // no more than its inputs): u of the largest |p| + |shift|, absolute.
  const double p_max = pm.nan_to_num(0).abs().max().item<double>();
  const double s_max = std::max({std::abs(sx), std::abs(sy), std::abs(sz)});
  for (int i = 0; i < 3; ++i)
    EXPECT_NEAR(out.pointmap_scale[i].item<double>(), scale, simu::testing::gamma(1) * (p_max + s_max));

  // Cropped point map: finite only on the object minus the NaN stripe (5 of 98 visible columns);
  // its median z is ~0 after normalisation.
  auto p = out.tensors.at("pointmap")[0];
  auto finite = torch::isfinite(p).all(0);
  // Nearest resampling: the region's edges (and the stripe's two) within one output pixel each.
  EXPECT_NEAR(finite.to(torch::kFloat64).mean().item<double>(), 93.0 * 60.0 / (116.0 * 116.0), 0.01);
  EXPECT_FALSE((finite & (mask[0][0] == 0)).any().item<bool>()) << "valid points only inside the mask";
  auto zc = p[2].masked_select(finite);
  // Nearest resampling repeats every source column 4 or 5 times: the median stays within a few
  // columns (0.01 in z each, over a scale of ~1) of the shift's column.
  EXPECT_NEAR(zc.median().item<double>(), 0.0, 0.05);
  // z spans 3.0 .. 3.99 on the object: within 0.99 / scale of the shift (scale ~1).
  EXPECT_LT(zc.abs().max().item<double>(), 3.0);
  // Full point map: every pixel with depth is valid (no background removal), NaN in the padding.
  auto rp = out.tensors.at("rgb_pointmap")[0];
  EXPECT_FALSE(torch::isfinite(rp[2][10][259]).item<bool>());  // padding row
  EXPECT_TRUE(torch::isfinite(rp[2][259][30]).item<bool>());   // background pixel with depth

  // Through the (small) condition embedder: 2 x (1 + 37^2) + 2 x (1 + 5^2) + 2 x 4^2 tokens. Its point
  // embedder is switched to the real model's `linear` remap: with the fixture's `exp` remap, normalised
  // depths below -1 (here the near background) give log1p(z) = NaN, in the official code as well.
  torch::NoGradGuard ng;
  auto ecfg = simu::models::CondEmbedderConfig::load(simu::testing::fixture("cond_embedder_small.json"));
  ecfg.embedders[2].point.remap_output = "linear";
  simu::models::CondEmbedder emb(ecfg);
  simu::models::load_safetensors_into(*emb, simu::testing::fixture("cond_embedder_small.safetensors"), {});
  emb->eval();
  auto tokens = emb->forward(out.tensors);
  // As many tokens and channels as the official embedder's output on its own inputs.
  const auto fused = simu::data::SafeTensorsFile::open(simu::testing::fixture("cond_embedder_small_io.safetensors"))
                         .info("out.fused")
                         .shape;
  EXPECT_EQ(tokens.sizes(), torch::IntArrayRef({1, fused[1], fused[2]}));
  EXPECT_TRUE(torch::isfinite(tokens).all().item<bool>());
#endif
}

// Amodal resampling input: the crop follows the auxiliary mask M' while the mask channel stays modal.
TEST(Preprocess, CropMaskDefinesTheCropButNotTheMaskChannel) {
#ifndef SIMU_HAVE_OPENCV
  GTEST_SKIP() << "built without OpenCV";
#else
  const auto files = write_scene(simu::testing::temp_dir("preprocess_crop_mask"));
  auto out = sd::prepare_condition_inputs_from_files(files.image, files.mask, make_pointmap(),
                                                    sd::PreprocessConfig::preset_named("default"), files.crop_mask);
  // M': x 100..199, y 60..179 -> w 99, h 119 -> side 119, half 59; centre (149.5, 119.5)
  // -> x [int(90.5), int(208.5)) = [90, 208), y [int(60.5), int(178.5)) = [60, 178); extend int(118*0.1) = 11.
  EXPECT_EQ(out.crop_box.x1, 90);
  EXPECT_EQ(out.crop_box.x2, 208);
  EXPECT_EQ(out.crop_box.y1, 60);
  EXPECT_EQ(out.crop_box.y2, 178);
  EXPECT_EQ(out.crop_extend, 11);
  // Mask channel: only the modal rows 60..119 -> crop rows [11, 71) of 140, columns [21, 121).
  auto mask = out.tensors.at("mask")[0][0];
  // Nearest resampling: each edge within one output pixel, 2/518 (100 + 60)/140 = 0.0044.
  EXPECT_NEAR(mask.mean().item<double>(), 100.0 * 60.0 / (140.0 * 140.0), 0.01);
  // Row of the amodal extension (y = 150 -> crop row 101 -> output 101/140*518 = 373): mask 0, image kept.
  EXPECT_EQ(mask[373][259].item<float>(), 0.f);
  auto image = out.tensors.at("image")[0];
  EXPECT_GT(image.select(1, 373).select(1, 259).abs().sum().item<float>(), 0.1f);
  // Shift still from the modal mask: lower median z of the object pixels with depth (u 100..179 and
  // 185..199, 95 columns x 60 rows: the 48th column, u = 147).
  // z = 2 + 0.01 u in fp32: 3 roundings of 3.47.
  EXPECT_NEAR(out.pointmap_shift[2].item<double>(), 2.0 + 0.01 * 147, 3.47 * simu::testing::gamma(3));
#endif
}

// Same algorithm on tensors (no files): checks the errors.
TEST(Preprocess, Errors) {
  auto rgb = torch::rand({3, 40, 50});
  auto mask = torch::zeros({40, 50});
  auto pm = torch::rand({3, 40, 50}) + 1;
  // Empty mask.
  EXPECT_THROW(sd::prepare_condition_inputs(rgb, mask, pm), simu::Error);
  mask.slice(0, 10, 20).slice(1, 10, 30).fill_(1);
  // Size mismatch between image and mask.
  EXPECT_THROW(sd::prepare_condition_inputs(rgb, torch::ones({41, 50}), pm), simu::Error);
  // Wrong image layout.
  EXPECT_THROW(sd::prepare_condition_inputs(torch::rand({40, 50, 3}), mask, pm), simu::Error);
  // All-invalid point map.
  EXPECT_THROW(sd::prepare_condition_inputs(rgb, mask, torch::full({3, 40, 50}, NAN)), simu::Error);
  // No valid point under the mask.
  auto pm_hole = pm.clone();
  pm_hole.slice(1, 10, 20).slice(2, 10, 30).fill_(NAN);
  try {
    sd::prepare_condition_inputs(rgb, mask, pm_hole);
    FAIL() << "expected an error";
  } catch (const simu::Error& e) {
    EXPECT_NE(std::string(e.what()).find("no valid"), std::string::npos) << e.what();
  }
  // A mask one pixel thin has no 2x2 box.
  auto thin = torch::zeros({40, 50});
  thin.slice(0, 10, 11).slice(1, 5, 30).fill_(1);
  EXPECT_THROW(sd::prepare_condition_inputs(rgb, thin, pm), simu::Error);
  // Empty crop mask.
  EXPECT_THROW(sd::prepare_condition_inputs(rgb, mask, pm, {}, torch::zeros({40, 50})), simu::Error);
  // Valid call without point map: no pointmap keys; a point map in H x W x 3 and of another size works.
  auto ok = sd::prepare_condition_inputs(rgb, mask, torch::Tensor());
  EXPECT_EQ(ok.tensors.count("pointmap"), 0u);
  auto ok2 = sd::prepare_condition_inputs(rgb, mask, torch::rand({20, 25, 3}) + 1);
  EXPECT_EQ(ok2.tensors.at("pointmap").sizes(), torch::IntArrayRef({1, 3, 518, 518}));
}

// compute_mask_bbox: a box that runs past the image edge is zero-filled in the crop.
TEST(Preprocess, CropPastTheImageEdge) {
  auto rgb = torch::ones({3, 30, 30});
  auto mask = torch::zeros({30, 30});
  mask.slice(0, 0, 10).slice(1, 0, 4).fill_(1);  // x 0..3 (w 3), y 0..9 (h 9): side 9, half 4
  auto b = sd::compute_mask_bbox(mask, 1.0);
  // centre (1.5, 4.5): x [int(-2.5), int(5.5)) = [-2, 5), y [int(0.5), int(8.5)) = [0, 8)
  EXPECT_EQ(b.x1, -2);
  EXPECT_EQ(b.x2, 5);
  EXPECT_EQ(b.y1, 0);
  EXPECT_EQ(b.y2, 8);
  auto cfg = sd::PreprocessConfig::preset_named("default");
  cfg.box_size_factor = 1.0;
  cfg.padding_factor = 0;
  cfg.image_size = 7;  // 7 x 8 crop -> padded to 8 x 8 -> resized to 7
  cfg.remove_background = false;
  auto out = sd::prepare_condition_inputs(rgb, mask, torch::Tensor(), cfg);
  EXPECT_EQ(out.tensors.at("image").sizes(), torch::IntArrayRef({1, 3, 7, 7}));
  // The two columns left of the image are black in the crop.
  sd::PreprocessConfig keep = cfg;
  keep.image_size = 8;
  auto out8 = sd::prepare_condition_inputs(rgb, mask, torch::Tensor(), keep);
  auto img = out8.tensors.at("image")[0][0];  // 8 x 8: 7 wide crop padded 0 left / 1 right; rows 8
  EXPECT_EQ(img.slice(1, 0, 2).abs().max().item<float>(), 0.f);
  EXPECT_EQ(img.slice(1, 2, 7).min().item<float>(), 1.f);
}

// OpenCV camera frame (x right, y down) -> PyTorch3D frame (x left, y up): diag(-1, -1, 1).
TEST(Preprocess, OpenCvToPyTorch3dPoints) {
  auto p = torch::tensor({1.f, 2.f, 3.f}).view({3, 1, 1});
  auto q = sd::pointmap_from_opencv_camera(p);
  EXPECT_EQ(q[0][0][0].item<float>(), -1.f);
  EXPECT_EQ(q[1][0][0].item<float>(), -2.f);
  EXPECT_EQ(q[2][0][0].item<float>(), 3.f);
}

// ---------------------------------------------------------------------------------------------
// The released pipeline.yaml `ss_preprocessor`, against the official code's tensors
// (../shared/fixtures/preprocess_released_case{0,1,2}.safetensors, README "preprocess_released"):
// raw uint8 image, 0/1 mask (alpha / 255) and OpenCV point map in; every tensor the condition
// embedder receives out, and the pose decode with the scene scale/shift.
namespace {

// max |a - b| over the positions where both are finite; also checks NaN positions are identical.
::testing::AssertionResult same_with_nan(const torch::Tensor& got, const torch::Tensor& want, double tol,
                                         const std::string& what, double* err_out = nullptr) {
  if (got.sizes() != want.sizes())
    return ::testing::AssertionFailure() << what << ": shape " << got.sizes() << " vs expected " << want.sizes();
  const auto g = got.to(torch::kFloat64), w = want.to(torch::kFloat64);
  const auto gn = torch::isnan(g), wn = torch::isnan(w);
  const int64_t nan_diff = (gn != wn).sum().item<int64_t>();
  if (nan_diff != 0)
    return ::testing::AssertionFailure() << what << ": NaN at " << nan_diff << " positions that differ (got "
                                         << gn.sum().item<int64_t>() << " NaN, expected " << wn.sum().item<int64_t>() << ")";
  if (!torch::isfinite(w.masked_select(~wn)).all().item<bool>())
    return ::testing::AssertionFailure() << what << ": expected tensor has inf";
  const double e = (g - w).masked_fill(wn, 0).abs().max().item<double>();
  if (err_out) *err_out = e;
  if (e > tol) return ::testing::AssertionFailure() << what << ": max abs error " << e << " > " << tol;
  return ::testing::AssertionSuccess();
}

// The fixture's cases (preprocess_released.json "cases"): name -> its record (H, W, seed, crop box,
// scale / shift, tensor statistics). Whatever cases a regeneration writes, each is checked.
nlohmann::json released_cases() {
  std::ifstream in(simu::testing::fixture("preprocess_released.json"));
  return nlohmann::json::parse(in).at("cases");
}

std::string released_case_path(const std::string& name) {
  return simu::testing::fixture("preprocess_released_" + name + ".safetensors");
}

// Taps per output pixel of an antialiased bilinear resize from `in` to `out` pixels (support
// max(1, in / out) on each side).
double bilinear_taps(double in, double out) { return std::ceil(2 * std::max(1.0, in / out)) + 1; }

void check_released_case(const std::string& name) {
  SCOPED_TRACE(name);
  const auto path = released_case_path(name);
  ASSERT_TRUE(std::filesystem::exists(path)) << "fixture missing: " << path;
  const auto f = simu::data::load_safetensors(path);
  // Inputs as the official pipeline reads them: rgb = uint8 / 255 (in float64, then float32),
  // mask = alpha / 255 with alpha = mask * 255, point map converted from the OpenCV camera.
  const auto rgb = (f.at("in.image").to(torch::kFloat64) / 255.0).to(torch::kFloat32).permute({2, 0, 1});  // [3,H,W]
  const auto mask = (f.at("in.mask").to(torch::kFloat64) * 255.0 / 255.0).to(torch::kFloat32);           // [H,W]
  const auto pm = sd::pointmap_from_opencv_camera(f.at("in.pointmap").permute({2, 0, 1}).contiguous());  // [3,H,W]
  // The frame conversion itself (a NaN/inf coordinate makes the whole point NaN): negations, and the
  // official 4x4 product's other terms are exact zeros, so bit for bit.
  EXPECT_TRUE(same_with_nan(pm, f.at("mid.pointmap"), 0.0, "mid.pointmap"));

  // Default config = the released preset.
  const sd::PreprocessConfig cfg;
  ASSERT_EQ(cfg.preset, "released");
  const auto out = sd::prepare_condition_inputs(rgb, mask, pm, cfg);

  // Images: two fp32 evaluations of the antialiased bilinear resize of values <= 1 (absolute): two
  // separable passes, each of `taps` products and sums and the weights' normalisation (a sum of taps
  // and a division), from the larger of the (padded) crop and the frame. Masks exact; NaN positions exact.
  const double side = std::max({static_cast<double>(rgb.size(1)), static_cast<double>(rgb.size(2)),
                                static_cast<double>(out.crop_box.x2 - out.crop_box.x1),
                                static_cast<double>(out.crop_box.y2 - out.crop_box.y1)});
  const double taps = bilinear_taps(side, static_cast<double>(cfg.image_size));
  const double image_tol = simu::testing::two_paths(2 * (2 * taps + 1));
  double err = 0;
  for (const char* key : {"image", "rgb_image"}) {
    EXPECT_TRUE(same_with_nan(out.tensors.at(key), f.at(std::string("out.") + key), image_tol, key, &err));
    std::printf("%s %-15s max abs error %.3g\n", name.c_str(), key, err);
  }
  for (const char* key : {"mask", "rgb_image_mask"})
    EXPECT_TRUE(same_with_nan(out.tensors.at(key), f.at(std::string("out.") + key), 0.0, key));
  // Point maps: nearest resampling copies (p - shift) / scale, two fp32 roundings of it in each of
  // the two implementations, absolute on its largest finite value.
  for (const char* key : {"pointmap", "rgb_pointmap"}) {
    const auto& want = f.at(std::string("out.") + key);
    const double p_max = want.masked_select(torch::isfinite(want)).abs().max().item<double>();
    EXPECT_TRUE(same_with_nan(out.tensors.at(key), want, simu::testing::two_paths(2) * p_max, key, &err));
    std::printf("%s %-15s max abs error %.3g\n", name.c_str(), key, err);
  }
  // Scale / shift: lower medians of fp32 values (the shift one of the points, the scale one of the
  // fp32 max |p - shift|): the same element in both implementations, bit for bit (the full-frame pair
  // is the same).
  for (const char* prefix : {"out.", "out.rgb_"}) {
    const auto want_scale = f.at(std::string(prefix) + "pointmap_scale").reshape({3});
    const auto want_shift = f.at(std::string(prefix) + "pointmap_shift").reshape({3});
    EXPECT_TRUE(simu::testing::close(out.pointmap_scale, want_scale, 0.0, std::string(prefix) + "pointmap_scale"));
    EXPECT_TRUE(simu::testing::close(out.pointmap_shift, want_shift, 0.0, std::string(prefix) + "pointmap_shift"));
  }

  // Pose decode with the scene scale/shift of this preprocessing (ScaleShiftInvariant, the released
  // pose_decoder_name).
  simu::models::PoseDecodeOptions po;
  po.convention = "ScaleShiftInvariant";
  po.scene_scale = out.pointmap_scale[0].item<double>();
  for (int i = 0; i < 3; ++i) po.scene_shift[i] = out.pointmap_shift[i].item<double>();
  std::map<std::string, torch::Tensor> lat;
  for (const char* n : {"6drotation_normalized", "scale", "translation", "translation_scale"})
    lat[n] = f.at(std::string("pose.in.") + n);
  const auto pose = simu::models::decode_pose(lat, po);
  // Two fp32 implementations: the rotation (de-normalise, Gram-Schmidt, the quaternion: ~27 roundings
  // of unit values, absolute); translation t s + shift and scale mean(exp(s)) s (<= 6 roundings of
  // their largest value).
  EXPECT_TRUE(same_with_nan(pose.quaternion, f.at("pose.out.rotation"), simu::testing::two_paths(27), "pose rotation"));
  for (const auto& [got, key] : {std::pair{pose.translation, "pose.out.translation"}, std::pair{pose.scale, "pose.out.scale"}}) {
    const auto& want = f.at(key);
    EXPECT_TRUE(same_with_nan(got, want, simu::testing::two_paths(6) * want.abs().max().item<double>(), key));
  }
}

}  // namespace

// Every case of the fixture against the official tensors (json "cases": object inside the frame, crop
// leaving the image with single-coordinate NaN, a large image with a near pole and +inf invalid points).
TEST(PreprocessReleased, EveryCaseMatchesTheOfficialTensors) {
  const auto cases = released_cases();
  ASSERT_FALSE(cases.empty()) << "preprocess_released.json lists no case";
  for (const auto& [name, record] : cases.items()) check_released_case(name);
}

// The crop box of each case is the official one (json: crop_bbox_x1y1x2y2).
TEST(PreprocessReleased, CropBoxes) {
  const auto cases = released_cases();
  ASSERT_FALSE(cases.empty()) << "preprocess_released.json lists no case";
  for (const auto& [name, record] : cases.items()) {
    const auto path = released_case_path(name);
    ASSERT_TRUE(std::filesystem::exists(path)) << "fixture missing: " << path;
    const auto f = simu::data::SafeTensorsFile::open(path);
    const auto b = sd::compute_mask_bbox(f.get("in.mask"), sd::PreprocessConfig{}.box_size_factor);
    const auto want = record.at("crop_bbox_x1y1x2y2").get<std::array<int64_t, 4>>();
    EXPECT_EQ((std::array<int64_t, 4>{b.x1, b.y1, b.x2, b.y2}), want) << name;
    // The input's size is the record's too.
    EXPECT_EQ(f.get("in.mask").size(0), record.at("H").get<int64_t>()) << name;
    EXPECT_EQ(f.get("in.mask").size(1), record.at("W").get<int64_t>()) << name;
  }
}

// Presets by name from YAML: `preset` first, then field overrides; an unknown name is an error.
TEST(PreprocessReleased, PresetsByName) {
  auto released = sd::PreprocessConfig::preset_named("released");
  EXPECT_EQ(released.image_interpolation, "bilinear");
  EXPECT_DOUBLE_EQ(released.box_size_factor, 1.2);
  EXPECT_DOUBLE_EQ(released.padding_factor, 0.0);
  EXPECT_FALSE(released.remove_background);
  auto def = sd::PreprocessConfig::preset_named("default");
  EXPECT_EQ(def.image_interpolation, "bicubic");
  EXPECT_DOUBLE_EQ(def.box_size_factor, 1.0);
  EXPECT_TRUE(def.remove_background);
  YAML::Node n = YAML::Load("{preset: default, padding_factor: 0.2}");
  simu::config::Reader r(n, "test.yaml");
  auto c = sd::PreprocessConfig::from(r);
  EXPECT_EQ(c.preset, "default");
  EXPECT_DOUBLE_EQ(c.padding_factor, 0.2);
  EXPECT_EQ(c.image_interpolation, "bicubic");
  YAML::Node bad = YAML::Load("{preset: bogus}");
  simu::config::Reader rb(bad, "test.yaml");
  EXPECT_THROW(sd::PreprocessConfig::from(rb), simu::Error);
}
