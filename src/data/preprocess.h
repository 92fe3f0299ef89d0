// Stage-1 condition preprocessing of SAM 3D Objects: RGB image + object mask + point map -> the
// inputs of the condition embedder (models/cond_embedder.h), as the official `ss_preprocessor`
// (sam3d_objects/data/dataset/tdfy/{preprocessor,img_and_mask_transforms,img_processing}.py,
// sam3d_objects/pipeline/inference_pipeline_pointmap.py::preprocess_image) does:
//
//   1. point map normalisation on the full map (ObjectCentricSSI): shift = per-axis nanmedian of the
//      points under the mask (> 0.5; torch's lower median); scale = nanmedian over all pixels of
//      max(|p - shift|) (scene scale) times scale_factor; p' = (p - shift) / scale;
//   2. object crop (crop_around_mask_with_padding): square box of side int(max(w, h, 2) * box_size_factor)
//      centred on the mask's bounding box (w, h = max - min pixel index; both must be >= 2; corners by
//      int() truncation), cut with ZERO fill outside the image (image, mask and point map alike),
//      padded to a square (0; NaN for the point map), then extended by int(side * padding_factor)
//      on each side (zeros; NaN for the point map);
//   3. background removal in the crop (rembg; only in the "default" preset): image * mask, point map
//      NaN where mask == 0;
//   4. per-tensor transforms: pad to a centred square (0, the official pad_to_square_centered default,
//      also for the full-frame point map in the released preset), resize to image_size (image:
//      bilinear or bicubic with antialias = torchvision Resize on float tensors; mask and point map:
//      F.interpolate "nearest", not "nearest-exact").
//   The full-image versions (rgb_image, rgb_image_mask, rgb_pointmap) get only step 4 (and step 1,
//   with the crop's scale and shift, as allow_scale_and_shift_override does).
//
// Presets (PreprocessConfig::preset, YAML key `preset`):
//   "released" (the default everywhere): the `ss_preprocessor` block of the released
//       checkpoints/hf/pipeline.yaml: bilinear + antialias resize to 518, box_size_factor 1.2,
//       padding_factor 0, no background removal, full point map padded with 0. Proven against
//       ../shared/fixtures/preprocess_released_case{0,1,2}.safetensors (tests/data/preprocess_test.cpp).
//   "default": the repository's get_default_preprocessor() style used before the release was read:
//       bicubic, box_size_factor 1.0, padding_factor 0.1, background removal, full point map padded
//       with NaN.
// Any field given after the preset in YAML overrides it.
//
// Amodal resampling: with `crop_mask` (the auxiliary mask M' of the paper), the crop box is computed
// from crop_mask and (when remove_background) the background is removed with crop_mask (the amodal
// crop image I_{M'}), while the `mask` / `rgb_image_mask` channels stay the modal mask and the point
// map is normalised with it.
//
// A point map of another size than the image is first resized to it with nearest sampling (as the
// official compute_pointmap does for a given point map).
#pragma once

#include <torch/torch.h>

#include <map>
#include <string>

#include "common/config.h"

namespace simu::data {

// Defaults = the "released" preset (see the file comment).
struct PreprocessConfig {
  std::string preset = "released";              // name of the preset the fields started from
  int64_t image_size = 518;                     // image and mask outputs: image_size x image_size
  std::string image_interpolation = "bilinear"; // "bicubic" or "bilinear"
  bool image_antialias = true;                  // torchvision >= 0.17 Resize default on tensors
  int64_t pointmap_size = 518;                  // 0: keep the padded crop's size
  double box_size_factor = 1.2;
  double padding_factor = 0.0;
  bool remove_background = false;               // rembg in the crop
  bool full_pointmap_pad_nan = false;           // pad value of the full-frame point map: NaN (true) or 0
  bool normalize_pointmap = true;               // false: points unchanged, scale/shift still returned
  // ObjectCentricSSI: "scene" (use_scene_scale true), "object_quantile" (false: 2 x spread between the
  // quantile_drop_threshold quantiles of |p - shift| over the mask), "object_norm_median".
  std::string scale_mode = "scene";
  double quantile_drop_threshold = 0.1;
  double scale_factor = 1.0;
  double clip_beyond_scale = 0.0;               // > 0: points with |p'| beyond it become NaN
  // A named preset: "released" or "default". Throws naming the known ones otherwise.
  static PreprocessConfig preset_named(const std::string& name);
  // Keys: `preset` (read first; default "released"), then every field above by its name.
  static PreprocessConfig from(config::Reader& r);
};

// Square crop window in original image pixels, [x1, x2) x [y1, y2); may extend past the image.
struct CropBox {
  int64_t x1 = 0, y1 = 0, x2 = 0, y2 = 0;
  int64_t width() const { return x2 - x1; }
  int64_t height() const { return y2 - y1; }
};

struct ConditionInputs {
  // Official kwarg names, each with a batch dimension of 1:
  //   image [1,3,S,S], rgb_image [1,3,S,S], mask [1,1,S,S], rgb_image_mask [1,1,S,S] (S = image_size),
  //   pointmap [1,3,P,P], rgb_pointmap [1,3,P,P] (only with a point map; NaN = invalid).
  std::map<std::string, torch::Tensor> tensors;
  CropBox crop_box;                      // the crop before the padding_factor extension
  int64_t crop_extend = 0;               // pixels added on each side after squaring
  torch::Tensor pointmap_scale;          // [3] (undefined without a point map)
  torch::Tensor pointmap_shift;          // [3]
};

// SAM 3D reads point maps in the PyTorch3D camera frame (x left, y up, z forward). Depth models such
// as MoGe give OpenCV-frame points (x right, y down, z forward); the official pipeline rotates them by
// diag(-1, -1, 1) (camera_to_pytorch3d_camera) as a 4x4 homogeneous product, so a point with any
// NaN/inf coordinate becomes NaN in all three. This does the same: pointmap [3,H,W] -> (-x, -y, z).
torch::Tensor pointmap_from_opencv_camera(const torch::Tensor& pointmap);

// compute_mask_bbox: box around mask != 0 (see step 2). Throws for an empty mask or a box thinner
// than 2 pixels.
CropBox compute_mask_bbox(const torch::Tensor& mask, double box_size_factor = 1.0);

// ObjectCentricSSI scale and shift ([3] each) of point map [3,H,W] under mask [H,W] (> 0.5 is object).
// Throws when no point under the mask is finite.
std::pair<torch::Tensor, torch::Tensor> object_centric_scale_shift(const torch::Tensor& pointmap,
                                                                   const torch::Tensor& mask,
                                                                   const PreprocessConfig& config = {});

// rgb: [3,H,W] float in [0,1]; mask: [H,W] (or [1,H,W]) in [0,1], object where > 0;
// pointmap: [3,Hp,Wp] or [Hp,Wp,3] points in the PyTorch3D camera frame (see
//   pointmap_from_opencv_camera; NaN/inf = invalid), or undefined for none;
// crop_mask: optional [H,W] mask that defines the crop box (and the background removal) instead of mask.
// Errors: empty mask / crop mask, size mismatches, a point map with no finite point under the mask.
ConditionInputs prepare_condition_inputs(const torch::Tensor& rgb, const torch::Tensor& mask,
                                         const torch::Tensor& pointmap, const PreprocessConfig& config = {},
                                         const torch::Tensor& crop_mask = {});

// Image I/O through OpenCV (an error naming the path when the build has no OpenCV):
// RGB image [3,H,W] float in [0,1] (8- or 16-bit files); with `alpha`, also its alpha channel [H,W]
// in [0,1] (undefined when the file has none).
torch::Tensor read_image_rgb(const std::string& path, torch::Tensor* alpha = nullptr);
// Mask [H,W] in [0,1]: a grey file as is, the alpha channel of an RGBA file, else the channel maximum.
torch::Tensor read_mask(const std::string& path);
// Pixels in memory converted exactly as read_image_rgb / read_mask convert a file's (OpenCV's k / 255):
// an 8-bit RGB image [H,W,3] uint8 -> [3,H,W] float in [0,1]; an 8-bit mask [H,W] uint8 -> [H,W] float.
// `what` names the array in errors (wrong shape or dtype).
torch::Tensor rgb_from_uint8(const torch::Tensor& image, const std::string& what);
torch::Tensor mask_from_uint8(const torch::Tensor& mask, const std::string& what);
// Files -> inputs. An empty mask_path uses the image's alpha channel; crop_mask_path is optional.
ConditionInputs prepare_condition_inputs_from_files(const std::string& image_path, const std::string& mask_path,
                                                    const torch::Tensor& pointmap,
                                                    const PreprocessConfig& config = {},
                                                    const std::string& crop_mask_path = "");

}  // namespace simu::data
