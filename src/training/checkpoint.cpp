#include "training/checkpoint.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <regex>
#include <thread>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "data/safetensors.h"

namespace simu::training {

namespace stdfs = std::filesystem;

namespace {

const std::regex kStepDir(R"(step_(\d+))");

// Test hook: SIMU_CHECKPOINT_STALL_MS makes the writer pause between files (kill-during-write test).
void maybe_stall() {
  if (const char* ms = std::getenv("SIMU_CHECKPOINT_STALL_MS"))
    std::this_thread::sleep_for(std::chrono::milliseconds(std::atoi(ms)));
}

}  // namespace

std::string save_checkpoint(const std::string& root, const CheckpointData& data, int keep_last) {
  stdfs::create_directories(root);
  // Stale temporaries of killed writers.
  for (const auto& e : stdfs::directory_iterator(root))
    if (e.is_directory() && e.path().filename().string().rfind(".tmp-", 0) == 0) fs::remove_tree(e.path());

  const std::string name = fmt::format("step_{:08d}", data.step);
  const std::string tmp = fmt::format("{}/.tmp-{}-{}", root, name, ::getpid());
  const std::string dst = root + "/" + name;
  stdfs::create_directories(tmp);
  // Each file is itself written atomically and fsynced.
  simu::data::save_safetensors(tmp + "/adapter.safetensors", data.adapter, {{"format", "pt"}});
  maybe_stall();
  simu::data::save_safetensors(tmp + "/optimizer.safetensors", data.optimizer, {{"format", "pt"}});
  maybe_stall();
  nlohmann::json state = data.state;
  state["step"] = data.step;
  simu::fs::atomic_write(tmp + "/train_state.json", state.dump(2) + "\n");
  simu::fs::fsync_dir(tmp);
  maybe_stall();
  // Into place: an existing directory of the same step is moved aside first.
  if (stdfs::exists(dst)) {
    const std::string old = fmt::format("{}/.tmp-old-{}-{}", root, name, ::getpid());
    simu::fs::atomic_rename(dst, old);
    simu::fs::atomic_rename(tmp, dst);
    fs::remove_tree(old);
  } else {
    simu::fs::atomic_rename(tmp, dst);
  }
  // Keep the last N.
  if (keep_last > 0) {
    auto all = list_checkpoints(root);
    for (size_t i = 0; i + keep_last < all.size(); ++i) fs::remove_tree(all[i]);
    simu::fs::fsync_dir(root);
  }
  return dst;
}

CheckpointData load_checkpoint(const std::string& dir) {
  CheckpointData d;
  for (const char* f : {"adapter.safetensors", "optimizer.safetensors", "train_state.json"})
    if (!stdfs::exists(dir + "/" + f))
      fail_hint("pass a directory written by train_fmdpo (step_NNNNNNNN) or --resume latest",
                "{}: not a checkpoint: missing {}", dir, f);
  d.adapter = simu::data::load_safetensors(dir + "/adapter.safetensors");
  d.optimizer = simu::data::load_safetensors(dir + "/optimizer.safetensors");
  try {
    d.state = nlohmann::json::parse(simu::fs::read_file(dir + "/train_state.json"));
    d.step = d.state.at("step").get<int64_t>();
  } catch (const nlohmann::json::exception& e) {
    fail("{}/train_state.json: malformed: {}", dir, e.what());
  }
  // Own copies: the mapped files may be replaced while training goes on.
  for (auto& [k, v] : d.adapter) v = v.clone();
  for (auto& [k, v] : d.optimizer) v = v.clone();
  return d;
}

std::vector<std::string> list_checkpoints(const std::string& root) {
  std::vector<std::pair<int64_t, std::string>> found;
  if (!stdfs::is_directory(root)) return {};
  for (const auto& e : stdfs::directory_iterator(root)) {
    std::smatch m;
    const std::string n = e.path().filename().string();
    if (e.is_directory() && std::regex_match(n, m, kStepDir) && stdfs::exists(e.path() / "train_state.json"))
      found.emplace_back(std::stoll(m[1]), e.path().string());
  }
  std::sort(found.begin(), found.end());
  std::vector<std::string> out;
  for (auto& f : found) out.push_back(f.second);
  return out;
}

std::optional<std::string> latest_checkpoint(const std::string& root) {
  auto all = list_checkpoints(root);
  if (all.empty()) return std::nullopt;
  return all.back();
}

std::string resolve_resume(const std::string& root, const std::string& arg) {
  if (arg == "latest") {
    auto l = latest_checkpoint(root);
    if (!l) fail_hint("start without --resume, or pass a checkpoint path", "--resume latest: no checkpoint under '{}'", root);
    return *l;
  }
  if (!stdfs::is_directory(arg)) fail("--resume {}: no such checkpoint directory", arg);
  return arg;
}

}  // namespace simu::training
