#include "pipeline/resample/lift.h"

#include "pipeline/resample/default_model.h"

#include <fmt/format.h>
#include <fmt/ranges.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <map>
#include <filesystem>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "common/timing.h"
#include "data/depth_io.h"
#include "pipeline/physics/mesh.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

namespace simu::resample {

using physics::Camera;
using physics::Mat3;
using physics::Mesh;
using physics::Scene;
using physics::SceneObject;
using physics::Vec3;
using physics::scene_to_json;
using physics::write_mesh;

namespace {

using json = nlohmann::json;

// PyTorch3D camera axes (x left, y up, z forward) -> OpenCV camera axes (x right, y down, z forward).
const Mat3 kP3dToOpenCv = Eigen::Vector3d(-1, -1, 1).asDiagonal();

json vec_json(const Eigen::Vector3d& v) { return json::array({v.x(), v.y(), v.z()}); }
json mat_json(const Mat3& m) {
  json rows = json::array();
  for (int r = 0; r < 3; ++r) rows.push_back(json::array({m(r, 0), m(r, 1), m(r, 2)}));
  return rows;
}

}  // namespace

ScenePose scene_pose_from_sam3d(const Mat3& rotation, const Vec3& scale_canonical, const Vec3& translation_canonical,
                                const Camera& camera) {
  const Mat3 M = camera.R_world_cam * kP3dToOpenCv;
  ScenePose p;
  p.R = M * rotation;
  p.scale = scale_canonical;
  p.t = M * translation_canonical + camera.t_world_cam;
  return p;
}

ScenePose scene_pose_from_sam3d(const ResampledShape& shape, const Camera& camera) {
  return scene_pose_from_sam3d(shape.rotation, shape.scale_canonical, shape.translation_canonical, camera);
}

int LiftResult::failed() const {
  int n = 0;
  for (const auto& o : objects) n += o.ok ? 0 : 1;
  return n;
}

namespace {

// One object's checks (naming it) and its released preprocessing -> the resampler request; fills
// out's crop box and point-map scale/shift. Throws with the object's id on any problem.
ResampleRequest prepare_object(const LiftInputs& inputs, const LiftObjectInput& in, const torch::Tensor& valid,
                               const torch::Tensor& pointmap_p3d, const data::PreprocessConfig& preprocess,
                               LiftedObject& out) {
  const int64_t H = inputs.rgb.size(1), W = inputs.rgb.size(2);
  SIMU_CHECK(in.error.empty(), "{}", in.error);
  SIMU_CHECK(in.mask.defined(), "object '{}': no mask", in.id);
  auto mask = in.mask.to(torch::kCPU, torch::kFloat32);
  if (mask.dim() == 3 && mask.size(0) == 1) mask = mask[0];
  SIMU_CHECK(mask.dim() == 2 && mask.size(0) == H && mask.size(1) == W,
             "object '{}': mask is {} but the image is {}x{} (W x H)", in.id,
             mask.dim() == 2 ? fmt::format("{}x{} (W x H)", mask.size(1), mask.size(0)) : fmt::format("{}", mask.sizes()),
             W, H);
  const auto object = mask > 0.5;
  const int64_t pixels = object.sum().item<int64_t>();
  SIMU_CHECK(pixels > 0, "object '{}': the mask is empty (no pixel above 0.5)", in.id);
  const int64_t valid_pixels = (object & valid).sum().item<int64_t>();
  SIMU_CHECK(valid_pixels > 0,
             "object '{}': no valid point under its mask ({} mask pixels, every point NaN/inf or without depth)",
             in.id, pixels);
  torch::Tensor crop = in.crop_mask.defined() ? in.crop_mask.to(torch::kCPU, torch::kFloat32) : torch::Tensor();
  auto prepared = [&] {
    try {
      return data::prepare_condition_inputs(inputs.rgb.to(torch::kCPU, torch::kFloat32), mask, pointmap_p3d,
                                            preprocess, crop);
    } catch (const std::exception& e) {
      fail("object '{}': preprocessing failed: {}", in.id, e.what());
    }
  }();
  out.crop_box = prepared.crop_box;
  out.has_crop_box = true;
  ResampleRequest r;
  r.inputs = std::move(prepared.tensors);
  if (prepared.pointmap_scale.defined()) {
    r.scene_scale = prepared.pointmap_scale.reshape({-1})[0].item<double>();
    for (int k = 0; k < 3; ++k) r.scene_shift[k] = prepared.pointmap_shift.reshape({-1})[k].item<double>();
  }
  out.scene_scale = r.scene_scale;
  out.scene_shift = r.scene_shift;
  return r;
}

}  // namespace

LiftResult lift_objects(Resampler& resampler, const LiftInputs& inputs, const LiftOptions& options) {
  torch::NoGradGuard no_grad;
  const data::PreprocessConfig preprocess =
      options.preprocess ? *options.preprocess : preprocess_choice("model", resampler.config());
  SIMU_CHECK(resampler.embedder(), "lift: the resampler has no condition embedder (set embedder_config)");
  SIMU_CHECK(inputs.rgb.defined() && inputs.rgb.dim() == 3 && inputs.rgb.size(0) == 3,
             "lift: the image must be [3, H, W], got {}",
             inputs.rgb.defined() ? fmt::format("{}", inputs.rgb.sizes()) : std::string("nothing"));
  const int64_t H = inputs.rgb.size(1), W = inputs.rgb.size(2);
  SIMU_CHECK(inputs.pointmap.defined() && inputs.pointmap.dim() == 3 && inputs.pointmap.size(2) == 3,
             "lift: the point map must be [H, W, 3] (OpenCV camera), got {}",
             inputs.pointmap.defined() ? fmt::format("{}", inputs.pointmap.sizes()) : std::string("nothing"));
  SIMU_CHECK(inputs.pointmap.size(0) == H && inputs.pointmap.size(1) == W,
             "lift: the point map is {}x{} (W x H) but the image is {}x{}", inputs.pointmap.size(1),
             inputs.pointmap.size(0), W, H);
  LiftResult result;
  result.objects.resize(inputs.objects.size());
  auto t0 = std::chrono::steady_clock::now();
  // OpenCV points -> PyTorch3D frame; a point with any non-finite coordinate is invalid in all three
  // (the released compute_pointmap does this through a homogeneous product).
  auto pm = inputs.pointmap.to(torch::kCPU, torch::kFloat32);                          // [H, W, 3]
  const auto valid = torch::isfinite(pm).all(-1);                                      // [H, W]
  pm = torch::where(valid.unsqueeze(-1), pm, torch::full_like(pm, NAN));
  const auto pointmap_p3d = data::pointmap_from_opencv_camera(pm.permute({2, 0, 1}).contiguous());  // [3, H, W]

  // Per object: checks that name the object, then the released preprocessing.
  std::vector<ResampleRequest> batch;
  std::vector<size_t> batch_index;
  for (size_t i = 0; i < inputs.objects.size(); ++i) {
    auto& out = result.objects[i];
    out.id = inputs.objects[i].id;
    try {
      batch.push_back(prepare_object(inputs, inputs.objects[i], valid, pointmap_p3d, preprocess, out));
      batch_index.push_back(i);
    } catch (const std::exception& e) {
      out.ok = false;
      out.error = e.what();
      log::error("{}", out.error);
    }
  }
  result.seconds.preprocess = seconds_since(t0);
  if (batch.empty()) return result;

  // Every object in one batched call: embedder, sampling, decoder, marching cubes, pose decoding. An
  // adapter for resampling only is off in a first lift (the base model runs, as in the paper) and on
  // again after; a resampling call keeps it on.
  struct AdapterOff {
    Resampler& r;
    bool off;
    ~AdapterOff() {
      if (off) r.set_adapter_enabled(true);
    }
  } adapter_off{resampler, resampler.adapter_resample_only() && !options.resampling};
  if (adapter_off.off) resampler.set_adapter_enabled(false);
  const auto rs = resampler.resample(batch, options.seed, options.samples);
  result.seconds.embed = rs.seconds_embed;
  result.seconds.sample = rs.seconds_sample;
  result.seconds.decode = rs.seconds_decode;
  result.seconds.mesh = rs.seconds_mesh;
  result.sampling_calls = rs.sampling_calls;

  // Poses in the scene convention; objects without a usable sample are errors naming them.
  t0 = std::chrono::steady_clock::now();
  for (size_t b = 0; b < batch.size(); ++b) {
    auto& out = result.objects[batch_index[b]];
    out.samples = rs.objects[b];
    std::vector<std::string> why;
    for (size_t s = 0; s < out.samples.size(); ++s) {
      out.scene_poses.push_back(scene_pose_from_sam3d(out.samples[s], inputs.camera));
      if (out.samples[s].ok)
        out.ok = true;
      else
        why.push_back(fmt::format("sample {}: {}", s, out.samples[s].message));
    }
    if (!out.ok) {
      out.error = fmt::format("object '{}': no usable sample ({})", out.id, fmt::join(why, "; "));
      log::error("{}", out.error);
    }
  }
  result.seconds.pose = seconds_since(t0);
  return result;
}

torch::Tensor read_scene_pointmap(const std::string& path, const Camera& camera) {
  auto ext = std::filesystem::path(path).extension().string();
  for (auto& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (ext == ".npy") {
    SIMU_CHECK(std::filesystem::exists(path), "{}: depth / point map file not found", path);
    const auto h = data::read_npy_header(path);
    if (h.shape.size() == 3 && h.shape[2] == 3) return data::read_pointmap(path);
  }
  SIMU_CHECK(camera.fx > 0 && camera.fy > 0, "{}: a depth map needs the camera intrinsics", path);
  return data::unproject_depth(data::read_depth(path), {camera.fx, camera.fy, camera.cx, camera.cy});
}

namespace {

// The objects of a lift: --masks expanded (a directory -> its .png files, sorted), then one label
// image (ids label_<k>) or one mask per file (ids = file stems); each checked against the image's H x W.
std::vector<LiftObjectInput> load_lift_masks(const LiftFiles& files, int64_t H, int64_t W) {
  namespace sfs = std::filesystem;
  LiftInputs in;
  SIMU_CHECK(!files.masks.empty(), "lift: no masks (--masks)");
  std::vector<std::string> paths;
  bool from_dir = false;
  for (const auto& m : files.masks) {
    if (sfs::is_directory(m)) {
      std::vector<std::string> found;
      for (const auto& e : sfs::directory_iterator(m)) {
        auto ext = e.path().extension().string();
        for (auto& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
        if (e.is_regular_file() && ext == ".png") found.push_back(e.path().string());
      }
      std::sort(found.begin(), found.end());
      SIMU_CHECK(!found.empty(), "{}: mask directory has no .png file", m);
      paths.insert(paths.end(), found.begin(), found.end());
      from_dir = true;
    } else {
      paths.push_back(m);
    }
  }
  const std::string kind = files.mask_kind;
  SIMU_CHECK(kind == "auto" || kind == "label" || kind == "per-object",
             "lift: --mask-kind must be auto, label or per-object, got '{}'", kind);
  const bool label = kind == "label" || (kind == "auto" && paths.size() == 1 && !from_dir);
  if (label) {
    SIMU_CHECK(paths.size() == 1, "lift: --mask-kind label takes one label image, got {} files", paths.size());
    SIMU_CHECK(sfs::exists(paths[0]), "{}: label image not found (--masks)", paths[0]);
    const auto labels = data::read_label_image(paths[0]);  // [H, W]
    SIMU_CHECK(labels.size(0) == H && labels.size(1) == W, "{}: label image is {}x{} (W x H) but the image {} is {}x{}",
               paths[0], labels.size(1), labels.size(0), files.image, W, H);
    const auto values = std::get<0>(torch::_unique(labels.flatten(), /*sorted=*/true));
    for (int64_t k = 0; k < values.numel(); ++k) {
      const int64_t v = values[k].item<int64_t>();
      if (v == 0) continue;
      in.objects.push_back({fmt::format("label_{}", v), (labels == v).to(torch::kFloat32), {}, ""});
    }
    SIMU_CHECK(!in.objects.empty(), "{}: the label image has no object (every pixel is 0)", paths[0]);
  } else {
    std::map<std::string, int> seen;
    for (const auto& p : paths) {
      LiftObjectInput o;
      o.id = sfs::path(p).stem().string();
      if (seen[o.id]++) o.id += "_" + std::to_string(seen[o.id] - 1);
      try {
        SIMU_CHECK(sfs::exists(p), "{}: mask file not found", p);
        o.mask = data::read_mask(p);  // [H, W] in [0, 1]
      } catch (const std::exception& e) {
        o.error = fmt::format("object '{}': {}", o.id, e.what());
      }
      in.objects.push_back(std::move(o));
    }
  }
  return std::move(in.objects);
}

}  // namespace

void set_lift_geometry(LiftInputs& in, const torch::Tensor& pointmap, const torch::Tensor& depth,
                       const std::optional<data::Intrinsics>& intrinsics, const std::string& geometry_what,
                       const std::string& image_what) {
  SIMU_CHECK(in.rgb.defined() && in.rgb.dim() == 3, "lift: set the image before the geometry");
  SIMU_CHECK(pointmap.defined() != depth.defined(), "lift: pass exactly one of a point map and a depth map");
  const int64_t H = in.rgb.size(1), W = in.rgb.size(2);
  data::Intrinsics K;
  if (pointmap.defined()) {
    in.pointmap = pointmap;
    K = intrinsics ? *intrinsics : data::estimate_intrinsics(in.pointmap, geometry_what);
    if (!intrinsics)
      log::info("{}: no intrinsics given, fitted to the point map: fx {:.2f} fy {:.2f} cx {:.2f} cy {:.2f}",
                geometry_what, K.fx, K.fy, K.cx, K.cy);
  } else {
    SIMU_CHECK(intrinsics.has_value(), "{}: a depth map needs the camera intrinsics K", geometry_what);
    K = *intrinsics;
    in.pointmap = data::unproject_depth(depth, K);
  }
  SIMU_CHECK(in.pointmap.size(0) == H && in.pointmap.size(1) == W, "{}: {}x{} (W x H), but the image {} is {}x{}",
             geometry_what, in.pointmap.size(1), in.pointmap.size(0), image_what, W, H);
  in.camera.fx = K.fx;
  in.camera.fy = K.fy;
  in.camera.cx = K.cx;
  in.camera.cy = K.cy;
  in.camera.width = static_cast<int>(W);
  in.camera.height = static_cast<int>(H);
}

LiftInputs load_lift_inputs(const LiftFiles& files) {
  namespace sfs = std::filesystem;
  LiftInputs in;
  SIMU_CHECK(!files.image.empty(), "lift: no image (--image)");
  SIMU_CHECK(sfs::exists(files.image), "{}: image file not found (--image)", files.image);
  in.rgb = data::read_image_rgb(files.image);  // [3, H, W]
  const int64_t H = in.rgb.size(1), W = in.rgb.size(2);
  // Geometry: a point map as it is, or depth unprojected through K.
  SIMU_CHECK(files.pointmap.empty() != files.depth.empty(), "lift: pass exactly one of --pointmap and --depth");
  std::optional<data::Intrinsics> K;
  if (!files.intrinsics.empty()) K = data::read_intrinsics_json(files.intrinsics);
  if (!files.pointmap.empty()) {
    set_lift_geometry(in, data::read_pointmap(files.pointmap), {}, K, files.pointmap, files.image);
  } else {
    SIMU_CHECK(K.has_value(), "{}: a depth map needs the camera intrinsics (--intrinsics K.json)", files.depth);
    set_lift_geometry(in, {}, data::read_depth(files.depth), K, files.depth, files.image);
  }
  // Masks: expand a directory, then one label image or one mask per file.
  in.objects = load_lift_masks(files, H, W);

  return in;
}

std::string check_lift_weights(const ResamplerConfig& c, bool random_weights) {
  std::vector<std::string> random;
  const std::pair<const std::string*, const char*> items[] = {{&c.generator_weights, "--generator-weights"},
                                                              {&c.decoder_weights, "--decoder-weights"},
                                                              {&c.embedder_weights, "--embedder-weights"}};
  for (const auto& [path, flag] : items) {
    if (!path->empty()) {
      SIMU_CHECK(std::filesystem::exists(*path), "{}: weight file not found ({})", *path, flag);
      continue;
    }
    if (!random_weights)
      fail_hint(fmt::format("pass {} FILE.safetensors (see checkpoints/README.md), or --random-weights for a "
                            "smoke run with meaningless shapes",
                            flag),
                "{} is missing", flag);
    random.push_back(flag);
  }
  if (random.empty()) {
    if (random_weights) log::warn("--random-weights has no effect: every weight file is given");
    return "";
  }
  return fmt::format("RANDOM WEIGHTS: no {} given, those modules keep their random initialisation; the shapes and "
                     "poses below are meaningless (--random-weights)",
                     fmt::join(random, ", "));
}

void apply_precision(ResamplerConfig& config, const std::string& precision) {
  SIMU_CHECK(precision == "auto" || precision == "fp16" || precision == "bf16" || precision == "fp32",
             "--precision must be auto, fp16, bf16 or fp32, got '{}'", precision);
  config.precision = precision;  // the Resampler resolves auto and checks the device (models/precision.h)
}

std::string effective_precision(const Resampler& resampler) { return models::precision_name(resampler.precision()); }

void check_output_dir(const std::string& out_dir, bool overwrite) {
  SIMU_CHECK(!out_dir.empty(), "lift: no output directory (--out)");
  if (std::filesystem::exists(out_dir) && !overwrite)
    fail_hint("pass --overwrite to replace it, or choose another --out", "{}: output directory exists", out_dir);
}

nlohmann::json lift_run_info(Resampler& resampler, const LiftOptions& options, const std::string& precision,
                             bool random_weights) {
  const auto& c = resampler.config();
  const auto p = options.preprocess ? *options.preprocess : preprocess_choice("model", resampler.config());
  return {{"model", resampler.shipped_model_note().empty() ? std::string("given weights") : resampler.shipped_model_note()},
          {"generator", {{"config", c.generator_config}, {"weights", c.generator_weights}}},
          {"decoder", {{"config", c.decoder_config}, {"weights", c.decoder_weights}}},
          {"embedder",
           {{"config", c.embedder_config},
            {"weights", c.embedder_weights},
            {"condition_tokens_per_object", resampler.embedder() ? resampler.embedder()->num_tokens() : 0}}},
          {"adapter", c.adapter_dir},
          {"random_weights", random_weights},
          {"device", resampler.device().str()},
          {"precision", {{"requested", precision}, {"effective", effective_precision(resampler)}}},
          {"sampler",
           {{"steps", c.steps},
            {"rescale_t", c.rescale_t},
            {"cfg_strength", c.cfg_strength},
            {"cfg_interval", {c.cfg_interval.first, c.cfg_interval.second}},
            {"shortcut", c.shortcut},
            {"solver", c.solver},
            {"num_samples", c.num_samples},
            {"seed", options.seed}}},
          {"pose_convention", c.pose_convention},
          {"preprocess",
           {{"image_size", p.image_size},
            {"image_interpolation", p.image_interpolation},
            {"image_antialias", p.image_antialias},
            {"pointmap_size", p.pointmap_size},
            {"box_size_factor", p.box_size_factor},
            {"padding_factor", p.padding_factor},
            {"remove_background", p.remove_background},
            {"scale_mode", p.scale_mode}}}};
}

int64_t occupancy_resolution(Resampler& resampler) {
  const auto& shape = resampler.generator()->config().backbone.latent("shape");
  return shape.resolution * resampler.decoder()->config().upsample_factor();
}

torch::Tensor occupancy_grid(const torch::Tensor& coords, int64_t resolution) {
  auto grid = torch::zeros({resolution, resolution, resolution}, torch::kUInt8);
  if (!coords.defined() || coords.numel() == 0) return grid;
  const auto c = coords.to(torch::kCPU, torch::kLong);
  SIMU_CHECK(c.dim() == 2 && c.size(1) == 3, "occupancy_grid: coords must be [N, 3], got {}", c.sizes());
  SIMU_CHECK(c.min().item<int64_t>() >= 0 && c.max().item<int64_t>() < resolution,
             "occupancy_grid: coordinates outside [0, {})", resolution);
  const auto flat = (c.select(1, 0) * resolution + c.select(1, 1)) * resolution + c.select(1, 2);
  grid.view({-1}).index_fill_(0, flat, 1);
  return grid;
}

namespace {

// A folder name for an object id (ids from file names or labels: keep [A-Za-z0-9._-]).
std::string safe_name(const std::string& id) {
  std::string s;
  for (char c : id) s.push_back(std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '_' || c == '-' ? c : '_');
  if (s.empty() || s == "." || s == "..") s = "object";
  return s;
}

void write_mask_png(const torch::Tensor& mask, const std::string& path) {
#ifdef SIMU_HAVE_OPENCV
  auto m = ((mask.to(torch::kCPU, torch::kFloat32) > 0.5).to(torch::kUInt8) * 255).contiguous();
  cv::Mat img(static_cast<int>(m.size(0)), static_cast<int>(m.size(1)), CV_8UC1, m.data_ptr<uint8_t>());
  SIMU_CHECK(cv::imwrite(path, img), "{}: cannot write the mask", path);
#else
  (void)mask;
  (void)path;
#endif
}

// pose.json of one sample: SAM 3D's pose, the voxel frame, the canonical frame and the scene pose.
json sample_pose_json(const ResampledShape& sh, const ScenePose& sp, const LiftedObject& o, int64_t resolution) {
  return {
      {"sam3d",
       {{"frame", "PyTorch3D camera (x left, y up, z forward); row vectors: p = (scale * v) @ R + translation, "
                  "R = the quaternion's matrix, v in the voxel frame"},
        {"rotation_wxyz", json::array({sh.quaternion(0), sh.quaternion(1), sh.quaternion(2), sh.quaternion(3)})},
        {"translation", vec_json(sh.translation)},
        {"scale", vec_json(sh.scale)},
        {"pointmap_scale", o.scene_scale},
        {"pointmap_shift", o.scene_shift}}},
      {"voxel_frame",
       {{"definition", "v = index / R - 0.5 for voxel index (x, y, z) of occupancy.npy (R = its side)"},
        {"resolution", resolution}}},
      {"canonical",
       {{"definition", "mesh vertex c = (v - centre) * factor (AABB-centred, longest side 1)"},
        {"centre", vec_json(sh.canonical.centre)},
        {"factor", sh.canonical.factor}}},
      {"scene",
       {{"frame", "scene world (docs/scene_format.md): x = R * (scale .* c) + t for mesh vertices c; with the "
                  "default camera pose the OpenCV camera frame (x right, y down, z forward)"},
        {"R", mat_json(sp.R)},
        {"t", vec_json(sp.t)},
        {"scale", vec_json(sp.scale)}}}};
}

// One object's directory under tmp/objects/dir_name: mask, per sample occupancy, meshes and pose.json;
// its first usable sample is added to the scene. Returns the object's report.json entry.
json write_lift_object(const LiftedObject& o, const torch::Tensor& mask, const std::filesystem::path& tmp,
                       const std::string& dir_name, int64_t resolution, Scene& scene) {
  namespace sfs = std::filesystem;
  const sfs::path odir = tmp / "objects" / dir_name;
  sfs::create_directories(odir);
  json rep = {{"id", o.id}, {"ok", o.ok}, {"dir", "objects/" + dir_name}};
  if (!o.error.empty()) rep["error"] = o.error;
  if (mask.defined()) write_mask_png(mask, (odir / "mask.png").string());
  if (o.has_crop_box)
    rep["crop_box"] = {{"x1", o.crop_box.x1}, {"y1", o.crop_box.y1}, {"x2", o.crop_box.x2}, {"y2", o.crop_box.y2}};
  rep["pointmap_scale"] = o.scene_scale;
  rep["pointmap_shift"] = o.scene_shift;
  json samples = json::array();
  int first_ok = -1;
  for (size_t s = 0; s < o.samples.size(); ++s) {
    const auto& sh = o.samples[s];
    const auto& sp = o.scene_poses[s];
    const std::string sname = fmt::format("sample_{}", s);
    const sfs::path sdir = odir / sname;
    sfs::create_directories(sdir);
    json js = {{"sample", s}, {"ok", sh.ok}, {"dir", "objects/" + dir_name + "/" + sname}};
    if (!sh.ok) js["error"] = sh.message;
    if (sh.retries > 0) js["retries"] = sh.retries;  // empty decodes drawn again (ResamplerConfig::empty_retries)
    if (sh.ok && sh.retries > 0) js["note"] = sh.message;
    data::write_npy((sdir / "occupancy.npy").string(), occupancy_grid(sh.coords, resolution));
    js["occupied_voxels"] = sh.coords.defined() ? sh.coords.size(0) : 0;
    if (sh.ok) {
      const Mesh& mesh = sh.mesh;
      write_mesh(mesh, (sdir / "mesh.glb").string());
      write_mesh(mesh, (sdir / "mesh.obj").string());
      if (first_ok < 0) first_ok = static_cast<int>(s);
    }
    // Both conventions and the link between the occupancy grid, the voxel frame and the mesh.
    const json pose = sample_pose_json(sh, sp, o, resolution);
    fs::atomic_write((sdir / "pose.json").string(), pose.dump(2) + "\n");
    samples.push_back(js);
  }
  rep["samples"] = samples;
  if (first_ok >= 0) {
    SceneObject so;
    so.id = o.id;
    so.label = o.id;
    so.mesh_path = (odir / fmt::format("sample_{}", first_ok) / "mesh.glb").string();
    if (sfs::exists(odir / "mask.png")) so.mask_path = (odir / "mask.png").string();
    const auto& sp = o.scene_poses[static_cast<size_t>(first_ok)];
    so.R = sp.R;
    so.t = sp.t;
    so.scale = sp.scale;
    so.extra = {{"lift_sample", first_ok}};
    scene.objects.push_back(so);
    rep["scene_sample"] = first_ok;
  }
  return rep;
}

}  // namespace

void write_lift_outputs(const LiftResult& result, const LiftInputs& inputs, const LiftWriteOptions& options,
                        int64_t resolution) {
  namespace sfs = std::filesystem;
  SIMU_CHECK(!options.out_dir.empty(), "lift: no output directory");
  const sfs::path out = sfs::absolute(options.out_dir).lexically_normal();
  const bool exists = sfs::exists(out);
  if (exists && !options.overwrite)
    fail_hint("pass --overwrite to replace it, or choose another --out", "{}: output directory exists", out.string());
  if (exists) SIMU_CHECK(sfs::is_directory(out), "{}: exists and is not a directory", out.string());
  // Everything goes into a temporary sibling, renamed into place at the end.
  sfs::create_directories(out.parent_path());
  const sfs::path tmp = out.parent_path() / (out.filename().string() + ".tmp-" + std::to_string(::getpid()));
  fs::remove_tree(tmp.string());
  sfs::create_directories(tmp);
  try {
    Scene scene;
    scene.image_path = options.image_path.empty() ? "" : sfs::absolute(options.image_path).string();
    scene.depth_path = options.depth_path.empty() ? "" : sfs::absolute(options.depth_path).string();
    scene.camera = inputs.camera;
    scene.camera.width = static_cast<int>(inputs.rgb.size(2));
    scene.camera.height = static_cast<int>(inputs.rgb.size(1));
    // Gravity is not known from one photo: +y of the OpenCV camera (down in the image), as the scene
    // format's default for a camera-frame world; `reconstruct` fits floor and gravity.
    scene.gravity = (scene.camera.R_world_cam * Vec3::UnitY()).normalized();
    json report = {{"format", "simuscene-lift/1"}, {"run", options.run_info}, {"objects", json::array()}};
    if (!options.banner.empty()) report["warning"] = options.banner;
    report["seconds"] = {{"preprocess", result.seconds.preprocess}, {"embed", result.seconds.embed},
                         {"sample", result.seconds.sample},         {"decode", result.seconds.decode},
                         {"mesh", result.seconds.mesh},             {"pose", result.seconds.pose},
                         {"total", result.seconds.total()}};
    report["sampling_calls"] = result.sampling_calls;
    std::map<std::string, int> used;
    for (size_t i = 0; i < result.objects.size(); ++i) {
      const auto& o = result.objects[i];
      std::string dir_name = safe_name(o.id);
      if (used[dir_name]++) dir_name += "_" + std::to_string(i);
      const torch::Tensor mask = i < inputs.objects.size() ? inputs.objects[i].mask : torch::Tensor();
      auto rep = write_lift_object(o, mask, tmp, dir_name, resolution, scene);
      report["objects"].push_back(rep);
    }
    report["failed"] = result.failed();
    // scene.json is written with paths relative to its directory (the final one after the rename).
    auto sj = scene_to_json(scene, tmp.string());
    fs::atomic_write((tmp / "scene.json").string(), sj.dump(2) + "\n");
    fs::atomic_write((tmp / "report.json").string(), report.dump(2) + "\n");
  } catch (...) {
    fs::remove_tree(tmp.string());
    throw;
  }
  // Into place: swap with an existing directory (then drop the old one), else rename.
  if (exists) {
    if (fs::atomic_exchange(tmp.string(), out.string())) {
      fs::remove_tree(tmp.string());
      return;
    }
    fs::remove_tree(out.string());
  }
  fs::atomic_rename(tmp.string(), out.string());
}

}  // namespace simu::resample
