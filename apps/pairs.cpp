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

// `pairs make` settings.
struct MakeOptions {
  std::string out, dtype = "f16", cond_mode = "tokens", inputs_storage = "exact";
  int64_t n = 0, tokens = 4096, channels = 8, cond_len = 64, cond_len_min = 0, cond_channels = 1024;
  int64_t input_size = 518, pointmap_size = 518;
  uint64_t seed = 0;
  bool overwrite = false;
  std::vector<std::string> examples;
};

CLI::App* add_make(CLI::App& app, MakeOptions& o) {
  auto* make = app.add_subcommand("make", "Write a synthetic pair cache (deterministic from --seed)");
  make->add_option("--out", o.out, "output file (.h5); written atomically")->required();
  make->add_flag("--overwrite", o.overwrite, "replace an existing --out file");
  make->add_option("--n", o.n, "number of pairs")->required()->check(CLI::PositiveNumber);
  make->add_option("--tokens", o.tokens, "latent tokens T")->capture_default_str()->check(CLI::PositiveNumber);
  make->add_option("--channels", o.channels, "latent channels C")->capture_default_str()->check(CLI::PositiveNumber);
  make->add_option("--cond-len", o.cond_len, "condition tokens L (maximum; lengths vary in [--cond-len-min, L])")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  make->add_option("--cond-len-min", o.cond_len_min,
                   "shortest condition (default L/2; = L gives every pair L tokens, like one embedder config)")
      ->check(CLI::NonNegativeNumber);
  make->add_option("--cond-channels", o.cond_channels, "condition channels Cc")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  make->add_option("--dtype", o.dtype, "storage dtype: f16 or f32")->capture_default_str();
  make->add_option("--seed", o.seed, "random seed")->capture_default_str();
  make->add_option("--cond-mode", o.cond_mode, "tokens (condition tokens) or inputs (the embedder's inputs)")
      ->capture_default_str()
      ->check(CLI::IsMember({"tokens", "inputs"}));
  make->add_option("--input-size", o.input_size, "inputs mode: image and mask side S")->capture_default_str();
  make->add_option("--pointmap-size", o.pointmap_size, "inputs mode: point map side P")->capture_default_str();
  make->add_option("--inputs-storage", o.inputs_storage,
                   "inputs mode: exact (float32) or compact (uint8 images, float16 point maps)")
      ->capture_default_str()
      ->check(CLI::IsMember({"exact", "compact"}));
  make->add_option("--inputs-example", o.examples,
                   "inputs mode: safetensors with the six inputs (names or out.<name>), used in turn (default: synthetic)");
  return make;
}

void run_make(const MakeOptions& o) {
  using namespace simu::data;
  simu::fs::check_overwrite(o.out, o.overwrite, "--out");
  simu::Progress progress{"make"};
  if (o.cond_mode == "inputs") {
    std::vector<std::map<std::string, torch::Tensor>> inputs;
    for (const auto& e : o.examples) inputs.push_back(read_inputs_example(e));
    make_synthetic_inputs_cache(o.out, o.n, {o.tokens, o.channels}, {o.cond_len, o.cond_channels},
                                InputsLayout::storage_named(o.inputs_storage, o.input_size, o.pointmap_size), o.seed,
                                parse_dtype(o.dtype), inputs, std::ref(progress));
  } else {
    SIMU_CHECK(o.examples.empty(), "--inputs-example needs --cond-mode inputs");
    make_synthetic_cache(o.out, o.n, {o.tokens, o.channels}, {o.cond_len, o.cond_channels}, o.seed, parse_dtype(o.dtype),
                         std::ref(progress), o.cond_len_min);
  }
  fmt::print("wrote {} ({} pairs, {:.1f} MiB)\n", o.out, o.n, std::filesystem::file_size(o.out) / (1024.0 * 1024.0));
}

void run_inspect(const std::string& path) {
  using namespace simu::data;
  const auto reader = PairCacheReader::open(path);
  const auto& info = reader.info();
  fmt::print("file            {} ({:.1f} MiB)\n", path, std::filesystem::file_size(path) / (1024.0 * 1024.0));
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
  const auto b = storage_bytes(path);
  fmt::print("bytes per pair  {:.0f} on disk ({:.2f} MB): latents {:.0f}, condition {:.0f}, other {:.0f}; file {:.0f}\n",
             b.latents + b.condition + b.other, (b.latents + b.condition + b.other) / 1e6, b.latents, b.condition, b.other,
             b.pairs > 0 ? b.file_bytes / b.pairs : 0.0);
  fmt::print("datasets:\n");
  for (const auto& d : describe_datasets(path))
    fmt::print("  {:<12} {:<8} [{}] chunk [{}] {}\n", d.name, d.dtype, fmt::join(d.shape, ", "), fmt::join(d.chunk, ", "),
               d.filters.empty() ? "uncompressed" : fmt::format("{}", fmt::join(d.filters, "+")));
}

void run_validate(const std::string& path) {
  using namespace simu::data;
  simu::Progress progress{"validate"};
  const auto info = validate_cache(path, std::ref(progress));
  fmt::print("ok: {} pairs ({} occlusion_completion, {} clean_preservation), latents [{}] {}, cond [{}] {}\n", info.size,
             info.counts[0], info.counts[1], fmt::join(info.latent_shape, ", "), info.latent_dtype,
             fmt::join(info.cond_shape, ", "),
             info.inputs_mode() ? fmt::format("from inputs [{}] {}/uint8/{}", fmt::join(info.input_size, ", "),
                                              info.image_dtype, info.pointmap_dtype)
                                : info.cond_dtype);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Make, inspect or validate an FM-DPO pair cache (HDF5; layout in docs/pair_cache.md)"};
  app.require_subcommand(1);
  simu::cli::CommonOptions common;
  MakeOptions mo;
  auto* make = add_make(app, mo);
  auto* inspect = app.add_subcommand("inspect", "Print counts, kinds, shapes, dtypes, storage, bytes per pair and attributes");
  std::string inspect_path;
  inspect->add_option("file", inspect_path, "pair cache (.h5)")->required();
  auto* validate = app.add_subcommand(
      "validate", "Full scan: structure, NaN/Inf, value ranges, shapes, dtypes, kinds, weights, ids; exit 1 on the first problem");
  std::string validate_path;
  validate->add_option("file", validate_path, "pair cache (.h5)")->required();
  return simu::cli::run(app, argc, argv, common, [&] {
    SIMU_CHECK(common.sets.empty(), "--set {}: pairs reads no config file, so nothing would take the value",
               common.sets.empty() ? std::string() : common.sets.front());
    if (*make)
      run_make(mo);
    else if (*inspect)
      run_inspect(inspect_path);
    else
      run_validate(validate_path);
    return 0;
  });
}
