#include "training/checkpoint.h"

#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <regex>
#include <thread>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"
#include "common/text.h"
#include "data/safetensors.h"

namespace simu::training {

namespace stdfs = std::filesystem;

namespace {

const std::regex kStepDir(R"(step_(\d+))");
// A complete step directory moved aside by a replacing writer: .tmp-old-step_<N>-<pid>.
const std::regex kMovedAside(R"(\.tmp-old-(step_(\d+))-\d+)");

// Test hooks between the writer's phases: SIMU_CHECKPOINT_STALL_MS pauses there, and
// SIMU_CHECKPOINT_KILL_AT=<phase> kills the process with SIGKILL there (kill-during-write tests).
void write_point(const char* phase) {
  if (const char* ms = std::getenv("SIMU_CHECKPOINT_STALL_MS"))
    std::this_thread::sleep_for(std::chrono::milliseconds(std::atoi(ms)));
  if (const char* at = std::getenv("SIMU_CHECKPOINT_KILL_AT"); at && std::strcmp(at, phase) == 0) ::raise(SIGKILL);
}

}  // namespace

std::string save_checkpoint(const std::string& root, const CheckpointData& data, int keep_last) {
  stdfs::create_directories(root);
  // Temporaries of killed writers: a step moved aside for a replacement that never landed goes back
  // into place; everything else is deleted.
  for (const auto& e : stdfs::directory_iterator(root)) {
    const std::string n = e.path().filename().string();
    if (!e.is_directory() || n.rfind(".tmp-", 0) != 0) continue;
    std::smatch m;
    if (std::regex_match(n, m, kMovedAside) && !stdfs::exists(root + "/" + m[1].str()))
      simu::fs::atomic_rename(e.path().string(), root + "/" + m[1].str());
    else
      fs::remove_tree(e.path().string());
  }

  const std::string name = fmt::format("step_{:08d}", data.step);
  const std::string tmp = fmt::format("{}/.tmp-{}-{}", root, name, ::getpid());
  const std::string dst = root + "/" + name;
  stdfs::create_directories(tmp);
  // Each file is itself written atomically and fsynced.
  SIMU_CHECK(data.params_file == "adapter.safetensors" || data.params_file == "model.safetensors",
             "checkpoint: parameters file '{}' (adapter.safetensors or model.safetensors expected)", data.params_file);
  simu::data::save_safetensors(tmp + "/" + data.params_file, data.adapter, {{"format", "pt"}});
  write_point("adapter");
  simu::data::save_safetensors(tmp + "/optimizer.safetensors", data.optimizer, {{"format", "pt"}});
  write_point("optimizer");
  if (!data.extra.empty()) simu::data::save_safetensors(tmp + "/extra.safetensors", data.extra, {{"format", "pt"}});
  nlohmann::json state = data.state;
  state["step"] = data.step;
  simu::fs::atomic_write(tmp + "/train_state.json", state.dump(2) + "\n");
  simu::fs::fsync_dir(tmp);
  write_point("state");
  // Into place. An existing directory of the same step is swapped with the new one in one atomic
  // step where the filesystem can; otherwise it is moved aside to .tmp-old-<name>-<pid> first, which
  // list_checkpoints still reads and the next writer moves back if the new one never landed.
  if (stdfs::exists(dst)) {
    const char* exchange = std::getenv("SIMU_CHECKPOINT_RENAME_EXCHANGE");  // test hook: "0" forces the fallback
    if (!(exchange && std::strcmp(exchange, "0") == 0) && simu::fs::atomic_exchange(tmp, dst)) {
      write_point("replace");
      fs::remove_tree(tmp);  // now the old directory
    } else {
      const std::string old = fmt::format("{}/.tmp-old-{}-{}", root, name, ::getpid());
      simu::fs::atomic_rename(dst, old);
      write_point("replace");
      simu::fs::atomic_rename(tmp, dst);
      fs::remove_tree(old);
    }
  } else {
    simu::fs::atomic_rename(tmp, dst);
  }
  // Keep the last N: each older checkpoint is first renamed out of sight (atomic), then deleted, so a
  // kill during the deletion never leaves a visible step directory with some of its files gone.
  if (keep_last > 0) {
    auto all = list_checkpoints(root);
    for (size_t i = 0; i + keep_last < all.size(); ++i) {
      const std::string gone = fmt::format("{}/.tmp-del-{}-{}", root, stdfs::path(all[i]).filename().string(), ::getpid());
      simu::fs::atomic_rename(all[i], gone);
      write_point("prune");
      fs::remove_tree(gone);
    }
    simu::fs::fsync_dir(root);
  }
  return dst;
}

CheckpointData load_checkpoint(const std::string& dir) {
  CheckpointData d;
  // The parameters' file: an FM-DPO adapter or a Stage-1 model.
  if (!stdfs::exists(dir + "/adapter.safetensors") && stdfs::exists(dir + "/model.safetensors"))
    d.params_file = "model.safetensors";
  for (const std::string f : {d.params_file, std::string("optimizer.safetensors"), std::string("train_state.json")})
    if (!stdfs::exists(dir + "/" + f))
      fail_hint("pass a directory written by train_fmdpo or train_stage1 (step_NNNNNNNN) or --resume latest",
                "{}: not a checkpoint: missing {}", dir, f);
  d.adapter = simu::data::load_safetensors(dir + "/" + d.params_file);
  d.optimizer = simu::data::load_safetensors(dir + "/optimizer.safetensors");
  if (stdfs::exists(dir + "/extra.safetensors")) d.extra = simu::data::load_safetensors(dir + "/extra.safetensors");
  const std::string state_path = dir + "/train_state.json";
  d.state = simu::text::parse_json(simu::fs::read_file(state_path), state_path);
  // What resume reads: step and data_position {epoch, step}, non-negative integers.
  auto integer = [&](const nlohmann::json& obj, const char* key, const char* where) {
    if (!obj.is_object() || !obj.contains(key) || !obj.at(key).is_number_integer() || obj.at(key).get<int64_t>() < 0)
      fail_hint("the checkpoint is damaged: resume from an earlier one", "{}: key '{}{}': expected a non-negative integer, got {}",
                state_path, where, key, obj.is_object() && obj.contains(key) ? simu::text::excerpt(obj.at(key)) : "nothing");
    return obj.at(key).get<int64_t>();
  };
  d.step = integer(d.state, "step", "");
  const nlohmann::json pos = d.state.contains("data_position") ? d.state.at("data_position") : nlohmann::json();
  integer(pos, "epoch", "data_position.");
  integer(pos, "step", "data_position.");
  if (d.state.contains("global_batch")) integer(d.state, "global_batch", "");
  // Own copies: the mapped files may be replaced while training goes on.
  for (auto& [k, v] : d.adapter) v = v.clone();
  for (auto& [k, v] : d.optimizer) v = v.clone();
  for (auto& [k, v] : d.extra) v = v.clone();
  return d;
}

std::vector<std::string> list_checkpoints(const std::string& root) {
  std::vector<std::pair<int64_t, std::string>> found;
  if (!stdfs::is_directory(root)) return {};
  std::vector<std::pair<int64_t, std::string>> aside;
  for (const auto& e : stdfs::directory_iterator(root)) {
    std::smatch m;
    const std::string n = e.path().filename().string();
    if (!e.is_directory() || !stdfs::exists(e.path() / "train_state.json")) continue;
    if (std::regex_match(n, m, kStepDir)) found.emplace_back(std::stoll(m[1]), e.path().string());
    else if (std::regex_match(n, m, kMovedAside)) aside.emplace_back(std::stoll(m[2]), e.path().string());
  }
  // A step moved aside by a writer killed before its replacement landed stands in for it.
  for (auto& a : aside)
    if (std::none_of(found.begin(), found.end(), [&](const auto& f) { return f.first == a.first; })) found.push_back(a);
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
