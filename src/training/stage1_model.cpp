#include "training/stage1_model.h"

#include <cmath>
#include <functional>

#include "common/error.h"
#include "common/log.h"
#include "data/safetensors.h"
#include "models/dino.h"
#include "models/weights.h"

namespace simu::training {

namespace {

// Released names of a module's parameters or buffers.
std::vector<std::pair<std::string, torch::Tensor>> prefixed(const torch::OrderedDict<std::string, torch::Tensor>& items,
                                                            const std::string& prefix) {
  std::vector<std::pair<std::string, torch::Tensor>> out;
  for (const auto& kv : items) out.emplace_back(prefix + kv.key(), kv.value());
  return out;
}

// Weight and bias of a Linear, in place (no autograd).
void set_linear(models::LinearImpl& l, const std::function<void(torch::Tensor&)>& weight_init) {
  weight_init(l.weight);
  if (l.bias.defined()) l.bias.zero_();
}

}  // namespace

Stage1ModelImpl::Stage1ModelImpl(const models::GeneratorConfig& generator_config,
                                 const models::CondEmbedderConfig& embedder_config) {
  generator = register_module("generator", models::Generator(generator_config));
  embedder = register_module("embedder", models::CondEmbedder(embedder_config));
}

std::vector<std::pair<std::string, torch::Tensor>> Stage1ModelImpl::named_weights() {
  auto out = prefixed(generator->named_parameters(), kGeneratorPrefix);
  for (auto& kv : prefixed(embedder->named_parameters(), models::kOfficialCondEmbedderPrefix)) out.push_back(kv);
  return out;
}

std::vector<std::pair<std::string, torch::Tensor>> Stage1ModelImpl::named_fixed() {
  auto out = prefixed(generator->named_buffers(), kGeneratorPrefix);
  for (auto& kv : prefixed(embedder->named_buffers(), models::kOfficialCondEmbedderPrefix)) out.push_back(kv);
  return out;
}

void init_stage1_weights(Stage1Model& model) {
  torch::NoGradGuard no_grad;
  auto backbone = model->backbone();
  const auto xavier = [](torch::Tensor& w) { torch::nn::init::xavier_uniform_(w); };
  const auto normal02 = [](torch::Tensor& w) { w.normal_(0.0, 0.02); };
  // Flow model: xavier everywhere, then the special cases.
  for (auto& m : backbone->modules(/*include_self=*/false))
    if (auto* l = m->as<models::LinearImpl>()) set_linear(*l, xavier);
  for (auto* te : {backbone->t_embedder.get(), backbone->d_embedder ? backbone->d_embedder.get() : nullptr}) {
    if (!te) continue;
    auto* first = (*te->mlp)[0]->as<models::LinearImpl>();
    auto* last = (*te->mlp)[2]->as<models::LinearImpl>();
    SIMU_CHECK(first && last, "init: the timestep embedder's MLP is not Linear-SiLU-Linear");
    if (te == backbone->t_embedder.get()) {
      normal02(first->weight);
      normal02(last->weight);
    } else {
      last->weight.zero_();  // official: the d embedder starts as a constant (zero-init last weight)
    }
  }
  const auto zero = [](torch::Tensor& w) { w.zero_(); };
  if (backbone->config().share_mod) {
    set_linear(*(*backbone->adaLN_modulation)[1]->as<models::LinearImpl>(), zero);
  } else {
    for (const auto& b : *backbone->blocks) set_linear(*b->as<models::MOTBlockImpl>()->ada_linear, zero);
  }
  // Embedder: dinov2's Linear init inside every ViT.
  for (auto& m : model->embedder->modules(/*include_self=*/false))
    if (auto* vit = m->as<models::DinoVisionTransformerImpl>())
      for (auto& sub : vit->modules(/*include_self=*/false))
        if (auto* l = sub->as<models::LinearImpl>()) set_linear(*l, normal02);
}

Stage1Model make_stage1_model(const std::string& generator_config, const std::string& embedder_config,
                              const std::string& init_weights, torch::Device device, uint64_t seed) {
  const auto gen_cfg = models::GeneratorConfig::from_official_file(generator_config);
  const auto emb_cfg = models::CondEmbedderConfig::load(embedder_config);
  if (gen_cfg.backbone.cond_channels != emb_cfg.embed_dims())
    fail_hint("make the embedder's output channels and the flow model's cond_channels agree",
              "{}: cond_channels {} but the condition embedder {} makes {} channels", generator_config,
              gen_cfg.backbone.cond_channels, embedder_config, emb_cfg.embed_dims());
  torch::manual_seed(seed);
  Stage1Model model(gen_cfg, emb_cfg);
  if (init_weights.empty()) {
    init_stage1_weights(model);
  } else {
    // Both parts from one file in the released layout (each strict within its prefix).
    models::LoadOptions g;
    g.strip_prefix = kGeneratorPrefix;
    g.source = init_weights;
    models::load_safetensors_into(*model->generator, init_weights, g);
    models::LoadOptions e;
    e.strip_prefix = models::kOfficialCondEmbedderPrefix;
    e.source = init_weights;
    models::load_safetensors_into(*model->embedder, init_weights, e);
    log::info("Stage-1 model: starting from {}", init_weights);
  }
  model->to(device);
  model->train();
  // The embedder's own training-time dropouts (modality and point-map dropout) draw from the global
  // generator, alike on every rank; they stay off (eval mode: the ViTs have no dropout layers), and
  // the condition dropout for CFG is the objective's (per sample, seeded).
  model->embedder->eval();
  for (auto& p : model->parameters()) p.set_requires_grad(true);
  // Gradients for every weight: the reference ops (the fused kernels keep no weight gradients).
  model->backbone()->set_fused_kernels(false);
  model->backbone()->set_training_kernels(true);
  return model;
}

void save_stage1_weights(const std::string& path, const std::vector<std::pair<std::string, torch::Tensor>>& tensors,
                         torch::ScalarType dtype) {
  SIMU_CHECK(dtype == torch::kFloat32 || dtype == torch::kFloat16, "{}: weights are written as float32 or float16", path);
  std::vector<std::pair<std::string, torch::Tensor>> out;
  for (const auto& [name, t] : tensors) {
    auto v = t.detach().to(torch::kCPU);
    if (v.is_floating_point()) v = v.to(dtype);
    out.emplace_back(name, v.contiguous());
  }
  data::save_safetensors(path, out, {{"format", "pt"}, {"written_by", "train_stage1"}});
}

Stage1Flops stage1_flops(const models::GeneratorConfig& generator, const models::CondEmbedderConfig& embedder) {
  Stage1Flops f;
  const double out = static_cast<double>(embedder.embed_dims());
  // The fuser's projection net on `tokens` tokens of width `in` (SwiGLU: w1, w3 in -> h, w2 h -> out).
  auto projection = [&](double tokens, double in) {
    if (embedder.projection_net_hidden_dim_multiplier <= 0) return 0.0;
    const double h = static_cast<double>(models::FeedForwardImpl::hidden_size(
        static_cast<int64_t>(embedder.projection_net_hidden_dim_multiplier * out)));
    return 2 * tokens * (2 * in * h + h * out);
  };
  // A pre-norm transformer block on `windows` sequences of `tokens` tokens of width D.
  auto block = [](double windows, double tokens, double D, double mlp_ratio) {
    return windows * (2 * tokens * (3 * D * D + D * D + 2 * D * std::floor(mlp_ratio * D)) + 4 * tokens * tokens * D);
  };
  for (const auto& e : embedder.embedders) {
    const double inputs = static_cast<double>(e.inputs.size());
    if (e.kind == models::CondEmbedderEntry::Kind::kDino) {
      const auto& v = e.dino.vit;
      const double g = static_cast<double>(e.dino.input_size / v.patch_size), D = static_cast<double>(v.embed_dim);
      const double N = 1 + static_cast<double>(v.num_register_tokens) + g * g;
      const double patch = 2 * g * g * 3 * v.patch_size * v.patch_size * D;
      f.embedder_forward += inputs * (patch + v.depth * block(1, N, D, v.mlp_ratio) + projection(1 + g * g, D));
    } else {
      const auto& p = e.point;
      const double S = static_cast<double>(p.input_size), P = static_cast<double>(p.patch_size);
      const double D = static_cast<double>(p.embed_dim), windows = (S / P) * (S / P);
      f.embedder_forward += inputs * (2 * S * S * 3 * D + block(windows, P * P + 1, D, p.mlp_ratio) + projection(windows, D));
    }
  }
  f.condition_tokens = embedder.num_tokens();
  f.flow_forward = models::flow_forward_flops(generator.backbone, 1, f.condition_tokens);
  return f;
}

Stage1Counts count_parameters(Stage1Model& model) {
  Stage1Counts c;
  for (const auto& p : model->generator->parameters()) c.flow += p.numel();
  for (const auto& p : model->embedder->parameters()) c.embedder += p.numel();
  return c;
}

}  // namespace simu::training
