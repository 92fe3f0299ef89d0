#include "training/ss_vae_eval.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <map>

#include "common/error.h"
#include "common/parallel.h"
#include "models/precision.h"

namespace simu::training {

namespace {
const std::vector<int64_t> kVoxelDims = {1, 2, 3, 4};
}  // namespace

SsVaeTerms ss_vae_terms(const torch::Tensor& logits, const torch::Tensor& occupancy, const torch::Tensor& mean,
                        const torch::Tensor& logvar, const SsVaeLossConfig& loss) {
  SIMU_CHECK(logits.sizes() == occupancy.sizes() && logits.dim() == 5,
             "ss_vae_terms: logits {} and occupancy {} must both be [B, 1, R, R, R]", logits.sizes(), occupancy.sizes());
  SsVaeTerms t;
  const auto y = occupancy;
  const auto p = torch::sigmoid(logits);
  t.bce = torch::binary_cross_entropy_with_logits(logits, y, {}, {}, at::Reduction::None).mean(kVoxelDims);  // [B]
  const auto inter = (p * y).sum(kVoxelDims);
  t.dice = 1 - (2 * inter + 1) / (p.sum(kVoxelDims) + y.sum(kVoxelDims) + 1);
  t.l1 = (p - y).abs().mean(kVoxelDims);
  t.kl = models::kl_to_standard_normal(mean, logvar).mean(kVoxelDims);
  t.total = loss.bce * t.bce + loss.dice * t.dice + loss.l1 * t.l1 + loss.lambda_kl * t.kl;
  t.iou = occupancy_iou(logits.detach(), y);
  return t;
}

torch::Tensor occupancy_iou(const torch::Tensor& logits, const torch::Tensor& occupancy) {
  const auto pred = logits > 0, occ = occupancy > 0;
  const auto inter = (pred & occ).sum(kVoxelDims).to(torch::kFloat32);
  const auto uni = (pred | occ).sum(kVoxelDims).to(torch::kFloat32);
  // Both empty: a perfect reconstruction.
  return torch::where(uni > 0, inter / uni.clamp_min(1), torch::ones_like(uni));
}

std::vector<double> reconstruction_iou(models::SparseStructureEncoderImpl& encoder,
                                       models::SparseStructureDecoderImpl& decoder, const ShapeSet& shapes,
                                       const std::vector<ShapeKey>& keys, int64_t batch, int workers, bool bf16) {
  const auto device = encoder.input_layer->weight.device();
  const int64_t R = shapes.resolution, n = static_cast<int64_t>(keys.size());
  std::vector<double> out;
  out.reserve(keys.size());
  torch::NoGradGuard no_grad;
  for (int64_t start = 0; start < n; start += batch) {
    const int64_t b = std::min(batch, n - start);
    // The chunk's grids (and the encoder's, when it reads another), made in parallel, one row each.
    const int64_t Ri = shapes.input_occupancy ? shapes.input_resolution : R;
    auto grids = torch::empty({b, 1, R, R, R}, torch::kUInt8);
    auto inputs = shapes.input_occupancy ? torch::empty({b, 1, Ri, Ri, Ri}, torch::kUInt8) : grids;
    parallel_for_each(b, workers, [&](int64_t j) {
      const auto& key = keys[start + j];
      const auto g = shapes.occupancy(key);
      SIMU_CHECK(static_cast<int64_t>(g.size()) == R * R * R, "shape {} seed {}: occupancy of {} voxels, {} expected",
                 key.family, key.seed, g.size(), R * R * R);
      std::memcpy(grids[j].data_ptr<uint8_t>(), g.data(), g.size());
      if (!shapes.input_occupancy) return;
      const auto in = shapes.input_occupancy(key);
      SIMU_CHECK(static_cast<int64_t>(in.size()) == Ri * Ri * Ri, "shape {} seed {}: encoder input of {} voxels, {} expected",
                 key.family, key.seed, in.size(), Ri * Ri * Ri);
      std::memcpy(inputs[j].data_ptr<uint8_t>(), in.data(), in.size());
    });
    const auto occ = (grids > 0).to(device, torch::kFloat32);   // [b, 1, R, R, R]
    const auto in = (inputs > 0).to(device, torch::kFloat32);   // [b, 1, Ri, Ri, Ri]
    torch::Tensor logits;
    {
      models::Autocast ac(models::Precision::kBf16, bf16 && device.is_cuda());
      const auto mean = encoder.posterior(in).first;
      logits = decoder.forward(mean).to(torch::kFloat32);
    }
    const auto iou = occupancy_iou(logits, occ).to(torch::kCPU, torch::kFloat64);
    for (int64_t j = 0; j < b; ++j) out.push_back(iou[j].item<double>());
  }
  return out;
}

IouTable iou_table(const std::vector<ShapeKey>& keys, const std::vector<double>& iou, const std::string& held_out_family) {
  SIMU_CHECK(keys.size() == iou.size(), "iou_table: {} shapes but {} IoU values", keys.size(), iou.size());
  IouTable t;
  std::vector<std::string> order;
  std::map<std::string, std::vector<double>> by_family;
  for (size_t i = 0; i < keys.size(); ++i) {
    if (!by_family.count(keys[i].family)) order.push_back(keys[i].family);
    by_family[keys[i].family].push_back(iou[i]);
  }
  double sum_seen = 0, sum_held = 0;
  for (const auto& family : order) {
    auto v = by_family[family];
    std::sort(v.begin(), v.end());
    IouTable::Row row;
    row.family = family;
    row.n = static_cast<int64_t>(v.size());
    row.held_out = !held_out_family.empty() && family == held_out_family;
    double sum = 0;
    for (double x : v) sum += x;
    row.mean = sum / row.n;
    row.min = v.front();
    row.median = v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
    (row.held_out ? sum_held : sum_seen) += sum;
    (row.held_out ? t.n_held_out : t.n_seen) += row.n;
    t.rows.push_back(row);
  }
  t.mean_seen = t.n_seen ? sum_seen / t.n_seen : NAN;
  t.mean_held_out = t.n_held_out ? sum_held / t.n_held_out : NAN;
  return t;
}

nlohmann::json IouTable::to_json() const {
  // NaN is not JSON: an absent group is null.
  auto num = [](double v) { return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(); };
  nlohmann::json fam = nlohmann::json::array();
  for (const auto& r : rows)
    fam.push_back({{"family", r.family}, {"n", r.n}, {"iou_mean", r.mean}, {"iou_median", r.median}, {"iou_min", r.min},
                   {"held_out", r.held_out}});
  return {{"families", fam},
          {"seen", {{"n", n_seen}, {"iou_mean", num(mean_seen)}}},
          {"held_out", {{"n", n_held_out}, {"iou_mean", num(mean_held_out)}}}};
}

std::string IouTable::markdown() const {
  std::string s = "| family | n | IoU mean | IoU median | IoU min |\n| --- | ---: | ---: | ---: | ---: |\n";
  for (const auto& r : rows)
    s += fmt::format("| {}{} | {} | {:.3f} | {:.3f} | {:.3f} |\n", r.family, r.held_out ? " (held out)" : "", r.n, r.mean,
                     r.median, r.min);
  s += fmt::format("| all seen families | {} | {:.3f} | | |\n", n_seen, mean_seen);
  if (n_held_out) s += fmt::format("| held-out family | {} | {:.3f} | | |\n", n_held_out, mean_held_out);
  return s;
}

}  // namespace simu::training
