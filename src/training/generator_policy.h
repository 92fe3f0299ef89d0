// The Stage-1 generator with LoRA adapters as the trainer's PolicyModel. (The HDF5 pair cache as
// its PairSource: pair_source.h.)
#pragma once

#include <memory>
#include <string>

#include "lora/lora.h"
#include "models/fp8_linear.h"
#include "training/fmdpo.h"
#include "training/pair_source.h"
#include "training/trainer.h"

namespace simu::training {

// Loads the generator (model.config / model.weights), injects LoRA (cfg.lora, strict keys) into
// its shape-branch projections, moves it to device. Only the adapters require gradients.
// Pose latents are fed as zeros (the shape prediction does not depend on them).
std::unique_ptr<PolicyModel> make_generator_policy(const TrainConfig& cfg, torch::Device device);

// Same, from a generator already built (tests: fixture weights + a PEFT adapter loaded on top).
// lora_dir: "" -> inject fresh adapters from cfg.lora; else load_peft(lora_dir) (adapter config there).
// lora_file: the file the lora node comes from, named in its errors ("" -> "lora section").
std::unique_ptr<PolicyModel> make_generator_policy(const std::string& generator_config, const std::string& weights,
                                                   const YAML::Node& lora, const std::string& lora_dir,
                                                   torch::Device device, const std::string& lora_file = "");

// Switches the opt-in FP8 frozen base (lora::set_fp8_base over the layers of `scope`) of a
// policy made by make_generator_policy. On: the model's device must have FP8 tensor cores
// (models::require_fp8_device; errors name `what`, e.g. "<config>: train.fp8_base"); the weights are
// quantised now (call it after they are loaded). Off: the FP8 copies are freed.
void set_policy_fp8_base(PolicyModel& policy, bool enabled, simu::models::Fp8Backward backward, const std::string& what,
                         simu::lora::Fp8Scope scope = simu::lora::Fp8Scope::kAdapted);


}  // namespace simu::training
