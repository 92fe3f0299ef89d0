// SparseStructureFlowTdfyWrapper configuration (official YAML/JSON and project layouts, checks) and the
// analytic FLOP counts of one forward (flow_model.h).
#include <fmt/ranges.h>

#include <cmath>
#include <set>

#include "common/config.h"
#include "common/error.h"
#include "models/flow_model.h"
#include "models/official_yaml.h"

namespace simu::models {

// ---------------------------------------------------------------------------------------------
// Config

int64_t LatentSpec::tokens() const {
  if (pos_embedder == "shape") {
    const int64_t side = resolution / patch_size;
    return side * side * side;
  }
  return token_len;
}

std::vector<std::string> FlowModelConfig::stream_names() const {
  std::set<std::string> merged;
  for (const auto& [_, members] : share_groups) merged.insert(members.begin(), members.end());
  std::vector<std::string> out;
  for (const auto& l : latents)
    if (!merged.count(l.name)) out.push_back(l.name);
  for (const auto& [name, _] : share_groups) out.push_back(name);
  return out;
}

std::string FlowModelConfig::stream_of(const std::string& latent_name) const {
  (void)latent(latent_name);  // throws for an unknown name
  for (const auto& [group, members] : share_groups)
    if (std::find(members.begin(), members.end(), latent_name) != members.end()) return group;
  return latent_name;
}

bool FlowModelConfig::is_protected(const std::string& stream) const {
  return std::find(protected_modalities.begin(), protected_modalities.end(), stream) != protected_modalities.end();
}

const LatentSpec& FlowModelConfig::latent(const std::string& name) const {
  for (const auto& l : latents)
    if (l.name == name) return l;
  fail("flow model config: no latent named '{}'", name);
}

void FlowModelConfig::validate(const std::string& where) const {
  const std::string w = where.empty() ? "flow model config" : where;
  SIMU_CHECK(model_channels > 0 && num_heads > 0 && model_channels % num_heads == 0,
             "{}: model_channels {} must be a positive multiple of num_heads {}", w, model_channels, num_heads);
  SIMU_CHECK(num_blocks > 0, "{}: num_blocks must be positive, got {}", w, num_blocks);
  SIMU_CHECK(cond_channels > 0, "{}: cond_channels must be positive, got {}", w, cond_channels);
  SIMU_CHECK(pe_mode == "ape", "{}: pe_mode '{}' is not supported by the MOT flow model (only 'ape')", w, pe_mode);
  SIMU_CHECK(qk_rms_norm, "{}: the MOT self-attention needs qk_rms_norm: true (the official model raises otherwise)", w);
  SIMU_CHECK(!latents.empty(), "{}: latent_mapping is empty", w);
  std::set<std::string> names;
  for (const auto& l : latents) {
    SIMU_CHECK(names.insert(l.name).second, "{}: latent '{}' listed twice", w, l.name);
    SIMU_CHECK(l.in_channels > 0, "{}: latent '{}' needs in_channels > 0", w, l.name);
    SIMU_CHECK(l.tokens() > 0, "{}: latent '{}' has no tokens (resolution/token_len)", w, l.name);
  }
  std::set<std::string> grouped;
  for (const auto& [g, members] : share_groups) {
    SIMU_CHECK(!members.empty(), "{}: latent_share_transformer group '{}' is empty", w, g);
    for (const auto& m : members) {
      SIMU_CHECK(names.count(m), "{}: latent_share_transformer group '{}' names unknown latent '{}'", w, g, m);
      SIMU_CHECK(grouped.insert(m).second, "{}: latent '{}' is in two latent_share_transformer groups", w, m);
    }
  }
  const auto streams = stream_names();
  for (const auto& p : protected_modalities)
    SIMU_CHECK(std::find(streams.begin(), streams.end(), p) != streams.end(),
               "{}: protected modality '{}' is not a transformer stream (streams: {})", w, p, fmt::join(streams, ", "));
}

FlowModelConfig FlowModelConfig::from_official(const YAML::Node& b, const std::string& file) {
  SIMU_CHECK(b && b.IsMap(), "{}: flow model (reverse_fn.backbone) section missing or not a mapping", file);
  const std::string target = short_target(b);
  SIMU_CHECK(target.empty() || target == "SparseStructureFlowTdfyWrapper",
             "{}: backbone _target_ '{}' is not SparseStructureFlowTdfyWrapper", file, target);
  FlowModelConfig c;
  c.in_channels = get_or<int64_t>(b, "in_channels", c.in_channels, file);
  c.model_channels = get_or<int64_t>(b, "model_channels", c.model_channels, file);
  c.cond_channels = get_or<int64_t>(b, "cond_channels", c.cond_channels, file);
  c.out_channels = get_or<int64_t>(b, "out_channels", c.out_channels, file);
  c.num_blocks = get_or<int64_t>(b, "num_blocks", c.num_blocks, file);
  const int64_t head_channels = get_or<int64_t>(b, "num_head_channels", 64, file);
  c.num_heads = get_or<int64_t>(b, "num_heads", 0, file);
  if (c.num_heads == 0) c.num_heads = c.model_channels / head_channels;
  c.mlp_ratio = get_or<double>(b, "mlp_ratio", 4.0, file);
  c.pe_mode = get_or<std::string>(b, "pe_mode", "ape", file);
  c.share_mod = get_or<bool>(b, "share_mod", false, file);
  c.qk_rms_norm = get_or<bool>(b, "qk_rms_norm", false, file);
  c.qk_rms_norm_cross = get_or<bool>(b, "qk_rms_norm_cross", false, file);
  c.is_shortcut_model = get_or<bool>(b, "is_shortcut_model", false, file);
  c.force_zeros_cond = get_or<bool>(b, "force_zeros_cond", false, file);
  // latent_mapping: name -> {in_channels, pos_embedder: {_target_, ...}}
  const YAML::Node lm = b["latent_mapping"];
  SIMU_CHECK(lm && lm.IsMap(), "{}: backbone.latent_mapping missing or not a mapping", file);
  for (const auto& kv : lm) {
    LatentSpec s;
    s.name = kv.first.as<std::string>();
    const YAML::Node n = kv.second;
    s.in_channels = get_or<int64_t>(n, "in_channels", 0, file);
    const YAML::Node pe = n["pos_embedder"];
    const std::string pt = short_target(pe);
    if (pt == "ShapePositionEmbedder") {
      s.pos_embedder = "shape";
      s.resolution = get_or<int64_t>(pe, "resolution", get_or<int64_t>(b, "resolution", 0, file), file);
      s.patch_size = get_or<int64_t>(pe, "patch_size", get_or<int64_t>(b, "patch_size", 1, file), file);
    } else if (pt == "LearntPositionEmbedder" || pt == "RandomPositionEmbedder") {
      s.pos_embedder = pt == "LearntPositionEmbedder" ? "learnt" : "random";
      s.token_len = get_or<int64_t>(pe, "token_len", 1, file);
    } else {
      fail("{}: latent_mapping.{}.pos_embedder: unknown _target_ '{}' (expected ShapePositionEmbedder, "
           "LearntPositionEmbedder or RandomPositionEmbedder)", file, s.name, pt);
    }
    c.latents.push_back(s);
  }
  // latent_share_transformer: merged name -> [latent names]
  if (const YAML::Node st = b["latent_share_transformer"]; st && st.IsMap()) {
    for (const auto& kv : st) c.share_groups.emplace_back(kv.first.as<std::string>(), kv.second.as<std::vector<std::string>>());
  }
  c.validate(file + ": module.generator.backbone.reverse_fn.backbone");
  return c;
}

FlowModelConfig FlowModelConfig::from(config::Reader& r) {
  FlowModelConfig c;
  r.field("in_channels", c.in_channels);
  r.field("model_channels", c.model_channels);
  r.field("cond_channels", c.cond_channels);
  r.field("out_channels", c.out_channels);
  r.field("num_blocks", c.num_blocks);
  r.field("num_heads", c.num_heads);
  r.field("mlp_ratio", c.mlp_ratio);
  r.field("pe_mode", c.pe_mode);
  r.field("share_mod", c.share_mod);
  r.field("qk_rms_norm", c.qk_rms_norm);
  r.field("qk_rms_norm_cross", c.qk_rms_norm_cross);
  r.field("is_shortcut_model", c.is_shortcut_model);
  r.field("force_zeros_cond", c.force_zeros_cond);
  r.field("protected_modalities", c.protected_modalities);
  // latents: list of {name, in_channels, pos_embedder: shape|learnt|random, resolution, patch_size, token_len}
  const YAML::Node list = r.raw("latents");
  SIMU_CHECK(list && list.IsSequence(), "{}: key '{}': expected a list of latents", r.file(), r.full("latents"));
  for (size_t i = 0; i < list.size(); ++i) {
    config::Reader lr(list[i], r.file(), r.full(fmt::format("latents[{}]", i)));
    LatentSpec s;
    s.name = lr.require<std::string>("name");
    s.in_channels = lr.require<int64_t>("in_channels");
    lr.field("pos_embedder", s.pos_embedder);
    lr.field("resolution", s.resolution);
    lr.field("patch_size", s.patch_size);
    lr.field("token_len", s.token_len);
    lr.finish();
    SIMU_CHECK(s.pos_embedder == "shape" || s.pos_embedder == "learnt" || s.pos_embedder == "random",
               "{}: latents[{}].pos_embedder: expected shape, learnt or random, got '{}'", r.file(), i, s.pos_embedder);
    c.latents.push_back(s);
  }
  // share_groups: mapping merged name -> list of latent names (order kept)
  if (r.has("share_groups")) {
    const YAML::Node g = r.raw("share_groups");
    SIMU_CHECK(g.IsMap(), "{}: key '{}': expected a mapping name -> list of latents", r.file(), r.full("share_groups"));
    for (const auto& kv : g) c.share_groups.emplace_back(kv.first.as<std::string>(), kv.second.as<std::vector<std::string>>());
  }
  c.validate(r.file() + ": " + (r.full("").empty() ? "flow_model" : r.full("")));
  return c;
}

// ---------------------------------------------------------------------------------------------
// FLOP counts

double flow_forward_flops(const FlowModelConfig& c, int64_t batch, int64_t cond_len) {
  const double C = static_cast<double>(c.model_channels), Cc = static_cast<double>(c.cond_channels);
  const double Lc = static_cast<double>(cond_len), hidden = std::floor(C * c.mlp_ratio);
  // Tokens per stream and keys each stream attends to.
  const auto streams = c.stream_names();
  double total_tokens = 0, protected_tokens = 0;
  std::map<std::string, double> tokens;
  for (const auto& s : streams) {
    double t = 0;
    const auto g = std::find_if(c.share_groups.begin(), c.share_groups.end(), [&](const auto& p) { return p.first == s; });
    if (g == c.share_groups.end()) t = static_cast<double>(c.latent(s).tokens());
    else
      for (const auto& m : g->second) t += static_cast<double>(c.latent(m).tokens());
    tokens[s] = t;
    total_tokens += t;
    if (std::find(c.protected_modalities.begin(), c.protected_modalities.end(), s) != c.protected_modalities.end())
      protected_tokens += t;
  }
  double block = 0;
  for (const auto& s : streams) {
    const double T = tokens[s];
    const bool prot = std::find(c.protected_modalities.begin(), c.protected_modalities.end(), s) != c.protected_modalities.end();
    const double keys = prot ? T : total_tokens;  // protected: itself; others: everything
    block += 2 * T * C * 3 * C + 2 * T * C * C;                 // self qkv + out
    block += 2 * 2 * T * keys * C;                              // self QK^T + PV
    block += 2 * T * C * C + 2 * Lc * Cc * 2 * C + 2 * T * C * C;  // cross q, kv, out
    block += 2 * 2 * T * Lc * C;                                // cross QK^T + PV
    block += 2 * 2 * T * C * hidden;                            // MLP
  }
  (void)protected_tokens;
  double io = 0;
  for (const auto& l : c.latents) io += 2 * 2 * static_cast<double>(l.tokens()) * C * l.in_channels;
  const double ada = (c.share_mod ? 1.0 : static_cast<double>(c.num_blocks)) * 2 * C * 6 * C;
  return batch * (c.num_blocks * block + io + ada);
}

double flow_condition_kv_flops(const FlowModelConfig& c, int64_t batch, int64_t cond_len) {
  const double streams = static_cast<double>(c.stream_names().size());
  return batch * c.num_blocks * streams * 2.0 * cond_len * c.cond_channels * 2.0 * c.model_channels;
}

}  // namespace simu::models
