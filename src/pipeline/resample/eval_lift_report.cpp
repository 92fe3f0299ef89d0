// eval_lift's aggregates, paired deltas with bootstrap intervals, summary.json and the terminal table.
#include "pipeline/resample/eval_lift.h"

#include <fmt/format.h>

#include <cmath>
#include <functional>
#include <map>

#include "common/error.h"
#include "common/random.h"
#include "common/stats.h"
#include "pipeline/physics/mesh.h"

namespace simu::resample {

namespace {

using json = nlohmann::json;

// A summary metric: its key, how one row scores it, the statistic, and whether a failed lift scores 0
// (IoU and F-scores: a missing shape overlaps nothing) or is left out (distances and errors).
struct MetricSpec {
  const char* key;
  std::function<double(const EvalRow&)> value;
  bool median;
  bool failed_zero;
};

const std::vector<MetricSpec>& metric_specs() {
  static const std::vector<MetricSpec> specs{
      {"iou_mean", [](const EvalRow& r) { return r.metrics.iou; }, false, true},
      {"fscore_1cm", [](const EvalRow& r) { return r.metrics.fscore.at(0).f; }, false, true},
      {"fscore_2cm", [](const EvalRow& r) { return r.metrics.fscore.at(1).f; }, false, true},
      {"chamfer_mean", [](const EvalRow& r) { return r.metrics.chamfer; }, false, false},
      {"rot_err_deg_median", [](const EvalRow& r) { return r.metrics.rot_err_deg; }, true, false},
      {"trans_err_median", [](const EvalRow& r) { return r.metrics.trans_err; }, true, false},
      {"scale_err_pct_median", [](const EvalRow& r) { return r.metrics.scale_err_pct; }, true, false},
      {"shape_iou_mean", [](const EvalRow& r) { return r.shape_iou; }, false, true},
  };
  return specs;
}

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// The per-row values of a metric (a failed row: 0 or NaN by the spec).
std::vector<double> values_of(const MetricSpec& spec, const std::vector<const EvalRow*>& rows) {
  std::vector<double> v;
  v.reserve(rows.size());
  for (const EvalRow* r : rows) v.push_back(r->ok ? spec.value(*r) : (spec.failed_zero ? 0.0 : kNaN));
  return v;
}

double statistic(const MetricSpec& spec, const std::vector<double>& v) {
  return spec.median ? stats::median_finite(v) : stats::mean_finite(v);
}

// A number, or null when not finite.
json number(double x) { return std::isfinite(x) ? json(x) : json(nullptr); }

// The rows of (depth, model) grouped by bucket, plus "all" (and "heldout").
std::map<std::string, std::vector<const EvalRow*>> bucket_rows(const EvalLiftResult& r, const std::string& depth,
                                                               const std::string& model, bool heldout) {
  std::map<std::string, std::vector<const EvalRow*>> out;
  for (const auto& b : visibility_buckets()) out[b];
  for (const EvalRow& row : r.rows) {
    if (row.depth != depth || row.model != model) continue;
    out[r.objects[row.object].bucket].push_back(&row);
    out["all"].push_back(&row);
    if (heldout && r.objects[row.object].held_out) out["heldout"].push_back(&row);
  }
  return out;
}

// Row buckets in table order.
std::vector<std::string> bucket_order(bool heldout) {
  std::vector<std::string> b = visibility_buckets();
  b.push_back("all");
  if (heldout) b.push_back("heldout");
  return b;
}

json object_row(const EvalLiftResult& r, const EvalRow& row) {
  const EvalObject& o = r.objects[row.object];
  json j{{"object", o.id},       {"scene", o.scene},   {"scene_seed", o.scene_seed}, {"family", o.family},
         {"instance", o.instance}, {"held_out", o.held_out}, {"visible_fraction", o.visible_fraction},
         {"bucket", o.bucket},   {"depth", row.depth}, {"model", row.model},         {"ok", row.ok},
         {"symmetry", o.symmetry.describe()}, {"size_m", o.gt.size()}};
  if (!o.source.empty()) j["source"] = o.source;
  if (!row.ok) j["error"] = row.error;
  if (row.ok) {
    const auto& m = row.metrics;
    j["iou"] = m.iou;
    j["iou_voxel_m"] = m.iou_voxel;
    j["fscore_1cm"] = m.fscore.at(0).f;
    j["fscore_2cm"] = m.fscore.at(1).f;
    j["precision_2cm"] = m.fscore.at(1).precision;
    j["recall_2cm"] = m.fscore.at(1).recall;
    j["chamfer"] = m.chamfer;
    j["rot_err_deg"] = m.rot_err_deg;
    j["trans_err"] = m.trans_err;
    j["scale_err_pct"] = m.scale_err_pct;
    j["shape_iou"] = row.shape_iou;
    // The translations in the camera frame (OpenCV: x right, y down, z forward; metres) and the sizes:
    // where a pose error comes from (depth along the ray or across it, scale).
    const auto& cam = o.camera;
    const physics::Vec3 pc = cam.R_world_cam.transpose() * (row.pred_t - cam.t_world_cam);
    const physics::Vec3 gc = cam.R_world_cam.transpose() * (o.gt.t - cam.t_world_cam);
    j["pred_t_cam"] = {pc.x(), pc.y(), pc.z()};
    j["gt_t_cam"] = {gc.x(), gc.y(), gc.z()};
    j["pred_size_m"] = row.pred_size;
    j["sample"] = row.sample;
    if (!row.sample_scores.empty()) {
      json sc = json::array();
      for (double v : row.sample_scores) sc.push_back(number(v));
      j["sample_scores"] = sc;
    }
    if (!row.refine_note.empty() || row.refined) {
      const physics::Vec3 lc = cam.R_world_cam.transpose() * (row.lifted_t - cam.t_world_cam);
      j["refined"] = row.refined;
      if (!row.refined) j["refine_note"] = row.refine_note;
      j["lifted_t_cam"] = {lc.x(), lc.y(), lc.z()};
      j["lifted_size_m"] = row.lifted_size;
    }
  }
  if (!row.picture.empty()) j["picture"] = row.picture;
  return j;
}

}  // namespace

json aggregate_rows(const EvalLiftResult&, const std::vector<const EvalRow*>& rows) {
  json j;
  j["n"] = rows.size();
  int failed = 0;
  for (const EvalRow* r : rows) failed += r->ok ? 0 : 1;
  j["n_failed"] = failed;
  int refined = 0;
  for (const EvalRow* r : rows) refined += r->refined ? 1 : 0;
  j["n_refined"] = refined;
  for (const MetricSpec& spec : metric_specs()) j[spec.key] = number(statistic(spec, values_of(spec, rows)));
  return j;
}

json eval_summary(const EvalLiftResult& r, const EvalLiftOptions& opt, const std::pair<std::string, std::string>& adapters,
                  const json& run_info) {
  const bool heldout = opt.world == "heldout";
  json s;
  s["schema"] = "simu-eval-lift/1";
  json src;
  if (!opt.world.empty()) src["world"] = opt.world;
  if (!opt.objects_dir.empty()) src["objects"] = opt.objects_dir;
  s["source"] = src;
  s["settings"] = {{"visible", {opt.visible_lo, opt.visible_hi}},
                   {"count", r.objects.size()},
                   {"seed", opt.seed},
                   {"shard", fmt::format("{}/{}", opt.shard_index, opt.shard_count)},
                   {"crop", opt.amodal_crop ? "amodal (ground truth)" : "modal"},
                   {"refine", opt.refine_name},
                   {"select", opt.select_name},
                   {"depth", r.depths},
                   {"object_size_m", opt.object_size},
                   {"gt_as_prediction", opt.gt_as_prediction},
                   {"oracle", opt.oracle.empty() ? "none" : opt.oracle},
                   {"shape_grid", opt.shape_grid},
                   {"bootstrap_resamples", opt.bootstrap_resamples},
                   {"metrics",
                    {{"max_voxel_m", opt.metrics.max_voxel},
                     {"voxels_across", opt.metrics.voxels_across},
                     {"surface_samples", opt.metrics.samples},
                     {"fscore_thresholds_m", opt.metrics.fscore_thresholds},
                     {"symmetry_tolerance", opt.metrics.symmetry.tolerance}}},
                   {"scene", {{"width", opt.scene.width}, {"height", opt.scene.height},
                              {"min_objects", opt.scene.min_objects}, {"max_objects", opt.scene.max_objects}}}};
  s["scenes"] = r.scenes;
  s["seconds"] = {{"lift", r.seconds_lift}, {"metrics", r.seconds_metrics}};
  if (!run_info.is_null()) s["run"] = run_info;
  s["models"] = {{"base", {{"adapter", adapters.first}}}};
  if (r.models.size() > 1) s["models"]["compare"] = {{"adapter", adapters.second}};

  // Aggregates per depth, model and bucket.
  for (const std::string& depth : r.depths)
    for (const std::string& model : r.models) {
      const auto groups = bucket_rows(r, depth, model, heldout);
      for (const std::string& b : bucket_order(heldout)) s["buckets"][depth][model][b] = aggregate_rows(r, groups.at(b));
    }

  // Paired deltas compare - base with bootstrap intervals.
  if (r.models.size() > 1) {
    for (const std::string& depth : r.depths) {
      const auto base = bucket_rows(r, depth, "base", heldout), cmp = bucket_rows(r, depth, "compare", heldout);
      for (const std::string& b : bucket_order(heldout)) {
        const auto& a = base.at(b);
        const auto& c = cmp.at(b);
        SIMU_CHECK(a.size() == c.size(), "eval_lift: bucket {} has {} base and {} compare rows", b, a.size(), c.size());
        json d{{"n", a.size()}};
        for (size_t i = 0; i < a.size(); ++i)
          SIMU_CHECK(a[i]->object == c[i]->object, "eval_lift: unpaired rows in bucket {}", b);
        for (const MetricSpec& spec : metric_specs()) {
          if (a.empty()) {
            d[spec.key] = nullptr;
            continue;
          }
          const std::vector<double> va = values_of(spec, a), vc = values_of(spec, c);
          // One bootstrap stream per (depth, bucket, metric), the same on every platform.
          const std::string key = depth + "/" + b + "/" + spec.key;
          const uint64_t seed = splitmix64(opt.seed ^ physics::fnv1a64(key.data(), key.size()));
          const stats::Interval ci = stats::paired_bootstrap_delta(
              va, vc, [&](const std::vector<double>& v) { return statistic(spec, v); }, opt.bootstrap_resamples, seed);
          d[spec.key] = {{"base", number(statistic(spec, va))},
                         {"compare", number(statistic(spec, vc))},
                         {"delta", number(ci.estimate)},
                         {"ci95", {number(ci.lo), number(ci.hi)}},
                         {"resamples", ci.resamples}};
        }
        s["deltas"][depth][b] = d;
      }
    }
  }
  json rows = json::array();
  for (const EvalRow& row : r.rows) rows.push_back(object_row(r, row));
  s["objects"] = rows;
  return s;
}

std::string format_summary_table(const json& s) {
  auto num = [](const json& v, const char* f, double scale = 1) {
    return v.is_number() ? fmt::format(fmt::runtime(f), scale * v.get<double>()) : std::string("-");
  };
  // Table order (JSON objects iterate their keys sorted).
  std::vector<std::string> order = bucket_order(true);
  std::string out;
  for (const auto& [depth, per_model] : s.at("buckets").items()) {
    out += fmt::format("\n{} depth\n", depth);
    out += fmt::format("  {:<11} {:<8} {:>4} {:>6} {:>6} {:>6} {:>8} {:>7} {:>8} {:>7}\n", "bucket", "model", "n", "IoU",
                       "F@1cm", "F@2cm", "CD mm", "rot deg", "trans cm", "scale%");
    for (const std::string& bucket : order)
      for (const auto& [model, buckets] : per_model.items()) {
        if (!buckets.contains(bucket) || buckets[bucket].at("n").get<int>() == 0) continue;
        const json& a = buckets[bucket];
        out += fmt::format("  {:<11} {:<8} {:>4} {:>6} {:>6} {:>6} {:>8} {:>7} {:>8} {:>7}\n", bucket, model,
                           a.at("n").get<int>(), num(a["iou_mean"], "{:.3f}"), num(a["fscore_1cm"], "{:.3f}"),
                           num(a["fscore_2cm"], "{:.3f}"), num(a["chamfer_mean"], "{:.1f}", 1000),
                           num(a["rot_err_deg_median"], "{:.1f}"), num(a["trans_err_median"], "{:.1f}", 100),
                           num(a["scale_err_pct_median"], "{:.1f}"));
      }
    if (!s.contains("deltas") || !s["deltas"].contains(depth)) continue;
    out += "  compare - base (95% bootstrap interval):\n";
    for (const std::string& bucket : order) {
      if (!s["deltas"][depth].contains(bucket) || s["deltas"][depth][bucket].at("n").get<int>() == 0) continue;
      const json& d = s["deltas"][depth][bucket];
      std::string line = fmt::format("    {:<11} n {:>4}", bucket, d.at("n").get<int>());
      for (const char* key : {"iou_mean", "fscore_2cm", "shape_iou_mean"}) {
        const json& m = d.at(key);
        line += fmt::format("  {} {} [{}, {}]", key, num(m["delta"], "{:+.3f}"), num(m["ci95"][0], "{:+.3f}"),
                            num(m["ci95"][1], "{:+.3f}"));
      }
      out += line + "\n";
    }
  }
  return out;
}

}  // namespace simu::resample
