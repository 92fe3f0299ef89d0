// Lift: SAM 3D Objects Stage 1 on a photo's objects. For every object of one image: the released
// condition preprocessing (data/preprocess.h), the condition embedder, Stage-1 CFG sampling, the
// sparse-structure decoder, marching cubes and pose decoding (all inside one batched
// Resampler::resample call), then the pose in SAM 3D's convention and in the scene convention
// (docs/scene_format.md). The `lift` program and `probe --resample` both go through lift_objects.
//
//   simu::resample::Resampler rs(cfg);                  // embedder_config set
//   simu::resample::LiftInputs in;
//   in.rgb = simu::data::read_image_rgb("photo.png");   // [3, H, W]
//   in.pointmap = simu::data::read_pointmap("moge.npy");  // [H, W, 3] OpenCV camera
//   in.objects = {{"cup", cup_mask}, {"bowl", bowl_mask}};
//   auto res = simu::resample::lift_objects(rs, in, {});
//   res.objects[0].samples[0].mesh;  res.objects[0].scene_poses[0].R;
//   simu::resample::write_lift_outputs(res, in, {"out/lift"});
//
// Frames. SAM 3D reads and writes the PyTorch3D camera frame (x left, y up, z forward); its pose maps
// the official voxel frame v in [-0.5, 0.5]^3 (voxel index p -> p / R - 0.5) to the camera with row
// vectors: p = (s * v) @ R_official + t. ResampledShape::rotation is R_official^T (column vectors).
// The scene convention: world = R * (s .* c) + t for a canonical-mesh vertex c (AABB-centred, longest
// side 1; c = (v - centre) * factor), world = R_world_cam * p_opencv + t_world_cam, and the OpenCV
// camera is PyTorch3D's with x and y negated.
#pragma once

#include <torch/torch.h>

#include <nlohmann/json.hpp>

#include <array>
#include <optional>
#include <string>
#include <vector>

#include "data/depth_io.h"
#include "data/preprocess.h"
#include "pipeline/resample/resampler.h"
#include "pipeline/physics/scene.h"

namespace simu::resample {

using physics::Camera;
using physics::Mat3;
using physics::Vec3;

// An object pose in the scene convention: world = R * (scale .* c) + t for canonical vertices c.
struct ScenePose {
  Mat3 R = Mat3::Identity();
  Vec3 scale = Vec3::Ones();
  Vec3 t = Vec3::Zero();
};

// SAM 3D's decoded pose of a canonical mesh (column-vector PyTorch3D camera frame:
// p = rotation * (scale_canonical .* c) + translation_canonical, as ResampledShape holds it) -> the
// scene convention with `camera`'s pose: R = R_world_cam * F * rotation, s = scale_canonical,
// t = R_world_cam * F * translation_canonical + t_world_cam, F = diag(-1, -1, 1).
ScenePose scene_pose_from_sam3d(const Mat3& rotation, const Vec3& scale_canonical, const Vec3& translation_canonical,
                                const Camera& camera);
ScenePose scene_pose_from_sam3d(const ResampledShape& shape, const Camera& camera);

// One object to lift.
struct LiftObjectInput {
  std::string id;           // names the object in messages and output folders
  torch::Tensor mask;       // [H, W] modal mask in [0, 1] (object where > 0); undefined when `error` is set
  torch::Tensor crop_mask;  // optional [H, W]: crop box and background from it (probe: the amodal M')
  std::string error;        // set when the object's input could not be read: reported, not lifted
};

struct LiftInputs {
  torch::Tensor rgb;       // [3, H, W] float in [0, 1]
  torch::Tensor pointmap;  // [H, W, 3] OpenCV camera (x right, y down, z forward); NaN / +-inf = invalid
  Camera camera;           // intrinsics, size and pose in the world (scene convention; identity = camera frame)
  std::vector<LiftObjectInput> objects;
};

struct LiftOptions {
  // The Stage-1 condition preprocessing; unset = the model's (preprocess_choice("model", ...) of
  // default_model.h: the shipped miniature's own sizes, else the released preset).
  std::optional<data::PreprocessConfig> preprocess;
  uint64_t seed = 0;                  // sampling noise seed (noise per object and sample, in object order)
  // A resampling call (the probe's, probe_resampler.h) rather than the first lift: an adapter loaded for
  // resampling only (Resampler::adapter_resample_only) stays on; in a first lift it is switched off.
  bool resampling = false;
  // Shapes drawn per object in this call; 0 = the model's num_samples (reconstruct's first lift draws
  // kFirstLiftSamples and keeps the one the point map agrees with most: ReconstructOptions::lift).
  int samples = 0;
};

// Shapes reconstruct's first lift draws per object by default (and eval_lift, which measures it): each
// is aligned to the point map and the one whose render agrees best with the depth and the mask is kept.
// Chosen on the validation split by docs/rules/sample_select.md (best of 4 against one sample,
// unoccluded IoU +0.042 [+0.028, +0.057]).
inline constexpr int kFirstLiftSamples = 4;

// LiftOptions of a first lift: kFirstLiftSamples shapes per object.
inline LiftOptions first_lift_options() {
  LiftOptions o;
  o.samples = kFirstLiftSamples;
  return o;
}

// The outcome for one object.
struct LiftedObject {
  std::string id;
  bool ok = false;      // at least one usable sample
  std::string error;    // why not ok (input, preprocessing or sampling), naming the object
  data::CropBox crop_box;
  bool has_crop_box = false;
  double scene_scale = 1.0;                    // ObjectCentricSSI scale of the point map
  std::array<double, 3> scene_shift{0, 0, 0};  // and shift (PyTorch3D camera frame)
  std::vector<ResampledShape> samples;   // every sample (ok or not), SAM 3D's pose inside
  std::vector<ScenePose> scene_poses;    // per sample, scene convention
};

// Seconds per stage for the whole call (all objects together).
struct LiftTimings {
  double preprocess = 0, embed = 0, sample = 0, decode = 0, mesh = 0, pose = 0;
  double total() const { return preprocess + embed + sample + decode + mesh + pose; }
};

struct LiftResult {
  std::vector<LiftedObject> objects;  // in input order
  LiftTimings seconds;
  int sampling_calls = 0;
  int failed() const;                 // objects not ok
};

// Lifts every object of `inputs` with `resampler` (which must have an embedder). Per-object problems
// (input error, mask size differs from the image, empty mask, no valid point under the mask, no usable
// sample) make that object not ok with an error naming it; the others are lifted together in one
// batched call. Whole-input problems (no image, point map of another size than the image) throw.
LiftResult lift_objects(Resampler& resampler, const LiftInputs& inputs, const LiftOptions& options);

// ---- Inputs from files (the `lift` program) ----

// A scene's "depth" file as an OpenCV point map [H, W, 3]: an .npy of shape [H, W, 3] is a point map
// read as it is; anything else is a depth map (data::read_depth) unprojected through the camera.
torch::Tensor read_scene_pointmap(const std::string& path, const Camera& camera);

struct LiftFiles {
  std::string image;                // RGB(A) image
  std::vector<std::string> masks;   // one label PNG, or one PNG per object, or one directory of PNGs
  std::string mask_kind = "auto";   // auto (one file = label image; several files / a directory = one
                                    // mask per file) | label | per-object
  std::string pointmap;             // .npy [H, W, 3] OpenCV camera (MoGe), or
  std::string depth;                // .npy (float m / uint16 mm), .png (16-bit mm), .exr (float m)
  std::string intrinsics;           // K JSON (data::read_intrinsics_json); needed with depth, optional
                                    // with a point map (then fitted to it)
};

// Reads and checks the files: the image, depth or point map and K are whole-run errors naming the
// file; a per-object mask that cannot be read becomes that object's error. Object ids: the mask file
// stem (per-object masks) or "label_<k>" (label image, k = the label value, ascending).
LiftInputs load_lift_inputs(const LiftFiles& files);

// The geometry of inputs whose rgb is set (what load_lift_inputs does after reading the files; the Python
// module calls it with arrays): exactly one of a point map [H, W, 3] (OpenCV camera, kept as it is; K
// fitted to it when not given) and a depth map [H, W] (metres, NaN invalid; data::clean_depth) unprojected
// through K (required). Sets inputs.pointmap and the camera's intrinsics and size; the names in errors
// are geometry_what and image_what (a size that differs from the image's).
void set_lift_geometry(LiftInputs& inputs, const torch::Tensor& pointmap, const torch::Tensor& depth,
                       const std::optional<data::Intrinsics>& intrinsics, const std::string& geometry_what,
                       const std::string& image_what);

// Checks that every weight file is given: a missing one is an error naming its flag
// (--generator-weights, --decoder-weights, --embedder-weights) unless random_weights, which instead
// returns the banner naming the modules left at random init ("" when every file is given).
std::string check_lift_weights(const ResamplerConfig& config, bool random_weights);

// Maps --precision onto the resampler: "auto" (fp16 autocast on CUDA as released, fp32 on CPU),
// "fp16", "bf16" (CUDA only), "fp32".
void apply_precision(ResamplerConfig& config, const std::string& precision);
// The precision a resampler actually runs in ("fp16", "bf16" or "fp32").
std::string effective_precision(const Resampler& resampler);

// Refuses an existing output directory unless overwrite (an error naming it and the flag).
void check_output_dir(const std::string& out_dir, bool overwrite);

// What a run used, for report.json: model configs and weights, device, precision, the sampler and
// preprocessing settings, condition tokens per object, seed.
nlohmann::json lift_run_info(Resampler& resampler, const LiftOptions& options, const std::string& precision,
                             bool random_weights);

// ---- Outputs ----

struct LiftWriteOptions {
  std::string out_dir;
  bool overwrite = false;            // replace an existing out_dir (else refuse)
  std::string image_path;            // the input image, referenced by scene.json ("image")
  std::string depth_path;            // the input depth or point map, referenced by scene.json ("depth")
  std::string banner;                // e.g. the random-weights warning; written into report.json
  nlohmann::json run_info;           // settings to record in report.json (models, sampler, precision...)
};

// Writes, into a temporary directory beside out_dir renamed into place at the end:
//   scene.json                       simuscene/1: camera, image, gravity (+y, camera frame), objects ok
//                                    (mesh = first usable sample's GLB, pose in the scene convention)
//   report.json                      per object ok/error, crop box, scale/shift, per-stage seconds, run info
//   objects/<id>/mask.png            the modal mask (8-bit, 255 = object)
//   objects/<id>/sample_<k>/mesh.glb, mesh.obj   canonical mesh (AABB-centred, longest side 1)
//   objects/<id>/sample_<k>/occupancy.npy        uint8 [R, R, R] (R = 64 at the released size), index (x, y, z)
//   objects/<id>/sample_<k>/pose.json            SAM 3D's pose, the scene pose, the canonical transform
// Throws when out_dir exists and overwrite is false.
void write_lift_outputs(const LiftResult& result, const LiftInputs& inputs, const LiftWriteOptions& options,
                        int64_t occupancy_resolution);

// The decoder's output grid side R of a resampler (latent resolution x 2 per upsampling stage).
int64_t occupancy_resolution(Resampler& resampler);

// Occupancy grid uint8 [R, R, R] from occupied voxel coordinates [N, 3] (x, y, z).
torch::Tensor occupancy_grid(const torch::Tensor& coords, int64_t resolution);

}  // namespace simu::resample
