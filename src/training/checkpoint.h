// Training checkpoints: one directory per step, written atomically, the last N kept.
//
// Layout of <root>/step_<NNNNNNNN>/:
//   adapter.safetensors    FM-DPO: the trained adapter tensors under their PEFT names
//                          (base_model.model.<path>.lora_A.weight), or
//   model.safetensors      Stage-1 pretraining: every trained parameter under its official name
//                          (_base_models.generator.<...>, _base_models.condition_embedder.<...>)
//   optimizer.safetensors  AdamW state (<name>.exp_avg, <name>.exp_avg_sq, <name>.step) and RNG
//                          states (rng.<name>, uint8)
//   extra.safetensors      the objective's own state, when it has one (Stage 1: the EMA weights)
//   train_state.json       step, data position, schedule, seeds, world size, config snapshot
// A checkpoint is built in <root>/.tmp-step_<N>-<pid>/ (every file fsynced), then renamed into place
// and the root fsynced, so a kill at any moment leaves every visible step_* directory complete.
#pragma once

#include <torch/torch.h>

#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>

namespace simu::training {

struct CheckpointData {
  int64_t step = 0;                                  // optimizer steps done
  std::map<std::string, torch::Tensor> adapter;      // the trained parameters (FM-DPO: the adapter, PEFT names)
  std::string params_file = "adapter.safetensors";   // their file: adapter.safetensors or model.safetensors
  std::map<std::string, torch::Tensor> optimizer;    // optimizer state + rng.*
  std::map<std::string, torch::Tensor> extra;        // the objective's own state (extra.safetensors when non-empty)
  nlohmann::json state = nlohmann::json::object();   // train_state.json ("step" is set from step)
};

// Writes data as <root>/step_<step>, replacing an existing one, and removes the oldest step_*
// directories beyond keep_last (keep_last <= 0 keeps all) and stale .tmp-* directories.
// Returns the checkpoint directory.
std::string save_checkpoint(const std::string& root, const CheckpointData& data, int keep_last);
// Reads a checkpoint directory; a missing or malformed file is an error naming it.
CheckpointData load_checkpoint(const std::string& dir);
// Complete checkpoint directories under root, oldest first.
std::vector<std::string> list_checkpoints(const std::string& root);
// The newest checkpoint under root, if any.
std::optional<std::string> latest_checkpoint(const std::string& root);
// "latest" -> newest under root (error if none); otherwise arg is a checkpoint directory.
std::string resolve_resume(const std::string& root, const std::string& arg);

}  // namespace simu::training
