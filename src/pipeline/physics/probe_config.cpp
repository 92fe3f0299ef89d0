// ProbeConfig from YAML: one table of keys (path, documentation, read, show) drives reading,
// --help's defaults and the tests' "every key" loop.
#include <cmath>
#include <functional>
#include <optional>

#include <fmt/ranges.h>

#include "common/config.h"
#include "common/error.h"
#include "pipeline/physics/probe.h"

namespace simu::physics {

namespace {

struct Key {
  std::string section, name, doc;
  std::function<void(config::Reader&, ProbeConfig&)> read;
  std::function<std::string(const ProbeConfig&)> show;
};

std::string show_num(double v) { return fmt::format("{:.9g}", v); }

// A key bound to a field reached by `field(cfg)`.
template <typename T, typename F>
Key make(const std::string& section, const std::string& name, F field, const std::string& doc) {
  Key k;
  k.section = section, k.name = name, k.doc = doc;
  k.read = [name, field](config::Reader& r, ProbeConfig& c) { r.field(name, field(c)); };
  k.show = [field](const ProbeConfig& c0) {
    auto& c = const_cast<ProbeConfig&>(c0);
    const T& v = field(c);
    if constexpr (std::is_same_v<T, bool>) return std::string(v ? "true" : "false");
    else if constexpr (std::is_same_v<T, std::string>) return v.empty() ? std::string("\"\"") : v;
    else if constexpr (std::is_floating_point_v<T>) return show_num(v);
    else return std::to_string(v);
  };
  return k;
}
#define PK(T, section, name, expr, doc) make<T>(section, name, [](ProbeConfig& c) -> T& { return expr; }, doc)

const std::vector<Key>& keys() {
  static const std::vector<Key> k = [] {
    std::vector<Key> v;
    // physics: MuJoCo model parameters (supplementary "Physics-mode parameters").
    v.push_back(PK(double, "physics", "timestep", c.physics.timestep, "s; paper: 1/480 s (supp. Physics-mode parameters)"));
    v.push_back(PK(std::string, "physics", "integrator", c.physics.integrator,
                   "implicit (paper, supp. Physics-mode parameters) | Euler | RK4"));
    v.push_back(PK(double, "physics", "solref_timeconst", c.physics.solref_timeconst, "s; paper: 0.01 (contact time constant)"));
    v.push_back(PK(double, "physics", "solref_dampratio", c.physics.solref_dampratio, "paper: 2.0 (inelastic contacts)"));
    v.push_back(Key{"physics", "friction", "sliding, torsional, rolling; paper: [1.0, 0.95, 0.01]",
                    [](config::Reader& r, ProbeConfig& c) {
                      if (!r.has("friction")) return;
                      const auto f = r.get<std::vector<double>>("friction", {});
                      SIMU_CHECK(f.size() == 3, "{}: key '{}': expected a list of 3 numbers, got {}", r.file(),
                                 r.full("friction"), f.size());
                      c.physics.friction = Vec3(f[0], f[1], f[2]);
                    },
                    [](const ProbeConfig& c) {
                      return fmt::format("[{}, {}, {}]", show_num(c.physics.friction[0]), show_num(c.physics.friction[1]),
                                         show_num(c.physics.friction[2]));
                    }});
    v.push_back(PK(int, "physics", "condim", c.physics.condim, "contact dimensionality; paper: 4"));
    v.push_back(PK(bool, "physics", "multiccd", c.physics.multiccd, "several contact points per mesh pair (a single one lets a resting cube sink ~4 mm)"));
    v.push_back(PK(double, "physics", "margin", c.physics.margin,
                   "m; written in scene.xml: 0 (MuJoCo 2.2 and 3+/4 combine margin/gap differently)"));
    v.push_back(PK(double, "physics", "gap", c.physics.gap, "m; written in scene.xml: 0 (see margin)"));
    v.push_back(PK(double, "physics", "detect_margin", c.physics.detect_margin,
                   "m; probe-internal diagnostic models only: first contact seen this far before touching"));
    v.push_back(PK(int, "physics", "nconmax", c.physics.nconmax, "contact buffer upper bound"));
    v.push_back(PK(int, "physics", "njmax", c.physics.njmax, "constraint buffer upper bound (mjData holds njmax^2)"));
    v.push_back(PK(double, "physics", "eq_timeconst", c.physics.eq_timeconst, "s; wall pins: stiff (supp. Wall-anchoring)"));
    v.push_back(PK(double, "physics", "eq_dampratio", c.physics.eq_dampratio, "wall pins: critically damped (supp. Wall-anchoring)"));
    // penetration: supplementary "Penetration Resolution".
    v.push_back(PK(double, "penetration", "push_extra", c.push_extra, "m added to the deepest contact per push; paper: 7 mm"));
    v.push_back(PK(int, "penetration", "max_iterations", c.max_pen_iterations, "paper: 200"));
    v.push_back(PK(double, "penetration", "max_total", c.max_pen_total, "m; larger cumulative push -> physics-disabled; paper: 0.3 m"));
    v.push_back(PK(double, "penetration", "tolerance", c.pen_tolerance, "m; a contact penetrates when deeper than this"));
    // diagnostics: gravity diagnostics (Sec. 3.4).
    v.push_back(PK(bool, "diagnostics", "gravity", c.gravity_diagnostics,
                   "false: penetration resolution only (no gravity drop, stretch or resampling; the ablation's '+ Pen.' row)"));
    v.push_back(PK(double, "diagnostics", "max_fall_time", c.max_fall_time, "s without contact -> no_support"));
    v.push_back(PK(double, "diagnostics", "settle_max_time", c.settle_max_time, "s; anchored objects on their pins"));
    v.push_back(PK(double, "diagnostics", "settle_speed", c.settle_speed, "m/s and rad/s below which a body is settled"));
    v.push_back(PK(double, "diagnostics", "settle_hold_time", c.settle_hold_time, "s the speed must stay below settle_speed"));
    v.push_back(PK(double, "diagnostics", "pin_region", c.pin_region, "top-back pin region, fraction of the extent (supp. Wall-anchoring)"));
    // decision: Sec. 3.5.
    v.push_back(PK(double, "decision", "rho_threshold", c.rho_threshold, "rho >= this resamples, else stretch; paper: 0.15 (Sec. 3.5)"));
    v.push_back(Key{"decision", "force_resample",
                    "object ids resampled whatever their rho (not in the paper; flag forced_resample): [id, ...] or one id",
                    [](config::Reader& r, ProbeConfig& c) {
                      if (!r.has("force_resample")) return;
                      if (r.node()["force_resample"].IsScalar())
                        c.force_resample = {r.get<std::string>("force_resample", "")};
                      else
                        c.force_resample = r.get<std::vector<std::string>>("force_resample", {});
                    },
                    [](const ProbeConfig& c) { return fmt::format("[{}]", fmt::join(c.force_resample, ", ")); }});
    // final: final-pass full settling.
    v.push_back(PK(double, "final", "settle_time", c.final_settle_time, "s; T_settle (supp. Final-pass full settling; value not given)"));
    v.push_back(PK(double, "final", "settle_window", c.settle_window, "s; settles stop early once at rest over one window"));
    v.push_back(PK(double, "final", "rest_distance", c.settle_rest_distance, "m; 'at rest' in the final settle"));
    v.push_back(PK(double, "final", "divergence_bound", c.divergence_bound, "m; delta_max^final: larger motion is reverted"));
    v.push_back(PK(double, "final", "candidate_settle_time", c.candidate_settle_time, "s; settle of each best-of-N candidate"));
    // evaluation: supplementary "Metrics".
    v.push_back(PK(double, "evaluation", "settle_time", c.metrics_settle_time, "s; paper: 5 s gravity settle before the metrics"));
    v.push_back(PK(double, "evaluation", "rest_distance", c.metrics_rest_distance, "m; the evaluation settle stops early once at rest"));
    v.push_back(PK(double, "evaluation", "stable_displacement", c.metrics.stable_displacement, "m; stable below; paper: 5 cm"));
    v.push_back(PK(double, "evaluation", "penetration_depth", c.metrics.penetration_depth, "m; penetrating above; paper: 2 mm"));
    v.push_back(PK(bool, "evaluation", "unstable_is_invalid", c.metrics.unstable_is_invalid, "unstable objects score 0 in ABO/IoU fh/fo"));
    v.push_back(PK(bool, "evaluation", "evaluate_input", c.evaluate_input, "also settle the input scene 5 s for the 'before' column"));
    // collision: convex decomposition (CoACD).
    v.push_back(PK(bool, "collision", "use_coacd", c.collision.use_coacd, "false: one convex hull per mesh"));
    v.push_back(PK(double, "collision", "threshold", c.collision.threshold, "CoACD concavity threshold"));
    v.push_back(PK(int, "collision", "max_hulls", c.collision.max_hulls, "CoACD max convex hulls (-1 = unlimited)"));
    v.push_back(PK(int, "collision", "resolution", c.collision.resolution, "CoACD sampling resolution"));
    v.push_back(PK(int, "collision", "mcts_iterations", c.collision.mcts_iterations, "CoACD MCTS iterations"));
    v.push_back(PK(int, "collision", "max_hull_vertices", c.collision.max_hull_vertices, "vertex cap per hull"));
    v.push_back(PK(int, "collision", "threads", c.collision.threads, "meshes decomposed in parallel (0 = one per core)"));
    v.push_back(PK(std::string, "collision", "cache_dir", c.collision.cache_dir,
                   "hull cache (\"\" = $SIMU_HULL_CACHE, else ~/.cache/simuscene/hulls)"));
    return v;
  }();
  return k;
}

}  // namespace

ProbeConfig ProbeConfig::from(config::Reader& r) {
  ProbeConfig c;
  std::string open;
  std::optional<config::Reader> sec;
  for (const Key& k : keys()) {
    if (k.section != open) sec.emplace(r.child(k.section)), open = k.section;
    k.read(*sec, c);
  }
  r.finish();
  // Domain checks name the key and the file.
  try {
    c.validate();
  } catch (const Error& e) {
    fail("{}: {}", r.file(), e.what());
  }
  return c;
}

ProbeConfig ProbeConfig::load(const std::string& path, const std::vector<std::string>& overrides) {
  YAML::Node node = path.empty() ? YAML::Node(YAML::NodeType::Map) : config::load_file(path, overrides);
  if (path.empty())
    for (const auto& a : overrides) config::apply_override(node, a, "--set");
  config::Reader r(node, path.empty() ? "--set" : path);
  return from(r);
}

void ProbeConfig::validate() const {
  auto positive = [](const char* key, double v) {
    SIMU_CHECK(std::isfinite(v) && v > 0, "key '{}': expected a positive finite number, got {}", key, v);
  };
  auto nonneg = [](const char* key, double v) {
    SIMU_CHECK(std::isfinite(v) && v >= 0, "key '{}': expected a finite number >= 0, got {}", key, v);
  };
  positive("physics.timestep", physics.timestep);
  SIMU_CHECK(physics.timestep <= 0.05, "key 'physics.timestep': {} s is too coarse for contacts (paper: 1/480 s)", physics.timestep);
  SIMU_CHECK(physics.integrator == "implicit" || physics.integrator == "Euler" || physics.integrator == "RK4",
             "key 'physics.integrator': expected implicit, Euler or RK4, got '{}'", physics.integrator);
  positive("physics.solref_timeconst", physics.solref_timeconst);
  positive("physics.solref_dampratio", physics.solref_dampratio);
  for (int k = 0; k < 3; ++k) nonneg("physics.friction", physics.friction[k]);
  SIMU_CHECK(physics.condim == 1 || physics.condim == 3 || physics.condim == 4 || physics.condim == 6,
             "key 'physics.condim': expected 1, 3, 4 or 6, got {}", physics.condim);
  nonneg("physics.margin", physics.margin);
  nonneg("physics.gap", physics.gap);
  SIMU_CHECK(physics.gap <= physics.margin, "keys 'physics.gap' ({}) > 'physics.margin' ({})", physics.gap, physics.margin);
  nonneg("physics.detect_margin", physics.detect_margin);
  SIMU_CHECK(physics.nconmax > 0 && physics.njmax > 0, "keys 'physics.nconmax'/'physics.njmax': expected positive integers");
  positive("physics.eq_timeconst", physics.eq_timeconst);
  positive("physics.eq_dampratio", physics.eq_dampratio);
  nonneg("penetration.push_extra", push_extra);
  SIMU_CHECK(max_pen_iterations >= 0, "key 'penetration.max_iterations': expected >= 0, got {}", max_pen_iterations);
  positive("penetration.max_total", max_pen_total);
  nonneg("penetration.tolerance", pen_tolerance);
  positive("diagnostics.max_fall_time", max_fall_time);
  positive("diagnostics.settle_max_time", settle_max_time);
  positive("diagnostics.settle_speed", settle_speed);
  nonneg("diagnostics.settle_hold_time", settle_hold_time);
  SIMU_CHECK(pin_region > 0 && pin_region <= 1, "key 'diagnostics.pin_region': expected (0, 1], got {}", pin_region);
  positive("decision.rho_threshold", rho_threshold);
  for (const auto& id : force_resample)
    SIMU_CHECK(!id.empty(), "key 'decision.force_resample': an empty object id");
  nonneg("final.settle_time", final_settle_time);
  positive("final.settle_window", settle_window);
  nonneg("final.rest_distance", settle_rest_distance);
  positive("final.divergence_bound", divergence_bound);
  nonneg("final.candidate_settle_time", candidate_settle_time);
  nonneg("evaluation.settle_time", metrics_settle_time);
  SIMU_CHECK(metrics_settle_time <= 600, "key 'evaluation.settle_time': {} s is absurd (paper: 5 s)", metrics_settle_time);
  nonneg("evaluation.rest_distance", metrics_rest_distance);
  positive("evaluation.stable_displacement", metrics.stable_displacement);
  positive("evaluation.penetration_depth", metrics.penetration_depth);
  positive("collision.threshold", collision.threshold);
  SIMU_CHECK(collision.threads >= 0, "key 'collision.threads': expected >= 0, got {}", collision.threads);
}

std::vector<ProbeConfig::KeyDoc> ProbeConfig::describe() const {
  std::vector<KeyDoc> out;
  for (const Key& k : keys()) out.push_back({k.section + "." + k.name, k.show(*this), k.doc});
  return out;
}

}  // namespace simu::physics
