// The reconstruct front end's masks and point maps (run_detail.h): from the lift's tensors, dilated,
// sampled, written as PNG.
#include "pipeline/reconstruct/run_detail.h"

#include "common/error.h"

#ifdef SIMU_HAVE_OPENCV
#include <opencv2/imgcodecs.hpp>
#endif

#include <cmath>
#include <cstring>

namespace simu::reconstruct::detail {

// The lift's point map tensor [H, W, 3] -> PointMap (invalid points NaN).
PointMap to_point_map(const torch::Tensor& pm) {
  const auto t = pm.to(torch::kCPU, torch::kFloat64).contiguous();
  PointMap m;
  m.height = int(t.size(0));
  m.width = int(t.size(1));
  m.p.resize(size_t(m.width) * m.height);
  const double* d = t.data_ptr<double>();
  for (size_t i = 0; i < m.p.size(); ++i) {
    m.p[i] = Vec3(d[3 * i], d[3 * i + 1], d[3 * i + 2]);
    if (!PointMap::valid(m.p[i])) m.p[i] = Vec3::Constant(std::nan(""));
  }
  return m;
}

// A mask tensor [H, W] -> Mask (values > 0 set).
Mask to_mask(const torch::Tensor& t) {
  const auto m = (t.to(torch::kCPU, torch::kFloat32) > 0).to(torch::kUInt8).contiguous();
  Mask out(int(m.size(1)), int(m.size(0)));
  std::memcpy(out.data.data(), m.data_ptr<uint8_t>(), out.data.size());
  return out;
}

// Writes a mask PNG; false (nothing written) without OpenCV.
bool write_mask(const Mask& m, const std::string& path) {
#ifdef SIMU_HAVE_OPENCV
  cv::Mat img(m.height, m.width, CV_8UC1);
  for (int r = 0; r < m.height; ++r)
    for (int c = 0; c < m.width; ++c) img.at<uint8_t>(r, c) = m.at(r, c) ? 255 : 0;
  SIMU_CHECK(cv::imwrite(path, img), "{}: cannot write the mask", path);
  return true;
#else
  (void)m;
  (void)path;
  return false;
#endif
}

// Square dilation of a mask by r pixels (separable running maximum).
Mask dilate(const Mask& m, int r) {
  Mask rows(m.width, m.height), out(m.width, m.height);
  for (int y = 0; y < m.height; ++y)
    for (int x = 0; x < m.width; ++x)
      if (m.at(y, x))
        for (int k = std::max(0, x - r); k <= std::min(m.width - 1, x + r); ++k) rows.at(y, k) = 1;
  for (int y = 0; y < m.height; ++y)
    for (int x = 0; x < m.width; ++x)
      if (rows.at(y, x))
        for (int k = std::max(0, y - r); k <= std::min(m.height - 1, y + r); ++k) out.at(k, x) = 1;
  return out;
}

// The valid points of a point map, every `stride`-th pixel, leaving out pixels under `exclude` (may be empty).
Points sample_points(const PointMap& pm, int stride, const Mask* exclude) {
  std::vector<Vec3> v;
  for (size_t i = 0; i < pm.p.size(); i += size_t(stride))
    if (PointMap::valid(pm.p[i]) && !(exclude && exclude->data[i])) v.push_back(pm.p[i]);
  Points all(Eigen::Index(v.size()), 3);
  for (size_t i = 0; i < v.size(); ++i) all.row(Eigen::Index(i)) = v[i].transpose();
  return all;
}

}  // namespace simu::reconstruct::detail
