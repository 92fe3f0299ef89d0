#include "training/generator_policy.h"

#include "common/error.h"
#include "common/log.h"

#include "data/pair_cache.h"
#include "lora/lora.h"
#include "models/generator.h"

namespace simu::training {

namespace {

// The generator with adapters, seen through PolicyModel.
class GeneratorPolicy : public PolicyModel {
 public:
  GeneratorPolicy(simu::models::Generator gen, simu::lora::LoraConfig lora)
      : gen_(std::move(gen)), lora_(std::move(lora)) {
    // Policy (with gradients) and reference (without) forwards must share one arithmetic: only the
    // fused kernels that have a backward, in both (on CUDA under bf16 autocast; CPU runs the reference ops).
    gen_->backbone()->set_fused_kernels(true);
    gen_->backbone()->set_training_kernels(true);
    // Only the shape latent is scored: the protected shape stream runs alone (the pose stream, which the
    // shape stream never reads, is skipped with its condition projections).
    gen_->backbone()->set_output_latents({"shape"});
  }

  torch::Tensor predict_shape(const torch::Tensor& x_shape, const torch::Tensor& t_scaled, const torch::Tensor& cond,
                              const torch::Tensor& d) override {
    auto backbone = gen_->backbone();
    const auto& c = backbone->config();
    // Shape latent as given; pose latents as zeros [B, tokens, ch].
    simu::models::Latents latents;
    const int64_t B = x_shape.size(0);
    for (const auto& spec : c.latents) {
      if (spec.name == "shape") latents["shape"] = x_shape;
      else latents[spec.name] = torch::zeros({B, spec.tokens(), spec.in_channels}, x_shape.options());
    }
    auto out = backbone->forward(latents, t_scaled, cond, c.is_shortcut_model ? c10::optional<torch::Tensor>(d) : c10::nullopt);
    return out.at("shape");
  }
  // Cross attention shares condition row b among the token rows b*G + g (CrossAttentionImpl::attend_shared).
  bool shares_condition() const override { return true; }
  void set_adapters_enabled(bool enabled) override { simu::lora::set_lora_enabled(*gen_, enabled); }
  std::vector<std::pair<std::string, torch::Tensor>> adapter_parameters() override {
    std::vector<std::pair<std::string, torch::Tensor>> out;
    for (auto& [name, p] : simu::lora::lora_parameters(*gen_)) out.emplace_back(simu::lora::peft_file_key(name), p);
    return out;
  }
  void export_peft(const std::string& dir) override {
    simu::lora::save_peft(dir, *gen_, lora_, "FM-DPO (train_fmdpo)");
  }
  // Wraps every MOT block of the backbone in a checkpointed segment over the block's trainable
  // parameters (its LoRA weights).
  bool set_block_checkpointing(bool enabled) override {
    auto backbone = gen_->backbone();
    if (!enabled) {
      backbone->set_block_wrapper(nullptr);
      return true;
    }
    backbone->set_block_wrapper([](int64_t, torch::nn::Module& block, const std::vector<torch::Tensor>& inputs,
                                   const simu::models::BlockFn& fn) {
      std::vector<torch::Tensor> params;
      for (auto& p : block.parameters())
        if (p.requires_grad()) params.push_back(p);
      return checkpointed_segment(fn, inputs, params);
    });
    return true;
  }
  simu::models::Generator& generator() { return gen_; }

 private:
  simu::models::Generator gen_;
  simu::lora::LoraConfig lora_;
};

// Freezes every parameter of the generator (adapters are added afterwards, trainable).
void freeze(torch::nn::Module& m) {
  for (auto& p : m.parameters()) p.set_requires_grad(false);
}

}  // namespace

std::unique_ptr<PolicyModel> make_generator_policy(const std::string& generator_config, const std::string& weights,
                                                   const YAML::Node& lora, const std::string& lora_dir,
                                                   torch::Device device, const std::string& lora_file) {
  auto gen = simu::models::load_generator(generator_config, weights, torch::kCPU);
  freeze(*gen);
  simu::lora::LoraConfig lc;
  if (lora_dir.empty()) {
    // Errors name the file the lora: section comes from (the training config), not the model's.
    simu::config::Reader r(lora ? lora : YAML::Node(YAML::NodeType::Map),
                           lora_file.empty() ? std::string("lora section") : lora_file, "lora");
    lc = simu::lora::LoraConfig::from(r);
    r.finish();
    auto report = simu::lora::inject_lora(*gen, lc);
    (void)report;
  } else {
    lc = simu::lora::load_peft(lora_dir, *gen);
  }
  gen->to(device);
  gen->train();
  // The frozen base's Linear weights kept in bf16, the training autocast dtype (models/linear.h compute copies).
  if (device.is_cuda()) simu::models::set_compute_copies(*gen, torch::kBFloat16);
  return std::make_unique<GeneratorPolicy>(gen, lc);
}

std::unique_ptr<PolicyModel> make_generator_policy(const TrainConfig& cfg, torch::Device device) {
  // train.seed fixes the random parts of the model (the LoRA A init, and the base when no weights are
  // given), identically on every rank and for every world size.
  torch::manual_seed(cfg.train.seed);
  auto policy = make_generator_policy(cfg.model.config, cfg.model.weights, cfg.lora, "", device, cfg.file);
  if (cfg.train.fp8_base)
    set_policy_fp8_base(*policy, true,
                        simu::models::parse_fp8_backward(cfg.train.fp8_base_backward, cfg.file + ": train.fp8_base_backward"),
                        cfg.file + ": train.fp8_base",
                        simu::lora::parse_fp8_scope(cfg.train.fp8_base_layers, cfg.file + ": train.fp8_base_layers"));
  return policy;
}

void set_policy_fp8_base(PolicyModel& policy, bool enabled, simu::models::Fp8Backward backward, const std::string& what,
                         simu::lora::Fp8Scope scope) {
  auto* gp = dynamic_cast<GeneratorPolicy*>(&policy);
  SIMU_CHECK(gp != nullptr, "{}: the FP8 frozen base needs the Stage-1 generator policy (make_generator_policy)", what);
  auto& gen = gp->generator();
  if (enabled) simu::models::require_fp8_device(gen->parameters().front().device(), what);
  simu::lora::set_fp8_base(*gen, enabled, backward, scope);
}

}  // namespace simu::training
