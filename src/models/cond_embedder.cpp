#include "models/cond_embedder.h"

#include <fmt/ranges.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <set>

#include "common/error.h"
#include "common/log.h"
#include "data/safetensors.h"
#include "models/weights.h"

namespace simu::models {

// ---------------------------------------------------------------------------------------------
// llama3 FeedForward and projection net

int64_t FeedForwardImpl::hidden_size(int64_t hidden_dim, int64_t multiple_of, double ffn_dim_multiplier) {
  auto h = static_cast<int64_t>(2.0 * static_cast<double>(hidden_dim) / 3.0);
  if (ffn_dim_multiplier != 0.0) h = static_cast<int64_t>(ffn_dim_multiplier * static_cast<double>(h));
  return multiple_of * ((h + multiple_of - 1) / multiple_of);
}

FeedForwardImpl::FeedForwardImpl(int64_t dim, int64_t hidden_dim, int64_t output_dim, int64_t multiple_of,
                                 double ffn_dim_multiplier, bool skip_w2) {
  const int64_t h = hidden_size(hidden_dim, multiple_of, ffn_dim_multiplier);
  if (output_dim < 0) output_dim = dim;
  w1 = register_module("w1", Linear(dim, h, false));
  if (!skip_w2) w2 = register_module("w2", Linear(h, output_dim, false));
  w3 = register_module("w3", Linear(dim, h, false));
}

torch::Tensor FeedForwardImpl::forward(const torch::Tensor& x) {
  // Gated SiLU: silu(w1 x) * w3 x, then w2.
  auto g = torch::silu(w1(x)) * w3(x);
  return w2 ? w2(g) : g;
}

ProjectionNetImpl::ProjectionNetImpl(int64_t in_dim, int64_t out_dim, double multiplier, bool pre_norm) {
  if (pre_norm) norm = register_module("0", torch::nn::LayerNorm(torch::nn::LayerNormOptions({in_dim})));
  ff = register_module("1", FeedForward(in_dim, static_cast<int64_t>(multiplier * static_cast<double>(out_dim)),
                                        out_dim));
}

torch::Tensor ProjectionNetImpl::forward(const torch::Tensor& x) { return ff(norm ? norm(x) : x); }

// ---------------------------------------------------------------------------------------------
// Config

namespace {

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}
bool starts_with(const std::string& s, const std::string& prefix) { return s.rfind(prefix, 0) == 0; }

// [[kwarg, group], ...] (group may be null).
std::vector<std::pair<std::string, std::string>> read_inputs(const YAML::Node& n, const std::string& where) {
  SIMU_CHECK(n.IsSequence() && n.size() > 0, "{}: expected a non-empty list of [kwarg, position group] pairs", where);
  std::vector<std::pair<std::string, std::string>> out;
  for (size_t j = 0; j < n.size(); ++j) {
    const auto& e = n[j];
    SIMU_CHECK(e.IsSequence() && e.size() == 2 && e[0].IsScalar(),
               "{}[{}]: expected [kwarg, position group] (group may be null)", where, j);
    out.emplace_back(e[0].Scalar(), e[1].IsNull() ? std::string() : e[1].as<std::string>());
  }
  return out;
}

std::vector<std::string> optional_strings(config::Reader& r, const std::string& key) {
  if (!r.has(key)) return {};
  YAML::Node n = r.raw(key);
  if (n.IsNull()) return {};
  SIMU_CHECK(n.IsSequence(), "{}: key '{}': expected a list of strings", r.file(), r.full(key));
  return n.as<std::vector<std::string>>();
}

// Fuser-level keys shared by both layouts.
void read_fuser_options(config::Reader& r, CondEmbedderConfig& c) {
  if (r.has("use_pos_embedding")) {
    YAML::Node n = r.raw("use_pos_embedding");
    SIMU_CHECK(!n.IsNull(), "{}: use_pos_embedding null is not supported by the official EmbedderFuser "
               "(expected 'learned' or 'random')", r.file());
    c.use_pos_embedding = n.as<std::string>();
  }
  r.field("projection_pre_norm", c.projection_pre_norm);
  r.field("projection_net_hidden_dim_multiplier", c.projection_net_hidden_dim_multiplier);
  r.field("compression_projection_multiplier", c.compression_projection_multiplier);
  r.field("dropout_prob", c.dropout_prob);
  if (r.has("freeze")) (void)r.raw("freeze");  // training switch only
  c.force_drop_modalities = optional_strings(r, "force_drop_modalities");
  if (r.has("drop_modalities_weight")) {
    YAML::Node n = r.raw("drop_modalities_weight");
    if (!n.IsNull()) {
      SIMU_CHECK(n.IsSequence(), "{}: drop_modalities_weight: expected a list of [[kwargs...], weight]", r.file());
      for (size_t i = 0; i < n.size(); ++i) {
        SIMU_CHECK(n[i].IsSequence() && n[i].size() == 2,
                   "{}: drop_modalities_weight[{}]: expected [[kwargs...], weight]", r.file(), i);
        c.drop_modalities_weight.emplace_back(n[i][0].as<std::vector<std::string>>(), n[i][1].as<double>());
      }
    }
  }
}

// Official Hydra node of one embedder (`_target_` ...Dino or ...PointPatchEmbed).
CondEmbedderEntry read_official_embedder(const YAML::Node& node, const std::string& file, const std::string& path) {
  config::Reader r(node, file, path);
  const auto target = r.require<std::string>("_target_");
  CondEmbedderEntry e;
  e.name = target;
  if (ends_with(target, ".Dino")) {
    e.kind = CondEmbedderEntry::Kind::kDino;
    e.dino.vit = DinoVitConfig::hub_model(r.get<std::string>("dino_model", "dinov2_vitb14"));
    e.dino.input_size = 224;  // dino.py default
    r.field("input_size", e.dino.input_size);
    r.field("normalize_images", e.dino.normalize_images);
    r.field("prenorm_features", e.dino.prenorm_features);
    const bool prune = r.get<bool>("prune_network", false);
    for (const char* ignored : {"repo_or_dir", "source", "freeze_backbone"})
      if (r.has(ignored)) (void)r.raw(ignored);  // where the weights come from / training switch
    if (r.has("backbone_kwargs") && !node["backbone_kwargs"].IsNull()) {
      auto b = r.child("backbone_kwargs");
      DinoVitConfig overrides = e.dino.vit;
      // ViT keyword overrides passed to the hub constructor.
      overrides = [&] {
        DinoVitConfig v = e.dino.vit;
        b.field("img_size", v.img_size);
        b.field("patch_size", v.patch_size);
        b.field("embed_dim", v.embed_dim);
        b.field("depth", v.depth);
        b.field("num_heads", v.num_heads);
        b.field("mlp_ratio", v.mlp_ratio);
        b.field("init_values", v.init_values);
        b.field("ffn_layer", v.ffn_layer);
        b.field("block_chunks", v.block_chunks);
        b.field("num_register_tokens", v.num_register_tokens);
        b.field("interpolate_antialias", v.interpolate_antialias);
        b.field("interpolate_offset", v.interpolate_offset);
        b.field("qkv_bias", v.qkv_bias);
        b.field("proj_bias", v.proj_bias);
        b.field("ffn_bias", v.ffn_bias);
        for (const char* ignored : {"pretrained", "weights"})
          if (b.has(ignored)) (void)b.raw(ignored);
        return v;
      }();
      e.dino.vit = overrides;
    } else if (r.has("backbone_kwargs")) {
      (void)r.raw("backbone_kwargs");
    }
    // prune_network drops mask_token, and the final norm when prenorm features are used.
    if (prune) {
      e.dino.vit.has_mask_token = false;
      if (e.dino.prenorm_features) e.dino.vit.has_norm = false;
    }
  } else if (ends_with(target, ".PointPatchEmbed")) {
    e.kind = CondEmbedderEntry::Kind::kPointPatch;
    e.point.embed_dim = 768;  // pointmap.py defaults
    e.point.input_size = 256;
    r.field("input_size", e.point.input_size);
    r.field("patch_size", e.point.patch_size);
    r.field("embed_dim", e.point.embed_dim);
    r.field("remap_output", e.point.remap_output);
    r.field("dropout_prob", e.point.dropout_prob);
    r.field("force_dropout_always", e.point.force_dropout_always);
    r.field("exp_near_points", e.point.exp_near_points);  // project key (not in the official yaml)
  } else {
    fail("{}: {}._target_ '{}' is not a supported condition embedder (expected ...dino.Dino or "
         "...pointmap.PointPatchEmbed)", file, path, target);
  }
  r.finish();
  return e;
}

CondEmbedderConfig read_official(const YAML::Node& fuser, const std::string& file, const std::string& path) {
  config::Reader r(fuser, file, path);
  CondEmbedderConfig c;
  const auto target = r.get<std::string>("_target_", "");
  SIMU_CHECK(target.empty() || ends_with(target, ".EmbedderFuser"),
             "{}: {}._target_ is '{}', expected ...embedder_fuser.EmbedderFuser", file, path, target);
  YAML::Node list = r.raw("embedder_list");
  SIMU_CHECK(list.IsSequence() && list.size() > 0, "{}: {}.embedder_list must be a non-empty list", file, path);
  for (size_t i = 0; i < list.size(); ++i) {
    const std::string where = fmt::format("{}.embedder_list[{}]", path, i);
    SIMU_CHECK(list[i].IsSequence() && list[i].size() == 2 && list[i][0].IsMap(),
               "{}: {}: expected [embedder mapping, [[kwarg, group], ...]]", file, where);
    auto e = read_official_embedder(list[i][0], file, where + "[0]");
    e.inputs = read_inputs(list[i][1], file + ": " + where + "[1]");
    c.embedders.push_back(std::move(e));
  }
  read_fuser_options(r, c);
  r.finish();
  return c;
}

CondEmbedderConfig read_fixture_layout(const YAML::Node& root, const std::string& file) {
  config::Reader r(root, file);
  CondEmbedderConfig c;
  auto vr = r.child("vit");
  const DinoVitConfig vit = DinoVitConfig::from(vr);
  PointPatchEmbedConfig point;
  if (r.has("pointpatch")) {
    auto pr = r.child("pointpatch");
    point = PointPatchEmbedConfig::from(pr);
  }
  auto fr = r.child("fuser");
  YAML::Node list = fr.raw("embedder_list");
  SIMU_CHECK(list.IsSequence() && list.size() > 0, "{}: fuser.embedder_list must be a non-empty list", file);
  for (size_t i = 0; i < list.size(); ++i) {
    SIMU_CHECK(list[i].IsSequence() && list[i].size() == 2 && list[i][0].IsScalar(),
               "{}: fuser.embedder_list[{}]: expected [name, [[kwarg, group], ...]]", file, i);
    CondEmbedderEntry e;
    e.name = list[i][0].Scalar();
    if (starts_with(e.name, "dino")) {
      e.kind = CondEmbedderEntry::Kind::kDino;
      e.dino.vit = vit;
      e.dino.input_size = r.require<int64_t>(e.name + "_input_size");
    } else if (starts_with(e.name, "point")) {
      e.kind = CondEmbedderEntry::Kind::kPointPatch;
      e.point = point;
    } else {
      fail("{}: fuser.embedder_list[{}]: unknown embedder '{}' (names start with 'dino' or 'point')", file, i, e.name);
    }
    e.inputs = read_inputs(list[i][1], fmt::format("{}: fuser.embedder_list[{}][1]", file, i));
    c.embedders.push_back(std::move(e));
  }
  read_fuser_options(fr, c);
  r.finish();
  return c;
}

}  // namespace

CondEmbedderConfig CondEmbedderConfig::from_node(const YAML::Node& root, const std::string& file) {
  SIMU_CHECK(root.IsMap(), "{}: condition embedder config must be a mapping", file);
  if (root["fuser"]) return read_fixture_layout(root, file);
  if (root["module"]) {
    const YAML::Node fuser = root["module"]["condition_embedder"]["backbone"];
    SIMU_CHECK(fuser && fuser.IsMap(), "{}: no module.condition_embedder.backbone mapping (the layout of "
               "ss_generator.yaml); this generator config has no condition embedder", file);
    return read_official(fuser, file, "module.condition_embedder.backbone");
  }
  if (root["embedder_list"]) return read_official(root, file, "");
  fail("{}: not a condition embedder config: expected 'fuser' (fixture layout), "
       "'module.condition_embedder.backbone' (ss_generator.yaml) or 'embedder_list' at the top", file);
}

CondEmbedderConfig CondEmbedderConfig::load(const std::string& path, const std::vector<std::string>& overrides) {
  return from_node(config::load_file(path, overrides), path);
}

CondEmbedderConfig CondEmbedderConfig::sam3d_stage1() {
  CondEmbedderConfig c;
  auto dino = [](const char* name, const char* a, const char* b) {
    CondEmbedderEntry e;
    e.name = name;
    e.kind = CondEmbedderEntry::Kind::kDino;
    e.dino.vit = DinoVitConfig::hub_model("dinov2_vitl14_reg");
    e.dino.input_size = 518;
    e.inputs = {{a, "cropped"}, {b, "full"}};
    return e;
  };
  c.embedders.push_back(dino("dino_image", "image", "rgb_image"));
  c.embedders.push_back(dino("dino_mask", "mask", "rgb_image_mask"));
  CondEmbedderEntry p;
  p.name = "pointpatch";
  p.kind = CondEmbedderEntry::Kind::kPointPatch;
  p.point.input_size = 256;
  p.point.patch_size = 8;
  p.point.embed_dim = 512;
  p.point.remap_output = "linear";
  p.inputs = {{"pointmap", "cropped"}, {"rgb_pointmap", "full"}};
  c.embedders.push_back(p);
  return c;
}

int64_t CondEmbedderConfig::num_tokens() const {
  int64_t total = 0, per_input = 0;
  for (const auto& e : embedders) {
    if (e.kind == CondEmbedderEntry::Kind::kDino) {
      const int64_t g = e.dino.input_size / e.dino.vit.patch_size;
      per_input = 1 + g * g + (e.dino.prenorm_features ? e.dino.vit.num_register_tokens : 0);
    } else {
      const int64_t n = e.point.input_size / e.point.patch_size;
      per_input = n * n;
    }
    total += per_input * static_cast<int64_t>(e.inputs.size());
  }
  return compression_projection_multiplier > 0 ? per_input : total;
}

int64_t CondEmbedderConfig::embed_dims() const {
  int64_t d = 0;
  for (const auto& e : embedders)
    d = std::max(d, e.kind == CondEmbedderEntry::Kind::kDino ? e.dino.vit.embed_dim : e.point.embed_dim);
  return d;
}

// ---------------------------------------------------------------------------------------------
// EmbedderFuser

CondEmbedderImpl::CondEmbedderImpl(const CondEmbedderConfig& c) : config(c) {
  SIMU_CHECK(!c.embedders.empty(), "condition embedder: no embedders configured");
  SIMU_CHECK(c.use_pos_embedding == "learned" || c.use_pos_embedding == "random",
             "condition embedder: use_pos_embedding '{}' is not supported (expected learned or random)",
             c.use_pos_embedding);
  // Embedders; position groups numbered in order of first appearance.
  int64_t groups = 0;
  std::vector<int64_t> dims;
  for (const auto& e : c.embedders) {
    if (e.kind == CondEmbedderEntry::Kind::kDino) {
      auto m = Dino(e.dino);
      module_list->push_back(m);
      dinos_.push_back(m);
      points_.push_back(nullptr);
      dims.push_back(m->embed_dim());
    } else {
      auto m = PointPatchEmbed(e.point);
      module_list->push_back(m);
      dinos_.push_back(nullptr);
      points_.push_back(m);
      dims.push_back(m->embed_dim());
    }
    embed_dims_ = std::max(embed_dims_, dims.back());
    for (const auto& [kwarg, group] : e.inputs)
      if (!group.empty() && !positional_embed_map.count(group)) positional_embed_map[group] = groups++;
  }
  register_module("module_list", module_list);
  // Modality / position-group embedding (one spare row, as upstream).
  if (c.use_pos_embedding == "learned") {
    idx_emb = register_parameter(
        "idx_emb", torch::randn({groups + 1, embed_dims_}) / std::sqrt(static_cast<double>(embed_dims_)));
  } else {
    idx_emb = register_buffer("idx_emb", torch::randn({groups + 1, 1, embed_dims_}));
  }
  // Per-embedder projection nets.
  if (c.projection_net_hidden_dim_multiplier > 0) {
    for (size_t i = 0; i < c.embedders.size(); ++i)
      projection_nets->push_back(
          ProjectionNet(dims[i], embed_dims_, c.projection_net_hidden_dim_multiplier, c.projection_pre_norm));
    register_module("projection_nets", projection_nets);
  }
  if (c.compression_projection_multiplier > 0) {
    int64_t concat = 0;
    for (size_t i = 0; i < c.embedders.size(); ++i) concat += dims[i] * static_cast<int64_t>(c.embedders[i].inputs.size());
    compression_projector = register_module(
        "compression_projector",
        ProjectionNet(concat, embed_dims_, c.compression_projection_multiplier, c.projection_pre_norm));
  }
}

torch::Tensor CondEmbedderImpl::embed(size_t index, const torch::Tensor& x) {
  SIMU_CHECK(index < config.embedders.size(), "condition embedder: no embedder {}", index);
  return dinos_[index] ? dinos_[index]->forward(x) : points_[index]->forward(x);
}

int64_t CondEmbedderImpl::num_tokens() const { return config.num_tokens(); }

std::vector<std::string> CondEmbedderImpl::input_names() const {
  std::vector<std::string> out;
  for (const auto& e : config.embedders)
    for (const auto& [kwarg, group] : e.inputs) out.push_back(kwarg);
  return out;
}

namespace {

// Input `kwarg` of inputs (for the embedder named `entry`); a missing one is an error naming what was
// given and what is expected (expected() lists the kwargs, called only then).
const torch::Tensor& input_of(const std::map<std::string, torch::Tensor>& inputs, const std::string& kwarg,
                              const std::string& entry, const std::function<std::vector<std::string>()>& expected) {
  const auto it = inputs.find(kwarg);
  if (it == inputs.end()) {
    std::vector<std::string> given;
    for (const auto& [k, _] : inputs) given.push_back(k);
    fail("condition embedder: input '{}' (for {}) is missing; given: [{}]; expected: [{}]", kwarg, entry,
         fmt::join(given, ", "), fmt::join(expected(), ", "));
  }
  return it->second;
}

// Training-time modality dropout: per sample one configuration is drawn (keep all with 1 - dropout_prob,
// else drop_modalities_weight's entry j with dropout_prob * w_j / sum w) and the tokens of the kwargs
// (names[k] for tokens[k], each [B, T_k, C]) it lists are multiplied by 0.
void drop_modalities_per_sample(const CondEmbedderConfig& config, const std::vector<std::string>& names,
                                std::vector<torch::Tensor>& tokens) {
  const int64_t B = tokens[0].size(0);
  double total = 0;
  for (const auto& [mods, w] : config.drop_modalities_weight) total += w;
  SIMU_CHECK(total > 0, "condition embedder: drop_modalities_weight must sum to a positive value");
  std::vector<double> weights = {1.0 - config.dropout_prob};
  for (const auto& [mods, w] : config.drop_modalities_weight) weights.push_back(config.dropout_prob * w / total);
  auto dev = tokens[0].device();
  auto cum = torch::cumsum(torch::tensor(weights, torch::kFloat32).to(dev), 0);
  auto pick = torch::searchsorted(cum, torch::rand({B}, torch::TensorOptions().device(dev)))
                  .clamp_max(static_cast<int64_t>(weights.size()) - 1);
  for (size_t k = 0; k < tokens.size(); ++k) {
    auto keep = torch::ones({B}, tokens[k].options());
    for (size_t j = 0; j < config.drop_modalities_weight.size(); ++j) {
      const auto& mods = config.drop_modalities_weight[j].first;
      if (std::find(mods.begin(), mods.end(), names[k]) != mods.end())
        keep = keep.masked_fill(pick == static_cast<int64_t>(j + 1), 0.0);
    }
    tokens[k] = tokens[k] * keep.view({B, 1, 1});
  }
}

}  // namespace

torch::Tensor CondEmbedderImpl::forward(const std::map<std::string, torch::Tensor>& inputs) {
  std::vector<torch::Tensor> tokens;
  std::vector<std::string> names;
  // Looks up one input of embedder i; a missing one is an error naming what was given.
  auto input = [&](size_t i, const std::string& kwarg) -> const torch::Tensor& {
    return input_of(inputs, kwarg, config.embedders[i].name, [&] { return input_names(); });
  };
  auto project = [&](size_t i, torch::Tensor t) {
    return config.projection_net_hidden_dim_multiplier > 0 ? projection_nets[i]->as<ProjectionNetImpl>()->forward(t)
                                                           : t;
  };
  // Embed every input in config order: embedder -> projection -> + group embedding.
  for (size_t i = 0; i < config.embedders.size(); ++i) {
    const auto& entry = config.embedders[i];
    std::vector<torch::Tensor> embedded;
    if (batch_dino_inputs && dinos_[i] && entry.inputs.size() > 1) {
      // Fast path: preprocess each input, then one ViT + projection pass over the stacked batch.
      std::vector<torch::Tensor> pre;
      std::vector<int64_t> sizes;
      const auto out_dtype = input(i, entry.inputs[0].first).scalar_type();
      for (const auto& [kwarg, group] : entry.inputs) {
        pre.push_back(dinos_[i]->preprocess_input(input(i, kwarg)));
        sizes.push_back(pre.back().size(0));
      }
      auto t = project(i, dinos_[i]->forward_preprocessed(torch::cat(pre, 0), out_dtype));
      embedded = t.split_with_sizes(sizes, 0);
    } else {
      for (const auto& [kwarg, group] : entry.inputs) embedded.push_back(project(i, embed(i, input(i, kwarg))));
    }
    for (size_t k = 0; k < entry.inputs.size(); ++k) {
      const auto& [kwarg, group] = entry.inputs[k];
      auto t = embedded[k];
      if (!group.empty()) {
        const int64_t row = positional_embed_map.at(group);
        auto e = config.use_pos_embedding == "learned" ? idx_emb.slice(0, row, row + 1).unsqueeze(1)  // [1, 1, C]
                                                       : idx_emb.slice(0, row, row + 1);               // [1, 1, C]
        t = t + e.to(t.dtype());
      }
      tokens.push_back(t);
      names.push_back(kwarg);
    }
  }
  // Forced modality drop (deterministic): those tokens times 0.
  if (!config.force_drop_modalities.empty()) {
    const std::set<std::string> drop(config.force_drop_modalities.begin(), config.force_drop_modalities.end());
    for (size_t k = 0; k < tokens.size(); ++k)
      if (drop.count(names[k])) tokens[k] = tokens[k] * 0.0;
  }
  // Training-time modality dropout: one configuration per sample.
  if (is_training() && config.dropout_prob > 0 && !config.drop_modalities_weight.empty())
    drop_modalities_per_sample(config, names, tokens);
  // Concatenate along tokens, or along channels then compress.
  if (compression_projector) return compression_projector(torch::cat(tokens, -1));
  return torch::cat(tokens, 1);
}

// ---------------------------------------------------------------------------------------------
// Loading

CondEmbedder load_cond_embedder(const std::string& config_path, const std::string& weights_path,
                                const std::string& prefix, torch::Device device) {
  auto cfg = CondEmbedderConfig::load(config_path);
  CondEmbedder model(cfg);
  LoadOptions opts;
  opts.strip_prefix = prefix;
  // No weights: keep the random initialisation (benchmarks and the small demo), and say so.
  if (weights_path.empty()) {
    log::warn("condition embedder: no weights given, random initialisation ({} tokens x {} channels)",
              model->num_tokens(), model->embed_dims());
    model->to(device);
    model->eval();
    for (auto& p : model->parameters()) p.set_requires_grad(false);
    return model;
  }
  if (prefix == "auto") {
    opts.strip_prefix.clear();
    const auto file = data::SafeTensorsFile::open(weights_path);
    for (const auto& k : file.keys())
      if (starts_with(k, kOfficialCondEmbedderPrefix)) {
        opts.strip_prefix = kOfficialCondEmbedderPrefix;
        break;
      }
  }
  const int64_t n = load_safetensors_into(*model, weights_path, opts);
  log::info("condition embedder: {} tensors from {} (prefix '{}'), {} tokens x {} channels per object", n,
            weights_path, opts.strip_prefix, model->num_tokens(), model->embed_dims());
  model->to(device);
  model->eval();
  for (auto& p : model->parameters()) p.set_requires_grad(false);
  return model;
}

}  // namespace simu::models
