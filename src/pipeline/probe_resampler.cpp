#include "pipeline/probe_resampler.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "common/error.h"
#include "common/log.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

namespace simu::pipeline {

namespace {
// PyTorch3D camera axes (x left, y up, z forward) -> OpenCV camera axes (x right, y down, z forward).
const Mat3 kP3dToOpenCv = Eigen::Vector3d(-1, -1, 1).asDiagonal();

#ifdef SIMU_HAVE_OPENCV
// An 8-bit mask image -> [H, W] float tensor in {0, 1}.
torch::Tensor mask_tensor(const MaskImage& m) {
  SIMU_CHECK(!m.empty() && m.type() == CV_8UC1, "mask must be a non-empty 8-bit single-channel image");
  auto t = torch::from_blob(const_cast<uint8_t*>(m.ptr<uint8_t>()), {m.rows, m.cols},
                            {static_cast<int64_t>(m.step[0]), 1}, torch::kUInt8);
  return (t > 0).to(torch::kFloat32).clone();
}
#endif
}  // namespace

torch::Tensor pointmap_from_depth_file(const std::string& path, const Camera& camera) {
#ifdef SIMU_HAVE_OPENCV
  cv::Mat depth = cv::imread(path, cv::IMREAD_ANYDEPTH | cv::IMREAD_GRAYSCALE);
  SIMU_CHECK(!depth.empty(), "{}: cannot read the depth image", path);
  cv::Mat metres;
  // 16-bit PNGs hold millimetres; float images hold metres.
  if (depth.depth() == CV_16U)
    depth.convertTo(metres, CV_32F, 1e-3);
  else
    depth.convertTo(metres, CV_32F);
  const int h = metres.rows, w = metres.cols;
  auto z = torch::from_blob(metres.ptr<float>(), {h, w}, torch::kFloat32).clone();  // [H, W]
  z = torch::where(torch::isfinite(z) & (z > 0), z, torch::full_like(z, NAN));
  // OpenCV camera back-projection, then PyTorch3D axes.
  auto v = torch::arange(h, torch::kFloat32).unsqueeze(1).expand({h, w});
  auto u = torch::arange(w, torch::kFloat32).unsqueeze(0).expand({h, w});
  auto x = (u - camera.cx) / camera.fx * z;
  auto y = (v - camera.cy) / camera.fy * z;
  return data::pointmap_from_opencv_camera(torch::stack({x, y, z}));  // [3, H, W]
#else
  (void)camera;
  fail("{}: reading depth images needs OpenCV (built with SIMU_WITH_OPENCV=OFF)", path);
#endif
}

ResampleFn make_probe_resample_fn(Resampler& resampler, const Scene& scene, ProbeResamplerOptions options) {
  return [&resampler, scene, options](const std::vector<ProbeResampleRequest>& requests) {
    std::vector<ProbeResampleResult> results(requests.size());
#ifdef SIMU_HAVE_OPENCV
    // Condition inputs per object; failures are reported per object.
    // An unreadable depth file fails every object with the file's name (not the whole call).
    torch::Tensor pointmap;
    std::string depth_error;
    if (!scene.depth_path.empty()) {
      try {
        pointmap = pointmap_from_depth_file(scene.depth_path, scene.camera);
      } catch (const std::exception& e) {
        depth_error = e.what();
      }
    }
    std::vector<ResampleRequest> batch;
    std::vector<size_t> batch_index;
    for (size_t i = 0; i < requests.size(); ++i) {
      const auto& rq = requests[i];
      try {
        SIMU_CHECK(depth_error.empty(), "object '{}': {}", rq.object_id, depth_error);
        const std::string image = rq.image_path.empty() ? scene.image_path : rq.image_path;
        SIMU_CHECK(!image.empty(), "object '{}': the scene has no image", rq.object_id);
        const auto rgb = data::read_image_rgb(image);
        const auto modal = mask_tensor(rq.modal_mask);
        const auto aux = rq.aux_mask.empty() ? torch::Tensor() : mask_tensor(rq.aux_mask);
        SIMU_CHECK(pointmap.defined(), "object '{}': the scene has no depth (depth_path), needed for the point map",
                   rq.object_id);
        auto prepared = data::prepare_condition_inputs(rgb, modal, pointmap, options.preprocess, aux);
        // Report the crop box taken from M' (the amodal crop).
        results[i].crop_box = {static_cast<int>(prepared.crop_box.x1), static_cast<int>(prepared.crop_box.y1),
                               static_cast<int>(prepared.crop_box.x2), static_cast<int>(prepared.crop_box.y2)};
        results[i].has_crop_box = true;
        ResampleRequest r;
        r.inputs = prepared.tensors;
        // Points nearer than the object (normalised z <= -1) go to the embedder as they are: with the
        // released `linear` remap they are ordinary values (as in the official code); PointPatchEmbed
        // itself handles the `exp` remap's domain (models/point_patch_embed.h).
        if (prepared.pointmap_scale.defined()) {
          r.scene_scale = prepared.pointmap_scale.reshape({-1})[0].item<double>();
          for (int k = 0; k < 3; ++k) r.scene_shift[k] = prepared.pointmap_shift.reshape({-1})[k].item<double>();
        }
        batch.push_back(std::move(r));
        batch_index.push_back(i);
      } catch (const std::exception& e) {
        results[i].ok = false;
        // Every message names the object.
        const std::string m = e.what();
        results[i].message = m.rfind("object '", 0) == 0 ? m : fmt::format("object '{}': {}", rq.object_id, m);
      }
    }
    if (batch.empty()) return results;
    // One batched resampling call for every object of the scene.
    const auto out = resampler.resample(batch, options.seed);
    for (size_t b = 0; b < batch.size(); ++b) {
      auto& res = results[batch_index[b]];
      const auto& samples = out.objects[b];
      // Decoded rotation is in the PyTorch3D camera frame; the scene's world frame is the camera's
      // (OpenCV axes) moved by the camera pose.
      std::vector<ProbeShapeCandidate> good;
      std::vector<std::string> failed;
      for (size_t s = 0; s < samples.size(); ++s) {
        const std::string label = fmt::format("sample {} of {} (seed {})", s, samples.size(), options.seed);
        if (!samples[s].ok) {
          failed.push_back(fmt::format("{}: {}", label, samples[s].message));
          continue;
        }
        ProbeShapeCandidate c;
        c.label = label;
        c.mesh.V = samples[s].mesh.V;
        c.mesh.F = samples[s].mesh.F;
        c.R = scene.camera.R_world_cam * kP3dToOpenCv * samples[s].rotation;
        c.scale = samples[s].scale_canonical;
        good.push_back(std::move(c));
      }
      const std::string failed_note = failed.empty() ? "" : fmt::format("; failed: {}", fmt::join(failed, "; "));
      if (good.empty()) {
        res.ok = false;
        res.message = samples.empty() ? "no sample" : fmt::format("no usable sample{}", failed_note);
        continue;
      }
      res.ok = true;
      res.mesh = good[0].mesh;
      res.R = good[0].R;
      res.scale = good[0].scale;
      // Several usable samples: the probe picks the most stable one (best-of-N).
      res.message = good.size() == 1 ? good[0].label + failed_note
                                     : fmt::format("{} candidates{}", good.size(), failed_note);
      if (good.size() >= 2) res.candidates = std::move(good);
    }
    log::info("resampled {} object(s) in one batched call: embed {:.2f} s, sample {:.2f} s, decode {:.2f} s, mesh {:.2f} s",
              batch.size(), out.seconds_embed, out.seconds_sample, out.seconds_decode, out.seconds_mesh);
#else
    for (auto& r : results) r.message = "resampling from images needs OpenCV (built with SIMU_WITH_OPENCV=OFF)";
#endif
    return results;
  };
}

}  // namespace simu::pipeline
