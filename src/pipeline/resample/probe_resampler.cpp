#include "pipeline/resample/probe_resampler.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <filesystem>

#include "common/error.h"
#include "common/log.h"
#include "pipeline/resample/lift.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

namespace simu::resample {

using physics::Camera;
using physics::MaskImage;
using physics::ProbeResampleRequest;
using physics::ProbeResampleResult;
using physics::ProbeShapeCandidate;
using physics::ResampleFn;
using physics::Scene;

namespace {
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
  // [H, W, 3] OpenCV -> [3, H, W] PyTorch3D frame.
  return data::pointmap_from_opencv_camera(read_scene_pointmap(path, camera).permute({2, 0, 1}).contiguous());
}

#ifdef SIMU_HAVE_OPENCV
namespace {

// The lift inputs of one probe call: the scene's image and point map, each request's modal mask and crop
// mask M' (a mask that cannot be read becomes that object's error). Throws when the image or the point
// map cannot be read.
LiftInputs probe_lift_inputs(const Scene& scene, const std::vector<ProbeResampleRequest>& requests) {
  LiftInputs in;
  in.camera = scene.camera;
  const std::string image = scene.image_path.empty() && !requests.empty() ? requests[0].image_path : scene.image_path;
  SIMU_CHECK(!image.empty(), "the scene has no image");
  in.rgb = data::read_image_rgb(image);
  SIMU_CHECK(!scene.depth_path.empty(), "the scene has no depth (depth_path), needed for the point map");
  in.pointmap = read_scene_pointmap(scene.depth_path, scene.camera);
  for (const auto& rq : requests) {
    LiftObjectInput o;
    o.id = rq.object_id;
    try {
      o.mask = mask_tensor(rq.modal_mask);
      if (!rq.aux_mask.empty()) o.crop_mask = mask_tensor(rq.aux_mask);
    } catch (const std::exception& e) {
      o.error = fmt::format("object '{}': {}", rq.object_id, e.what());
    }
    in.objects.push_back(std::move(o));
  }
  return in;
}

// One object's lifted samples as the probe's result: the crop box, the usable samples as candidates
// (rotation and scale in the scene convention; the probe sets the translation), the failed ones named.
ProbeResampleResult probe_result(const LiftedObject& lo_i, uint64_t seed) {
  ProbeResampleResult res;
  if (lo_i.has_crop_box) {
    // Report the crop box taken from M' (the amodal crop).
    res.crop_box = {static_cast<int>(lo_i.crop_box.x1), static_cast<int>(lo_i.crop_box.y1),
                    static_cast<int>(lo_i.crop_box.x2), static_cast<int>(lo_i.crop_box.y2)};
    res.has_crop_box = true;
  }
  if (lo_i.samples.empty()) {
    res.ok = false;
    res.message = lo_i.error.empty() ? "no sample" : lo_i.error;
    return res;
  }
  std::vector<ProbeShapeCandidate> good;
  std::vector<std::string> failed;
  for (size_t s = 0; s < lo_i.samples.size(); ++s) {
    const auto& sample = lo_i.samples[s];
    const std::string label = fmt::format("sample {} of {} (seed {})", s, lo_i.samples.size(), seed);
    if (!sample.ok) {
      failed.push_back(fmt::format("{}: {}", label, sample.message));
      continue;
    }
    ProbeShapeCandidate c;
    c.label = label;
    c.mesh = sample.mesh;
    c.R = lo_i.scene_poses[s].R;
    c.scale = lo_i.scene_poses[s].scale;
    good.push_back(std::move(c));
  }
  const std::string failed_note = failed.empty() ? "" : fmt::format("; failed: {}", fmt::join(failed, "; "));
  if (good.empty()) {
    res.ok = false;
    res.message = fmt::format("no usable sample{}", failed_note);
    return res;
  }
  res.ok = true;
  res.mesh = good[0].mesh;
  res.R = good[0].R;
  res.scale = good[0].scale;
  // Several usable samples: the probe picks the most stable one (best-of-N).
  res.message = good.size() == 1 ? good[0].label + failed_note : fmt::format("{} candidates{}", good.size(), failed_note);
  if (good.size() >= 2) res.candidates = std::move(good);
  return res;
}

}  // namespace
#endif

ResampleFn make_probe_resample_fn(Resampler& resampler, const Scene& scene, ProbeResamplerOptions options) {
  // The scene's image and depth files must exist: an error naming the file before any probing.
  for (const auto& [path, what] : {std::pair<std::string, const char*>{scene.image_path, "image"},
                                   std::pair<std::string, const char*>{scene.depth_path, "depth"}})
    SIMU_CHECK(path.empty() || std::filesystem::exists(path), "{}: the scene's {} file is not found", path, what);
  return [&resampler, scene, options](const std::vector<ProbeResampleRequest>& requests) {
    std::vector<ProbeResampleResult> results(requests.size());
#ifdef SIMU_HAVE_OPENCV
    // Every object's error when the shared inputs or the batched lift fail.
    auto fail_all = [&](const std::exception& e) {
      for (size_t i = 0; i < requests.size(); ++i)
        results[i].message = fmt::format("object '{}': {}", requests[i].object_id, e.what());
      return results;
    };
    LiftInputs in;
    try {
      in = probe_lift_inputs(scene, requests);
    } catch (const std::exception& e) {
      return fail_all(e);
    }
    LiftOptions lo;
    lo.preprocess = options.preprocess;
    lo.seed = options.seed;
    lo.resampling = true;  // an adapter for resampling only stays on
    LiftResult lifted;
    try {
      lifted = lift_objects(resampler, in, lo);  // one batched resampling call for every object
    } catch (const std::exception& e) {
      return fail_all(e);
    }
    for (size_t i = 0; i < requests.size(); ++i) results[i] = probe_result(lifted.objects[i], options.seed);
    const auto& t = lifted.seconds;
    log::info("resampled {} object(s) in one batched call: embed {:.2f} s, sample {:.2f} s, decode {:.2f} s, mesh {:.2f} s",
              lifted.objects.size() - lifted.failed(), t.embed, t.sample, t.decode, t.mesh);
#else
    for (auto& r : results) r.message = "resampling from images needs OpenCV (built with SIMU_WITH_OPENCV=OFF)";
#endif
    return results;
  };
}

}  // namespace simu::resample
