// libFuzzer target: a PEFT adapter directory as a user downloads it: adapter_config.json (through
// the same parser and checks as read_peft_config, then PEFT target matching over module paths of
// the Stage-1 generator) + adapter_model.safetensors (header and tensor table).
// Input: 4-byte little-endian length L, L bytes of adapter_config.json, then the safetensors bytes.
#include <cstdint>
#include <string>

#include "common/error.h"
#include "data/safetensors_header.h"
#include "lora/lora_config.h"

namespace {
const char* kPaths[] = {
    "reverse_fn.backbone.blocks.0.self_attn.to_qkv.shape",
    "reverse_fn.backbone.blocks.11.cross_attn.shape.to_kv",
    "reverse_fn.backbone.blocks.3.mlp.6drotation_normalized.mlp.0",
    "reverse_fn.backbone.input_layer.shape",
    "",
};
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 4) return 0;
  const uint32_t n = data[0] | (data[1] << 8) | (data[2] << 16) | (static_cast<uint32_t>(data[3]) << 24);
  if (n > size - 4) return 0;
  const std::string config(reinterpret_cast<const char*>(data) + 4, n);
  try {
    const auto cfg = simu::lora::peft_config_from_json(config, "fuzz/adapter_config.json");
    const simu::lora::TargetMatcher m(cfg);
    for (const char* p : kPaths) (void)m.matches(p);
  } catch (const simu::Error&) {
  }
  try {
    (void)simu::data::parse_safetensors_header(data + 4 + n, size - 4 - n, "fuzz/adapter_model.safetensors");
  } catch (const simu::Error&) {
  }
  return 0;
}
