#include "training/stage1_data.h"

#include <ATen/CPUGeneratorImpl.h>

#include <cmath>
#include <algorithm>
#include <functional>
#include <mutex>

#include "common/error.h"
#include "common/log.h"
#include "common/parallel.h"
#include "common/progress.h"

namespace simu::training {

std::shared_ptr<const Stage1Samples> load_stage1_samples(const std::string& cache, data::SampleSplit split,
                                                         bool progress, int64_t chunk, int threads) {
  const auto reader = data::Stage1CacheReader::open(cache);
  const auto& info = reader.info();
  const auto& splits = reader.splits();
  const int64_t wanted = info.counts[static_cast<int>(split)];
  if (wanted == 0)
    fail_hint("build the cache with samples of that split (build_stage1_data --split)",
              "stage-1 cache '{}' has no {} samples ({} train, {} val, {} test)", cache, data::split_name(split),
              info.counts[0], info.counts[1], info.counts[2]);
  // Chunks of records, read on `threads` threads (each keeps the rows of the split), joined in order.
  const int64_t chunks = (info.size + chunk - 1) / chunk;
  std::vector<data::Stage1Rows> parts(static_cast<size_t>(chunks));
  std::mutex mu;
  int64_t done = 0;
  std::unique_ptr<simu::Progress> bar;
  if (progress) bar = std::make_unique<simu::Progress>("loading " + cache, "records");
  simu::parallel_for_each(chunks, threads, [&](int64_t c) {
    const int64_t start = c * chunk, count = std::min(chunk, info.size - start);
    std::vector<int64_t> keep;
    for (int64_t i = start; i < start + count; ++i)
      if (splits[i] == static_cast<uint8_t>(split)) keep.push_back(i - start);
    if (!keep.empty()) {
      auto rows = reader.read_rows(start, count);
      if (static_cast<int64_t>(keep.size()) != count) {
        const auto idx = torch::tensor(keep, torch::kInt64);
        for (auto& [k, v] : rows.inputs) v = v.index_select(0, idx);
        for (auto& [k, v] : rows.pose) v = v.index_select(0, idx);
        rows.occupancy = rows.occupancy.index_select(0, idx);
        std::vector<int64_t> index;
        for (int64_t j : keep) index.push_back(rows.index[j]);
        rows.index = index;
      }
      parts[c] = std::move(rows);
    }
    std::lock_guard<std::mutex> lock(mu);
    done += count;
    if (bar) (*bar)(done, info.size);
  });
  parts.erase(std::remove_if(parts.begin(), parts.end(), [](const data::Stage1Rows& r) { return r.index.empty(); }),
              parts.end());
  auto out = std::make_shared<Stage1Samples>();
  auto cat = [&](const std::function<torch::Tensor(const data::Stage1Rows&)>& get) {
    std::vector<torch::Tensor> ts;
    for (const auto& p : parts) ts.push_back(get(p));
    return torch::cat(ts, 0);
  };
  for (const auto& name : data::condition_input_names())
    out->inputs[name] = cat([&](const data::Stage1Rows& r) { return r.inputs.at(name); });
  for (const auto& [name, k] : data::stage1_pose_latents())
    out->pose[name] = cat([&](const data::Stage1Rows& r) { return r.pose.at(name); });
  out->occupancy = cat([](const data::Stage1Rows& r) { return r.occupancy; });
  for (const auto& p : parts) out->ids.insert(out->ids.end(), p.index.begin(), p.index.end());
  int64_t bytes = out->occupancy.nbytes();
  for (const auto& [k, v] : out->inputs) bytes += v.nbytes();
  log::info("stage-1 samples: {} {} records of {} in memory ({:.2f} GB: images {}, point maps {})", out->size(),
            data::split_name(split), cache, bytes / 1e9, info.image_dtype, info.pointmap_dtype);
  return out;
}

std::shared_ptr<Stage1Samples> synthetic_stage1_samples(int64_t n, int64_t S, int64_t P, int64_t R, uint64_t seed) {
  auto gen = at::make_generator<at::CPUGeneratorImpl>(seed);
  const auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  namespace F = torch::nn::functional;
  auto smooth = [&](int64_t ch, int64_t side) {  // [n, ch, side, side] in [0, 1]
    return F::interpolate(at::rand({n, ch, 4, 4}, gen, f32),
                          F::InterpolateFuncOptions().size(std::vector<int64_t>{side, side}).mode(torch::kBilinear).align_corners(false));
  };
  auto s = std::make_shared<Stage1Samples>();
  for (int64_t i = 0; i < n; ++i) s->ids.push_back(i);
  for (const char* name : {"image", "rgb_image"}) s->inputs[name] = (smooth(3, S) * 255).round().to(torch::kByte);
  for (const char* name : {"mask", "rgb_image_mask"}) {
    auto m = torch::zeros({n, 1, S, S}, torch::kByte);
    m.slice(2, S / 4, 3 * S / 4).slice(3, S / 3, 2 * S / 3).fill_(255);
    s->inputs[name] = m;
  }
  for (const char* name : {"pointmap", "rgb_pointmap"}) {
    auto p = smooth(3, P) * 2 - 1;
    p.slice(2, 0, 1).slice(3, 0, 1).fill_(NAN);
    s->inputs[name] = p.to(torch::kFloat16);
  }
  s->occupancy = (at::rand({n, R, R, R}, gen, f32) < 0.3).to(torch::kByte);
  for (const auto& [name, k] : data::stage1_pose_latents()) s->pose[name] = at::randn({n, k}, gen, f32);
  return s;
}

std::map<std::string, torch::Tensor> decode_inputs(const std::map<std::string, torch::Tensor>& stored) {
  std::map<std::string, torch::Tensor> out;
  // float(k) * float(1/255): one float32 product, as the cache reader's u8 levels.
  const float level = static_cast<float>(1.0 / 255.0);
  for (const auto& [name, v] : stored)
    out[name] = v.scalar_type() == torch::kByte ? v.to(torch::kFloat32) * level : v.to(torch::kFloat32);
  return out;
}

std::map<std::string, torch::Tensor> pose_latents(const std::map<std::string, torch::Tensor>& pose_rows) {
  std::map<std::string, torch::Tensor> out;
  for (const auto& [name, v] : pose_rows) out[name] = v.to(torch::kFloat32).unsqueeze(1);  // [m, 1, k]
  return out;
}

}  // namespace simu::training
