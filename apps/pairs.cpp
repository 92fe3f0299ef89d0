// pairs: make a synthetic FM-DPO pair cache, inspect one (counts, kinds, shapes, dtypes, attributes),
// or validate one (full scan; exit 1 with an error naming the file and record).
#include <fmt/ranges.h>
#include <filesystem>

#include "common/cli.h"
#include "common/error.h"
#include "common/fs.h"
#include "common/progress.h"
#include "data/pair_cache.h"
#include "data/safetensors.h"

namespace {

// Condition inputs from a safetensors file: the six kwargs by name, or with the prefix "out." (as
// the preprocessing fixtures store them).
std::map<std::string, torch::Tensor> read_inputs_example(const std::string& path) {
  auto file = simu::data::SafeTensorsFile::open(path);
  std::map<std::string, torch::Tensor> out;
  for (const auto& name : simu::data::condition_input_names()) {
    for (const std::string key : {name, "out." + name}) {
      bool found = false;
      for (const auto& k : file.keys()) found = found || k == key;
      if (found) {
        out[name] = file.get(key).to(torch::kFloat32).clone();
        break;
      }
    }
    SIMU_CHECK(out.count(name), "--inputs-example {}: no tensor '{}' (or 'out.{}')", path, name, name);
  }
  return out;
}

torch::ScalarType parse_dtype(const std::string& s) {
  if (s == "f16" || s == "float16") return torch::kFloat16;
  if (s == "f32" || s == "float32") return torch::kFloat32;
  simu::fail("--dtype must be f16 or f32, got '{}'", s);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Make, inspect or validate an FM-DPO pair cache (HDF5; layout in docs/pair_cache.md)"};
  app.require_subcommand(1);
  simu::cli::CommonOptions common;
  simu::cli::add_common_options(app, common);

  // pairs make
  auto* make = app.add_subcommand("make", "Write a synthetic pair cache (deterministic from --seed)");
  std::string out;
  int64_t n = 0, tokens = 4096, channels = 8, cond_len = 64, cond_len_min = 0, cond_channels = 1024;
  std::string dtype = "f16";
  uint64_t seed = 0;
  bool overwrite = false;
  make->add_option("--out", out, "output file (.h5); written atomically")->required();
  make->add_flag("--overwrite", overwrite, "replace an existing --out file");
  make->add_option("--n", n, "number of pairs")->required()->check(CLI::PositiveNumber);
  make->add_option("--tokens", tokens, "latent tokens T")->capture_default_str()->check(CLI::PositiveNumber);
  make->add_option("--channels", channels, "latent channels C")->capture_default_str()->check(CLI::PositiveNumber);
  make->add_option("--cond-len", cond_len, "condition tokens L (maximum; lengths vary in [--cond-len-min, L])")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  make->add_option("--cond-len-min", cond_len_min,
                   "shortest condition (default L/2; = L gives every pair L tokens, like one embedder config)")
      ->check(CLI::NonNegativeNumber);
  make->add_option("--cond-channels", cond_channels, "condition channels Cc")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  make->add_option("--dtype", dtype, "storage dtype: f16 or f32")->capture_default_str();
  make->add_option("--seed", seed, "random seed")->capture_default_str();
  std::string cond_mode = "tokens", inputs_storage = "exact";
  int64_t input_size = 518, pointmap_size = 518;
  std::vector<std::string> examples;
  make->add_option("--cond-mode", cond_mode, "tokens (condition tokens) or inputs (the embedder's inputs)")
      ->capture_default_str()
      ->check(CLI::IsMember({"tokens", "inputs"}));
  make->add_option("--input-size", input_size, "inputs mode: image and mask side S")->capture_default_str();
  make->add_option("--pointmap-size", pointmap_size, "inputs mode: point map side P")->capture_default_str();
  make->add_option("--inputs-storage", inputs_storage, "inputs mode: exact (float32) or compact (uint8 images, float16 point maps)")
      ->capture_default_str()
      ->check(CLI::IsMember({"exact", "compact"}));
  make->add_option("--inputs-example", examples,
                   "inputs mode: safetensors with the six inputs (names or out.<name>), used in turn (default: synthetic)");

  // pairs inspect
  auto* inspect = app.add_subcommand("inspect", "Print counts, kinds, shapes, dtypes, storage and attributes");
  std::string inspect_path;
  inspect->add_option("file", inspect_path, "pair cache (.h5)")->required();

  // pairs validate
  auto* validate = app.add_subcommand(
      "validate", "Full scan: structure, NaN/Inf, shapes, dtypes, kinds, weights, ids; exit 1 on the first problem");
  std::string validate_path;
  validate->add_option("file", validate_path, "pair cache (.h5)")->required();

  return simu::cli::run(app, argc, argv, [&] {
    simu::cli::apply_common_options(common);
    SIMU_CHECK(common.sets.empty(), "--set {}: pairs reads no config file, so nothing would take the value",
               common.sets.empty() ? std::string() : common.sets.front());
    using namespace simu::data;
    if (*make) {
      simu::fs::check_overwrite(out, overwrite, "--out");
      simu::Progress progress{"make"};
      if (cond_mode == "inputs") {
        std::vector<std::map<std::string, torch::Tensor>> inputs;
        for (const auto& e : examples) inputs.push_back(read_inputs_example(e));
        make_synthetic_inputs_cache(out, n, {tokens, channels}, {cond_len, cond_channels},
                                    InputsLayout::storage_named(inputs_storage, input_size, pointmap_size), seed,
                                    parse_dtype(dtype), inputs, std::ref(progress));
      } else {
        SIMU_CHECK(examples.empty(), "--inputs-example needs --cond-mode inputs");
        make_synthetic_cache(out, n, {tokens, channels}, {cond_len, cond_channels}, seed, parse_dtype(dtype),
                             std::ref(progress), cond_len_min);
      }
      fmt::print("wrote {} ({} pairs, {:.1f} MiB)\n", out, n,
                 std::filesystem::file_size(out) / (1024.0 * 1024.0));
      return 0;
    }
    if (*inspect) {
      const auto reader = PairCacheReader::open(inspect_path);
      const auto& info = reader.info();
      fmt::print("file            {} ({:.1f} MiB)\n", inspect_path,
                 std::filesystem::file_size(inspect_path) / (1024.0 * 1024.0));
      fmt::print("schema_version  {}\n", info.schema_version);
      fmt::print("created_by      {}\n", info.created_by);
      fmt::print("pairs           {}\n", info.size);
      const auto weights = reader.weights();
      const auto kinds = reader.kinds();
      for (int k = 0; k < 2; ++k) {
        const auto sel = kinds.eq(k);
        const double mean_w = info.counts[k] > 0 ? weights.masked_select(sel).mean().item<double>() : 0.0;
        fmt::print("  {:<22} {} (mean weight {:.3g})\n", kind_name(static_cast<PairKind>(k)), info.counts[k], mean_w);
      }
      fmt::print("latent_shape    [{}] {}\n", fmt::join(info.latent_shape, ", "), info.latent_dtype);
      fmt::print("cond_mode       {}\n", info.cond_mode);
      if (info.inputs_mode()) {
        fmt::print("cond_shape      [{}] (tokens the condition embedder makes)\n", fmt::join(info.cond_shape, ", "));
        fmt::print("input_size      [{}] images {}, masks uint8, point maps {}\n", fmt::join(info.input_size, ", "),
                   info.image_dtype, info.pointmap_dtype);
      } else {
        fmt::print("cond_shape      [{}] {}\n", fmt::join(info.cond_shape, ", "), info.cond_dtype);
      }
      const auto bytes = storage_bytes(inspect_path);
      fmt::print("bytes per pair  {:.0f} on disk ({:.2f} MB): latents {:.0f}, condition {:.0f}, other {:.0f}; file {:.0f}\n",
                 bytes.latents + bytes.condition + bytes.other, (bytes.latents + bytes.condition + bytes.other) / 1e6,
                 bytes.latents, bytes.condition, bytes.other, bytes.pairs > 0 ? bytes.file_bytes / bytes.pairs : 0.0);
      fmt::print("datasets:\n");
      for (const auto& d : describe_datasets(inspect_path))
        fmt::print("  {:<12} {:<8} [{}] chunk [{}] {}\n", d.name, d.dtype, fmt::join(d.shape, ", "),
                   fmt::join(d.chunk, ", "), d.filters.empty() ? "uncompressed" : fmt::format("{}", fmt::join(d.filters, "+")));
      return 0;
    }
    simu::Progress progress{"validate"};
    const auto info = validate_cache(validate_path, std::ref(progress));
    fmt::print("ok: {} pairs ({} occlusion_completion, {} clean_preservation), latents [{}] {}, cond [{}] {}\n",
               info.size, info.counts[0], info.counts[1], fmt::join(info.latent_shape, ", "), info.latent_dtype,
               fmt::join(info.cond_shape, ", "),
               info.inputs_mode() ? fmt::format("from inputs [{}] {}/uint8/{}", fmt::join(info.input_size, ", "),
                                                info.image_dtype, info.pointmap_dtype)
                                  : info.cond_dtype);
    return 0;
  });
}
