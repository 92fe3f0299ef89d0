#include "pipeline/reconstruct/synthetic_inputs.h"

#include "common/error.h"

#include <fmt/format.h>

#include <filesystem>
#include <set>

namespace simu::reconstruct {

ReconstructInputs camera_scene_inputs(const CameraScene& s, const std::string& dir, bool with_meshes) {
  const int W = s.K.width, H = s.K.height;
  SIMU_CHECK(int64_t(s.rgb.size()) == int64_t(W) * H * 3 && int64_t(s.labels.size()) == int64_t(W) * H,
             "camera_scene_inputs: the scene's images are not {}x{}", W, H);
  ReconstructInputs in;
  in.sidecar_name = (std::filesystem::path(dir) / "objects.json").string();
  in.specs = read_sidecar(in.sidecar_name, &in.messages);
  if (!with_meshes)
    for (auto& sp : in.specs) sp.mesh.clear(), sp.pose.clear();
  auto& L = in.lift;
  // [3, H, W] RGB in [0, 1].
  L.rgb = torch::from_blob(const_cast<uint8_t*>(s.rgb.data()), {H, W, 3}, torch::kUInt8)
              .permute({2, 0, 1})
              .to(torch::kFloat32)
              .div(255.0)
              .contiguous();
  // [H, W, 3] point map, NaN where nothing was drawn.
  L.pointmap = torch::empty({H, W, 3}, torch::kFloat32);
  float* pm = L.pointmap.data_ptr<float>();
  for (size_t i = 0; i < s.points.p.size(); ++i)
    for (int k = 0; k < 3; ++k) pm[3 * i + k] = float(s.points.p[i][k]);
  L.camera.fx = s.K.fx, L.camera.fy = s.K.fy, L.camera.cx = s.K.cx, L.camera.cy = s.K.cy;
  L.camera.width = W, L.camera.height = H;
  // One mask per label value present, ids "label_<k>" as load_lift_inputs names a label image's.
  std::set<int> values(s.labels.begin(), s.labels.end());
  values.erase(0);
  for (int v : values) {
    resample::LiftObjectInput o;
    o.id = fmt::format("label_{}", v);
    o.mask = torch::empty({H, W}, torch::kFloat32);
    float* m = o.mask.data_ptr<float>();
    for (size_t i = 0; i < s.labels.size(); ++i) m[i] = s.labels[i] == v ? 1.0f : 0.0f;
    L.objects.push_back(o);
  }
  return in;
}

}  // namespace simu::reconstruct
