#include "data/preprocess.h"

#include <fmt/ranges.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "common/error.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#endif

namespace simu::data {

namespace F = torch::nn::functional;

PreprocessConfig PreprocessConfig::preset_named(const std::string& name) {
  PreprocessConfig c;  // the released pipeline.yaml ss_preprocessor
  if (name == "released") return c;
  if (name == "default") {
    c.preset = name;
    c.image_interpolation = "bicubic";
    c.box_size_factor = 1.0;
    c.padding_factor = 0.1;
    c.remove_background = true;
    c.full_pointmap_pad_nan = true;
    return c;
  }
  fail("preprocess preset '{}' is unknown (expected released or default)", name);
}

PreprocessConfig PreprocessConfig::from(config::Reader& r) {
  PreprocessConfig c = preset_named(r.get<std::string>("preset", "released"));
  r.field("image_size", c.image_size);
  r.field("image_interpolation", c.image_interpolation);
  r.field("image_antialias", c.image_antialias);
  r.field("pointmap_size", c.pointmap_size);
  r.field("box_size_factor", c.box_size_factor);
  r.field("padding_factor", c.padding_factor);
  r.field("remove_background", c.remove_background);
  r.field("full_pointmap_pad_nan", c.full_pointmap_pad_nan);
  r.field("normalize_pointmap", c.normalize_pointmap);
  r.field("scale_mode", c.scale_mode);
  r.field("quantile_drop_threshold", c.quantile_drop_threshold);
  r.field("scale_factor", c.scale_factor);
  r.field("clip_beyond_scale", c.clip_beyond_scale);
  SIMU_CHECK(c.image_interpolation == "bicubic" || c.image_interpolation == "bilinear",
             "{}: image_interpolation '{}' (expected bicubic or bilinear)", r.file(), c.image_interpolation);
  SIMU_CHECK(c.scale_mode == "scene" || c.scale_mode == "object_quantile" || c.scale_mode == "object_norm_median",
             "{}: scale_mode '{}' (expected scene, object_quantile or object_norm_median)", r.file(), c.scale_mode);
  return c;
}

namespace {

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

std::string shape(const torch::Tensor& t) { return fmt::format("[{}]", fmt::join(t.sizes(), ", ")); }

// [H,W] or [1,H,W] float mask.
torch::Tensor as_mask(const torch::Tensor& m, const char* what) {
  SIMU_CHECK(m.defined(), "{}: missing", what);
  SIMU_CHECK(m.dim() == 2 || (m.dim() == 3 && m.size(0) == 1), "{}: shape {} expected [H, W] or [1, H, W]", what,
             shape(m));
  return (m.dim() == 3 ? m[0] : m).to(torch::kFloat32);
}

// Cut box out of t [C,H,W], filling outside the image with `fill` (torchvision crop pads with 0).
torch::Tensor crop_fill(const torch::Tensor& t, const CropBox& b, float fill) {
  const int64_t H = t.size(1), W = t.size(2);
  auto out = torch::full({t.size(0), b.height(), b.width()}, fill, t.options());
  const int64_t sx1 = std::max<int64_t>(0, b.x1), sy1 = std::max<int64_t>(0, b.y1);
  const int64_t sx2 = std::min<int64_t>(W, b.x2), sy2 = std::min<int64_t>(H, b.y2);
  if (sx2 > sx1 && sy2 > sy1)
    out.slice(1, sy1 - b.y1, sy2 - b.y1).slice(2, sx1 - b.x1, sx2 - b.x1).copy_(t.slice(1, sy1, sy2).slice(2, sx1, sx2));
  return out;
}

// Centred padding to a square: the smaller side gets diff/2 before (floor) and the rest after.
torch::Tensor pad_to_square_centered(const torch::Tensor& t, float value) {
  const int64_t h = t.size(-2), w = t.size(-1);
  if (h == w) return t;
  const int64_t diff = std::abs(h - w), a = diff / 2, b = diff - a;
  std::vector<int64_t> pad = h > w ? std::vector<int64_t>{a, b, 0, 0} : std::vector<int64_t>{0, 0, a, b};
  return F::pad(t, F::PadFuncOptions(pad).mode(torch::kConstant).value(value));
}

// Resize [C,h,w] to size x size.
torch::Tensor resize_square(const torch::Tensor& t, int64_t size, const std::string& mode, bool antialias) {
  if (t.size(-2) == size && t.size(-1) == size) return t;
  auto opts = F::InterpolateFuncOptions().size(std::vector<int64_t>{size, size});
  if (mode == "nearest") {
    opts.mode(torch::kNearest);
  } else {
    if (mode == "bicubic") opts.mode(torch::kBicubic);
    else opts.mode(torch::kBilinear);
    opts.align_corners(false).antialias(antialias);
  }
  return F::interpolate(t.unsqueeze(0), opts).squeeze(0);
}

// Per-tensor transforms (step 4).
torch::Tensor image_transform(const torch::Tensor& img, const PreprocessConfig& c) {
  return resize_square(pad_to_square_centered(img, 0.f), c.image_size, c.image_interpolation, c.image_antialias);
}
torch::Tensor mask_transform(const torch::Tensor& m, const PreprocessConfig& c) {
  return resize_square(pad_to_square_centered(m, 0.f), c.image_size, "nearest", false);
}
torch::Tensor pointmap_transform(const torch::Tensor& p, const PreprocessConfig& c, float pad_value) {
  auto sq = pad_to_square_centered(p, pad_value);
  return c.pointmap_size > 0 ? resize_square(sq, c.pointmap_size, "nearest", false) : sq;
}

}  // namespace

torch::Tensor pointmap_from_opencv_camera(const torch::Tensor& pointmap) {
  SIMU_CHECK(pointmap.dim() == 3 && pointmap.size(0) == 3, "pointmap: shape {} expected [3, H, W]", shape(pointmap));
  auto flip = torch::tensor({-1.f, -1.f, 1.f}, pointmap.options()).view({3, 1, 1});
  // The official 4x4 product sums every coordinate (times 0 off the diagonal): one NaN/inf -> all NaN.
  const auto valid = torch::isfinite(pointmap).all(0, /*keepdim=*/true);  // [1, H, W]
  return torch::where(valid, pointmap * flip, torch::full_like(pointmap, kNaN));
}

CropBox compute_mask_bbox(const torch::Tensor& mask_in, double box_size_factor) {
  auto mask = as_mask(mask_in, "mask");
  auto idx = torch::nonzero(mask);  // [K, 2] (y, x)
  SIMU_CHECK(idx.size(0) > 0, "mask is empty (no pixel > 0): cannot crop around the object");
  const int64_t min_y = idx.select(1, 0).min().item<int64_t>(), max_y = idx.select(1, 0).max().item<int64_t>();
  const int64_t min_x = idx.select(1, 1).min().item<int64_t>(), max_x = idx.select(1, 1).max().item<int64_t>();
  const int64_t w = max_x - min_x, h = max_y - min_y;
  SIMU_CHECK(w >= 2 && h >= 2,
             "mask bounding box is {}x{} pixels (x {}..{}, y {}..{}); it must be at least 2x2 (max - min index)", w,
             h, min_x, max_x, min_y, max_y);
  const double cx = (min_x + max_x) / 2.0, cy = (min_y + max_y) / 2.0;
  const auto size = static_cast<int64_t>(static_cast<double>(std::max<int64_t>({w, h, 2})) * box_size_factor);
  const int64_t half = size / 2;
  // Python int() truncates toward zero.
  CropBox b;
  b.x1 = static_cast<int64_t>(std::trunc(cx - half));
  b.y1 = static_cast<int64_t>(std::trunc(cy - half));
  b.x2 = static_cast<int64_t>(std::trunc(cx + half));
  b.y2 = static_cast<int64_t>(std::trunc(cy + half));
  return b;
}

std::pair<torch::Tensor, torch::Tensor> object_centric_scale_shift(const torch::Tensor& pointmap,
                                                                   const torch::Tensor& mask_in,
                                                                   const PreprocessConfig& c) {
  auto mask = as_mask(mask_in, "mask");
  SIMU_CHECK(pointmap.dim() == 3 && pointmap.size(0) == 3, "pointmap: shape {} expected [3, H, W]", shape(pointmap));
  // Mask at the point map's resolution (nearest).
  if (mask.sizes() != pointmap.sizes().slice(1))
    mask = F::interpolate(mask.unsqueeze(0).unsqueeze(0),
                          F::InterpolateFuncOptions()
                              .size(std::vector<int64_t>{pointmap.size(1), pointmap.size(2)})
                              .mode(torch::kNearest))
               .squeeze(0)
               .squeeze(0);
  auto flat = pointmap.reshape({3, -1}).to(torch::kFloat32);  // [3, N]
  auto object = flat.index({torch::indexing::Slice(), mask.reshape(-1) > 0.5});  // [3, M]
  SIMU_CHECK(object.size(1) > 0 && torch::isfinite(object).any().item<bool>(),
             "pointmap: no valid (finite) point under the object mask ({} mask pixels); the depth model gave no "
             "geometry for this object", object.size(1));
  // Shift: per-axis median of the object's points (NaN ignored; lower median like torch.nanmedian).
  auto shift = std::get<0>(torch::nanmedian(object, -1));  // [3]
  torch::Tensor scale;
  if (c.scale_mode == "scene") {
    // Scene scale: median over all pixels of the largest |coordinate - shift|.
    auto max_dims = std::get<0>((flat - shift.unsqueeze(-1)).abs().max(0));  // [N], NaN propagates
    scale = torch::nanmedian(max_dims);
  } else {
    auto norm = (object - shift.unsqueeze(-1)).pow(2).sum(0).sqrt();  // [M]
    if (c.scale_mode == "object_norm_median") {
      scale = torch::nanmedian(norm);
    } else {
      auto q = torch::nanquantile(norm, torch::tensor({c.quantile_drop_threshold, 1.0 - c.quantile_drop_threshold},
                                                      torch::kFloat32));
      scale = (q[1] - q[0]) * 2.0;
    }
  }
  scale = (scale * c.scale_factor).expand({3}).clone();
  return {scale, shift};
}

ConditionInputs prepare_condition_inputs(const torch::Tensor& rgb_in, const torch::Tensor& mask_in,
                                         const torch::Tensor& pointmap_in, const PreprocessConfig& c,
                                         const torch::Tensor& crop_mask_in) {
  // Check and convert inputs.
  SIMU_CHECK(rgb_in.defined() && rgb_in.dim() == 3 && rgb_in.size(0) == 3, "image: shape {} expected [3, H, W]",
             rgb_in.defined() ? shape(rgb_in) : std::string("(none)"));
  const auto rgb = rgb_in.to(torch::kCPU, torch::kFloat32);
  const int64_t H = rgb.size(1), W = rgb.size(2);
  const auto mask = as_mask(mask_in, "mask").to(torch::kCPU);
  SIMU_CHECK(mask.size(0) == H && mask.size(1) == W, "mask is {}x{} but the image is {}x{} (H x W)", mask.size(0),
             mask.size(1), H, W);
  SIMU_CHECK((mask > 0).any().item<bool>(), "mask is empty (no pixel > 0)");
  torch::Tensor crop_mask;
  if (crop_mask_in.defined()) {
    crop_mask = as_mask(crop_mask_in, "crop mask").to(torch::kCPU);
    SIMU_CHECK(crop_mask.size(0) == H && crop_mask.size(1) == W, "crop mask is {}x{} but the image is {}x{} (H x W)",
               crop_mask.size(0), crop_mask.size(1), H, W);
    SIMU_CHECK((crop_mask > 0).any().item<bool>(), "crop mask is empty (no pixel > 0)");
  }
  torch::Tensor pm;
  if (pointmap_in.defined()) {
    pm = pointmap_in.to(torch::kCPU, torch::kFloat32);
    if (pm.dim() == 3 && pm.size(0) != 3 && pm.size(2) == 3) pm = pm.permute({2, 0, 1});
    SIMU_CHECK(pm.dim() == 3 && pm.size(0) == 3, "pointmap: shape {} expected [3, H, W] or [H, W, 3]",
               shape(pointmap_in));
    SIMU_CHECK(torch::isfinite(pm).all(0).any().item<bool>(), "pointmap: every point is invalid (non-finite)");
    // A point map of another resolution is brought to the image's with nearest sampling.
    if (pm.size(1) != H || pm.size(2) != W)
      pm = F::interpolate(pm.unsqueeze(0), F::InterpolateFuncOptions()
                                               .size(std::vector<int64_t>{H, W})
                                               .mode(torch::kNearest))
               .squeeze(0);
    pm = pm.contiguous();
  }

  ConditionInputs out;
  // 1. Point map normalisation on the full map with the (modal) object mask.
  torch::Tensor pm_norm;
  if (pm.defined()) {
    auto [scale, shift] = object_centric_scale_shift(pm, mask, c);
    out.pointmap_scale = scale;
    out.pointmap_shift = shift;
    if (c.normalize_pointmap) {
      pm_norm = (pm - shift.view({3, 1, 1})) / scale.view({3, 1, 1});
      if (c.clip_beyond_scale > 0)
        pm_norm = torch::where(pm_norm.pow(2).sum(0, true).sqrt() > c.clip_beyond_scale, torch::full_like(pm_norm, kNaN), pm_norm);
    } else {
      pm_norm = pm;
    }
  }

  // 2. Square crop around the (crop) mask, zero fill outside the image.
  const auto& box_mask = crop_mask.defined() ? crop_mask : mask;
  out.crop_box = compute_mask_bbox(box_mask, c.box_size_factor);
  auto img_c = crop_fill(rgb, out.crop_box, 0.f);
  auto mask_c = crop_fill(mask.unsqueeze(0), out.crop_box, 0.f);
  auto bg_c = crop_mask.defined() ? crop_fill(crop_mask.unsqueeze(0), out.crop_box, 0.f) : mask_c;
  torch::Tensor pm_c = pm_norm.defined() ? crop_fill(pm_norm, out.crop_box, 0.f) : torch::Tensor();
  //    pad to a square (zeros / NaN), then extend by padding_factor on each side.
  auto square = [](const torch::Tensor& t, float v) {
    const int64_t h = t.size(1), w = t.size(2), m = std::max(h, w);
    const int64_t ph = (m - h) / 2, pw = (m - w) / 2;
    return F::pad(t, F::PadFuncOptions({pw, m - w - pw, ph, m - h - ph}).mode(torch::kConstant).value(v));
  };
  const int64_t side = std::max(img_c.size(1), img_c.size(2));
  img_c = square(img_c, 0.f), mask_c = square(mask_c, 0.f), bg_c = square(bg_c, 0.f);
  if (pm_c.defined()) pm_c = square(pm_c, kNaN);
  out.crop_extend = c.padding_factor > 0 ? static_cast<int64_t>(static_cast<double>(side) * c.padding_factor) : 0;
  if (out.crop_extend > 0) {
    const int64_t e = out.crop_extend;
    auto ext = [e](const torch::Tensor& t, float v) {
      return F::pad(t, F::PadFuncOptions({e, e, e, e}).mode(torch::kConstant).value(v));
    };
    img_c = ext(img_c, 0.f), mask_c = ext(mask_c, 0.f), bg_c = ext(bg_c, 0.f);
    if (pm_c.defined()) pm_c = ext(pm_c, kNaN);
  }

  // 3. Background removal in the crop.
  if (c.remove_background) {
    img_c = img_c * bg_c;
    if (pm_c.defined()) pm_c = torch::where(bg_c > 0, pm_c, torch::full_like(pm_c, kNaN));
  }

  // 4. Per-tensor transforms; full-image versions get only these.
  out.tensors["image"] = image_transform(img_c, c).unsqueeze(0);
  out.tensors["mask"] = mask_transform(mask_c, c).unsqueeze(0);
  out.tensors["rgb_image"] = image_transform(rgb, c).unsqueeze(0);
  out.tensors["rgb_image_mask"] = mask_transform(mask.unsqueeze(0), c).unsqueeze(0);
  if (pm_c.defined()) {
    // The crop is square already (its NaN padding is in pm_c); the full frame is padded here.
    out.tensors["pointmap"] = pointmap_transform(pm_c, c, kNaN).unsqueeze(0);
    out.tensors["rgb_pointmap"] = pointmap_transform(pm_norm, c, c.full_pointmap_pad_nan ? kNaN : 0.f).unsqueeze(0);
  }
  return out;
}

// ---------------------------------------------------------------------------------------------
// OpenCV image I/O

#ifdef SIMU_HAVE_OPENCV
namespace {

cv::Mat read_any(const std::string& path) {
  cv::Mat m = cv::imread(path, cv::IMREAD_UNCHANGED);
  SIMU_CHECK(!m.empty(), "{}: cannot read the image (missing file or unsupported format)", path);
  return m;
}

// One 8/16-bit or float channel -> [H,W] float in [0,1].
torch::Tensor channel_to_tensor(const cv::Mat& ch, const std::string& path) {
  cv::Mat f;
  double s = 1.0;
  if (ch.depth() == CV_8U) s = 1.0 / 255.0;
  else if (ch.depth() == CV_16U) s = 1.0 / 65535.0;
  else SIMU_CHECK(ch.depth() == CV_32F || ch.depth() == CV_64F, "{}: unsupported pixel depth {}", path, ch.depth());
  ch.convertTo(f, CV_32F, s);
  return torch::from_blob(f.data, {f.rows, f.cols}, torch::kFloat32).clone();
}

}  // namespace
#endif

torch::Tensor read_image_rgb(const std::string& path, torch::Tensor* alpha) {
#ifdef SIMU_HAVE_OPENCV
  cv::Mat m = read_any(path);
  std::vector<cv::Mat> ch;
  cv::split(m, ch);
  if (alpha) *alpha = torch::Tensor();
  torch::Tensor rgb;
  if (ch.size() == 1) {
    auto g = channel_to_tensor(ch[0], path);
    rgb = torch::stack({g, g, g});
  } else {
    SIMU_CHECK(ch.size() == 3 || ch.size() == 4, "{}: {} channels, expected 1, 3 or 4", path, ch.size());
    // OpenCV stores BGR(A).
    rgb = torch::stack({channel_to_tensor(ch[2], path), channel_to_tensor(ch[1], path), channel_to_tensor(ch[0], path)});
    if (ch.size() == 4 && alpha) *alpha = channel_to_tensor(ch[3], path);
  }
  return rgb;
#else
  (void)alpha;
  fail_hint("configure with OpenCV (libopencv-{core,imgproc,imgcodecs}-dev) or pass tensors to "
            "prepare_condition_inputs", "{}: cannot read images: this build has no OpenCV", path);
#endif
}

torch::Tensor read_mask(const std::string& path) {
#ifdef SIMU_HAVE_OPENCV
  cv::Mat m = read_any(path);
  std::vector<cv::Mat> ch;
  cv::split(m, ch);
  if (ch.size() == 1) return channel_to_tensor(ch[0], path);
  if (ch.size() == 4) return channel_to_tensor(ch[3], path);
  cv::Mat mx = cv::max(cv::max(ch[0], ch[1]), ch[2]);
  return channel_to_tensor(mx, path);
#else
  fail_hint("configure with OpenCV (libopencv-{core,imgproc,imgcodecs}-dev) or pass tensors to "
            "prepare_condition_inputs", "{}: cannot read masks: this build has no OpenCV", path);
#endif
}

torch::Tensor rgb_from_uint8(const torch::Tensor& image, const std::string& what) {
  SIMU_CHECK(image.dim() == 3 && image.size(2) == 3 && image.scalar_type() == torch::kUInt8,
             "{}: expected an RGB image [H, W, 3] uint8, got {} {}", what, image.sizes(), c10::toString(image.scalar_type()));
#ifdef SIMU_HAVE_OPENCV
  const auto c = image.contiguous().cpu();
  const cv::Mat m(static_cast<int>(c.size(0)), static_cast<int>(c.size(1)), CV_8UC3, const_cast<uint8_t*>(c.data_ptr<uint8_t>()));
  std::vector<cv::Mat> ch;
  cv::split(m, ch);
  return torch::stack({channel_to_tensor(ch[0], what), channel_to_tensor(ch[1], what), channel_to_tensor(ch[2], what)});
#else
  fail("{}: converting images needs OpenCV (built with SIMU_WITH_OPENCV=OFF)", what);
#endif
}

torch::Tensor mask_from_uint8(const torch::Tensor& mask, const std::string& what) {
  SIMU_CHECK(mask.dim() == 2 && mask.scalar_type() == torch::kUInt8, "{}: expected a mask [H, W] uint8, got {} {}", what,
             mask.sizes(), c10::toString(mask.scalar_type()));
#ifdef SIMU_HAVE_OPENCV
  const auto c = mask.contiguous().cpu();
  const cv::Mat m(static_cast<int>(c.size(0)), static_cast<int>(c.size(1)), CV_8UC1, const_cast<uint8_t*>(c.data_ptr<uint8_t>()));
  return channel_to_tensor(m, what);
#else
  fail("{}: converting masks needs OpenCV (built with SIMU_WITH_OPENCV=OFF)", what);
#endif
}

ConditionInputs prepare_condition_inputs_from_files(const std::string& image_path, const std::string& mask_path,
                                                    const torch::Tensor& pointmap, const PreprocessConfig& config,
                                                    const std::string& crop_mask_path) {
  torch::Tensor alpha;
  auto rgb = read_image_rgb(image_path, &alpha);
  torch::Tensor mask;
  if (mask_path.empty()) {
    SIMU_CHECK(alpha.defined(), "{}: no mask file given and the image has no alpha channel", image_path);
    mask = alpha;
  } else {
    mask = read_mask(mask_path);
  }
  SIMU_CHECK(mask.size(0) == rgb.size(1) && mask.size(1) == rgb.size(2), "{}: mask is {}x{} but {} is {}x{}",
             mask_path.empty() ? image_path : mask_path, mask.size(0), mask.size(1), image_path, rgb.size(1),
             rgb.size(2));
  torch::Tensor crop_mask;
  if (!crop_mask_path.empty()) crop_mask = read_mask(crop_mask_path);
  return prepare_condition_inputs(rgb, mask, pointmap, config, crop_mask);
}

}  // namespace simu::data
