// FM-DPO's staging, forward/backward and metrics as the trainer's objective (fmdpo_objective.h).
#include "training/fmdpo_objective.h"

#include <algorithm>

#include "common/error.h"
#include "models/precision.h"
#include "training/staging.h"
#include "training/trainer.h"

namespace simu::training {

namespace {

const char* kKindNames[2] = {"completion", "preservation"};

// One forward group's inputs, stacked [m, ...] in their stored dtype on the trainer's device.
struct PairGroup {
  std::vector<int> kinds;                        // the pairs' kinds, in order
  torch::Tensor x_pos, x_neg, eps_pos, eps_neg;  // [m, T, C]
  torch::Tensor t, w;                            // [m]
  torch::Tensor cond;                            // [m, L, Cc] tokens; undefined in inputs mode
  std::map<std::string, torch::Tensor> inputs;   // inputs mode: kwarg -> [m, ch, S, S]
  Uploads uploads;
  // The device tensors above.
  std::vector<torch::Tensor*> device_tensors() {
    std::vector<torch::Tensor*> out = {&x_pos, &x_neg, &eps_pos, &eps_neg, &t, &w};
    if (cond.defined()) out.push_back(&cond);
    for (auto& [name, v] : inputs) out.push_back(&v);
    return out;
  }
};

struct PairBatch : StagedBatch {
  std::vector<PairGroup> groups;
  std::vector<int> kinds;  // every pair's kind, in group order (the terms' column order)
};

// Micro-batches of `micro` pairs; within one, pairs with different condition lengths run as separate
// forwards (the model has no condition mask, so padding would change the result).
std::vector<std::vector<int64_t>> forward_groups(const std::vector<Pair>& pairs, int64_t micro) {
  const int64_t share = static_cast<int64_t>(pairs.size());
  std::vector<std::vector<int64_t>> groups;
  for (int64_t m0 = 0; m0 < share; m0 += micro) {
    std::map<int64_t, std::vector<int64_t>> by_len;
    // Inputs-mode pairs (no tokens yet) all give the embedder's one length: key -1.
    for (int64_t i = m0; i < std::min(share, m0 + micro); ++i)
      by_len[pairs[i].cond.defined() ? pairs[i].cond.size(0) : -1].push_back(i);
    for (auto& [len, idx] : by_len) groups.push_back(idx);
  }
  return groups;
}

}  // namespace

std::vector<double> StepSums::pack() const {
  std::vector<double> v = {loss, correct, margin};
  for (const auto& k : kind) v.insert(v.end(), {k.count, k.policy_pos, k.policy_neg, k.ref_pos, k.ref_neg});
  return v;
}

StepSums StepSums::unpack(const std::vector<double>& v) {
  SIMU_CHECK(v.size() == 13, "step sums: {} values, 13 expected", v.size());
  StepSums s;
  s.loss = v[0];
  s.correct = v[1];
  s.margin = v[2];
  for (int k = 0; k < 2; ++k) s.kind[k] = {v[3 + 5 * k], v[4 + 5 * k], v[5 + 5 * k], v[6 + 5 * k], v[7 + 5 * k]};
  return s;
}

FmdpoObjective::FmdpoObjective(TrainConfig cfg, PolicyModel& model, PairSourceFactory sources, torch::Device device)
    : cfg_(std::move(cfg)), model_(model), make_source_(std::move(sources)), device_(device) {}

void FmdpoObjective::open_data(int rank, int world, int64_t global_batch, uint64_t seed, DataPosition position) {
  source_.reset();
  source_ = make_source_(rank, world, global_batch, seed, position);
}

std::unique_ptr<StagedBatch> FmdpoObjective::read_batch(int64_t step, const UploadStream& stream) {
  auto b = std::make_unique<PairBatch>();
  b->position = source_->position();
  b->step = step;
  const auto pairs = source_->next_batch();
  b->samples = static_cast<int64_t>(pairs.size());
  for (const auto& group : forward_groups(pairs, cfg_.data.micro_batch)) {
    PairGroup g;
    auto up = [&](const std::vector<torch::Tensor>& parts) { return stack_to(parts, device_, stream, g.uploads.host); };
    // Stack the pairs, draw their noise (per pair: independent of rank, micro-batch and read-ahead).
    std::vector<torch::Tensor> xp, xn, ts, ep, en, ws;
    for (int64_t i : group) {
      const Pair& p = pairs[i];
      auto nz = draw_pair_noise(cfg_.train.seed, step, p.id, p.x_pos.sizes(), cfg_.objective.t_mean, cfg_.objective.t_std);
      xp.push_back(p.x_pos);
      xn.push_back(p.x_neg);
      ts.push_back(nz.t);
      ep.push_back(nz.eps_pos);
      en.push_back(nz.eps_neg);
      ws.push_back(torch::tensor(static_cast<float>(cfg_.objective.weight_of(p.kind))));
      g.kinds.push_back(static_cast<int>(p.kind));
    }
    // Stored dtype (f16 or f32) across the bus, fp32 on the device: the host does no conversion work.
    g.x_pos = up(xp);
    g.x_neg = up(xn);
    g.t = up(ts);
    g.eps_pos = up(ep);
    g.eps_neg = up(en);
    g.w = up(ws);
    // The condition: the pairs' tokens, or the embedder's inputs (embedded in the step).
    if (pairs[group.front()].cond.defined()) {
      std::vector<torch::Tensor> cd;
      for (int64_t i : group) cd.push_back(pairs[i].cond);
      g.cond = up(cd);
    } else {
      for (const auto& [name, first] : pairs[group.front()].inputs) {
        std::vector<torch::Tensor> parts;
        for (int64_t i : group) {
          const auto it = pairs[i].inputs.find(name);
          SIMU_CHECK(it != pairs[i].inputs.end(), "pair {} lacks condition input '{}'", pairs[i].id, name);
          parts.push_back(it->second);
        }
        g.inputs[name] = up(parts);
      }
    }
    g.uploads.record(stream);
    b->kinds.insert(b->kinds.end(), g.kinds.begin(), g.kinds.end());
    b->groups.push_back(std::move(g));
  }
  return b;
}

torch::Tensor FmdpoObjective::forward_backward(StagedBatch& staged) {
  auto& batch = static_cast<PairBatch&>(staged);
  const double beta = cfg_.objective.beta;
  const bool bf16 = cfg_.train.precision == "bf16" && device_.is_cuda();
  std::vector<torch::Tensor> metric_terms;
  for (auto& g : batch.groups) {
    g.uploads.wait(g.device_tensors(), device_);
    FmdpoInputs in;
    in.x_pos = g.x_pos.to(torch::kFloat32);
    in.x_neg = g.x_neg.to(torch::kFloat32);
    in.t = g.t;
    in.eps_pos = g.eps_pos;
    in.eps_neg = g.eps_neg;
    in.w = g.w;
    if (g.cond.defined()) {
      in.cond = g.cond.to(torch::kFloat32);
    } else {
      if (!embed_)
        fail_hint("set model.embedder_config (and model.embedder_weights) in the training config",
                  "{}: the pair cache holds condition inputs (cond_mode inputs) but no condition embedder is loaded",
                  cfg_.file);
      std::map<std::string, torch::Tensor> inputs;
      for (const auto& [name, v] : g.inputs) inputs[name] = v.to(torch::kFloat32);  // [m, ch, S, S]
      // The frozen embedder: no gradient, the step's precision policy.
      torch::NoGradGuard no_grad;
      models::Autocast ac(models::Precision::kBf16, bf16);
      in.cond = embed_(inputs).to(torch::kFloat32);  // [m, L, Cc]
    }
    FmdpoTerms terms;
    {
      // CUDA bf16 autocast when enabled (adapters stay fp32; matmuls in bf16); nests, restores.
      models::Autocast ac(models::Precision::kBf16, bf16);
      terms = fmdpo_terms(model_, in, beta, cfg_.train.activation_checkpointing);
    }
    // Rank-local mean over its share; the all-reduce averages the ranks -> global mean.
    auto weighted = in.w * terms.per_pair;  // [m]
    (weighted.sum() / static_cast<double>(batch.samples)).backward();
    // Per-pair metric terms stay on the device until the last micro-batch (no host sync in between):
    // rows weighted loss, d_theta, d_ref, policy +/-, reference +/-; one column per pair.
    metric_terms.push_back(torch::stack({weighted, terms.d_theta, terms.d_ref, terms.loss_pos_policy, terms.loss_neg_policy,
                                         terms.loss_pos_ref, terms.loss_neg_ref})
                               .detach()
                               .to(torch::kFloat32));  // [7, m]
  }
  return metric_terms.empty() ? torch::Tensor() : torch::cat(metric_terms, 1);  // [7, pairs]
}

std::vector<double> FmdpoObjective::metric_sums(const torch::Tensor& terms, const StagedBatch& staged) const {
  const auto& kinds = static_cast<const PairBatch&>(staged).kinds;
  const double beta = cfg_.objective.beta;
  // Sums in float64 pair by pair (in micro-batch order).
  StepSums sums;
  if (!terms.defined()) return sums.pack();
  auto host = terms.to(torch::kCPU, torch::kFloat64).contiguous();  // [7, pairs]
  auto a = host.accessor<double, 2>();
  for (int64_t b = 0; b < host.size(1); ++b) {
    sums.loss += a[0][b];
    sums.correct += a[1][b] < a[2][b] ? 1.0 : 0.0;
    sums.margin += -beta / 2.0 * (a[1][b] - a[2][b]);
    auto& k = sums.kind[std::clamp(kinds[b], 0, 1)];
    k.count += 1.0;
    k.policy_pos += a[3][b];
    k.policy_neg += a[4][b];
    k.ref_pos += a[5][b];
    k.ref_neg += a[6][b];
  }
  return sums.pack();
}

void FmdpoObjective::set_metrics(const std::vector<double>& packed, double n, StepMetrics& m) const {
  // The step's means over its n pairs (all ranks): loss, accuracy, margin and each pair kind's losses.
  const auto sums = StepSums::unpack(packed);
  m.loss = sums.loss / n;
  m.accuracy = sums.correct / n;
  m.margin = sums.margin / n;
  for (int k = 0; k < 2; ++k) {
    const auto& s = sums.kind[k];
    if (s.count == 0) continue;
    const std::string kn = kKindNames[k];
    m.per_kind[kn + "/policy_pos"] = s.policy_pos / s.count;
    m.per_kind[kn + "/policy_neg"] = s.policy_neg / s.count;
    m.per_kind[kn + "/ref_pos"] = s.ref_pos / s.count;
    m.per_kind[kn + "/ref_neg"] = s.ref_neg / s.count;
  }
}

std::string FmdpoObjective::export_result(const std::string& out_dir) {
  model_.export_peft(out_dir + "/adapter");
  return "adapter (PEFT) in " + out_dir + "/adapter";
}

}  // namespace simu::training
