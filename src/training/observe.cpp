#include "training/observe.h"

#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <sstream>

#include <fmt/format.h>
#include <nlohmann/json.hpp>

#include "common/error.h"
#include "common/fs.h"
#include "common/log.h"

namespace simu::training {

namespace {

// CRC-32C lookup table (reflected polynomial 0x82f63b78).
struct Crc32cTable {
  uint32_t t[256];
  Crc32cTable() {
    for (uint32_t i = 0; i < 256; ++i) {
      uint32_t c = i;
      for (int k = 0; k < 8; ++k) c = (c & 1) ? (c >> 1) ^ 0x82f63b78u : (c >> 1);
      t[i] = c;
    }
  }
};

// Protobuf varint.
void put_varint(std::string& out, uint64_t v) {
  while (v >= 0x80) {
    out.push_back(static_cast<char>((v & 0x7f) | 0x80));
    v >>= 7;
  }
  out.push_back(static_cast<char>(v));
}
// Field key (field number, wire type).
void put_key(std::string& out, int field, int wire) { put_varint(out, (static_cast<uint64_t>(field) << 3) | wire); }
// Length-delimited field.
void put_bytes(std::string& out, int field, const std::string& bytes) {
  put_key(out, field, 2);
  put_varint(out, bytes.size());
  out += bytes;
}
// Little-endian fixed-width value.
template <typename T>
void put_fixed(std::string& out, T v) {
  char b[sizeof(T)];
  std::memcpy(b, &v, sizeof(T));
  out.append(b, sizeof(T));
}
// Event{wall_time, step} prefix.
std::string event_head(int64_t step) {
  std::string ev;
  const double wall = std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  put_key(ev, 1, 1);
  put_fixed<double>(ev, wall);
  put_key(ev, 2, 0);
  put_varint(ev, static_cast<uint64_t>(step));
  return ev;
}

}  // namespace

uint32_t crc32c(const void* data, size_t size, uint32_t crc) {
  static const Crc32cTable table;
  const auto* p = static_cast<const uint8_t*>(data);
  crc = ~crc;
  for (size_t i = 0; i < size; ++i) crc = table.t[(crc ^ p[i]) & 0xff] ^ (crc >> 8);
  return ~crc;
}

uint32_t masked_crc32c(const void* data, size_t size) {
  const uint32_t crc = crc32c(data, size);
  return ((crc >> 15) | (crc << 17)) + 0xa282ead8u;
}

TensorBoardWriter::TensorBoardWriter(const std::string& dir) {
  std::filesystem::create_directories(dir);
  char host[256] = "localhost";
  ::gethostname(host, sizeof(host) - 1);
  const std::string base =
      fmt::format("{}/events.out.tfevents.{}.{}.{}", dir, static_cast<long long>(std::time(nullptr)), host, ::getpid());
  // Another writer of this process in the same second: a suffix keeps both files (and their order).
  path_ = base;
  for (int i = 1; std::filesystem::exists(path_); ++i) path_ = fmt::format("{}.{}", base, i);
  file_ = std::fopen(path_.c_str(), "wb");
  if (!file_) fail("{}: cannot create TensorBoard event file: {}", path_, std::strerror(errno));
  // First record: the file version.
  std::string ev = event_head(0);
  put_bytes(ev, 3, "brain.Event:2");
  write_record(ev);
}

TensorBoardWriter::~TensorBoardWriter() {
  if (file_) std::fclose(file_);
}

void TensorBoardWriter::add_scalars(int64_t step, const std::map<std::string, double>& scalars) {
  for (const auto& [tag, value] : scalars) {
    // Summary.Value{tag, simple_value}
    std::string val;
    put_bytes(val, 1, tag);
    put_key(val, 2, 5);
    put_fixed<float>(val, static_cast<float>(value));
    std::string summary;
    put_bytes(summary, 1, val);
    std::string ev = event_head(step);
    put_bytes(ev, 5, summary);
    write_record(ev);
  }
  std::fflush(file_);
}

void TensorBoardWriter::session_start(int64_t step) {
  // SessionLog{status = START (1)} as Event field 7 (session_log; 6 is the deprecated log_message).
  std::string log;
  put_key(log, 1, 0);
  put_varint(log, 1);
  std::string ev = event_head(step);
  put_bytes(ev, 7, log);
  write_record(ev);
  std::fflush(file_);
}

void TensorBoardWriter::write_record(const std::string& payload) {
  // TFRecord framing: uint64 length, masked crc of length, payload, masked crc of payload.
  std::string rec;
  const uint64_t len = payload.size();
  put_fixed<uint64_t>(rec, len);
  put_fixed<uint32_t>(rec, masked_crc32c(rec.data(), 8));
  rec += payload;
  put_fixed<uint32_t>(rec, masked_crc32c(payload.data(), payload.size()));
  if (std::fwrite(rec.data(), 1, rec.size(), file_) != rec.size()) fail("{}: write failed", path_);
}

MetricsWriter::MetricsWriter(const std::string& path, int64_t resume_step) {
  std::filesystem::create_directories(std::filesystem::path(path).parent_path());
  // A resumed run drops the lines the previous run wrote after its checkpoint.
  if (resume_step >= 0 && std::filesystem::exists(path)) {
    std::istringstream in(simu::fs::read_file(path));
    std::string line, kept;
    while (std::getline(in, line)) {
      if (line.empty()) continue;
      try {
        if (nlohmann::json::parse(line).value("step", int64_t{0}) > resume_step) continue;
      } catch (const std::exception&) {
        continue;  // a torn last line of a killed run
      }
      kept += line + "\n";
    }
    simu::fs::atomic_write(path, kept);
  }
  file_ = std::fopen(path.c_str(), resume_step >= 0 ? "ab" : "wb");
  if (!file_) fail("{}: cannot open metrics file: {}", path, std::strerror(errno));
}

MetricsWriter::~MetricsWriter() {
  if (file_) std::fclose(file_);
}

void MetricsWriter::write(int64_t step, const std::map<std::string, double>& values) {
  nlohmann::json j;
  j["step"] = step;
  for (const auto& [k, v] : values) j[k] = std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr);
  const std::string line = j.dump() + "\n";
  std::fwrite(line.data(), 1, line.size(), file_);
  std::fflush(file_);
}

std::string format_duration(double s) {
  if (!std::isfinite(s) || s < 0) return "?";
  const long long t = static_cast<long long>(s + 0.5);
  if (t >= 3600) return fmt::format("{}h{:02}m{:02}s", t / 3600, (t / 60) % 60, t % 60);
  if (t >= 60) return fmt::format("{}m{:02}s", t / 60, t % 60);
  return fmt::format("{}s", t);
}

Progress::Progress(int64_t total_steps, int64_t start_step, bool tty, int64_t every, std::string accuracy_label,
                   std::string items)
    : total_(total_steps), start_(start_step), every_(std::max<int64_t>(every, 1)), tty_(tty),
      accuracy_label_(std::move(accuracy_label)), items_(std::move(items)), began_(std::chrono::steady_clock::now()) {}

bool Progress::stderr_is_tty() { return ::isatty(STDERR_FILENO) == 1 && !simu::log::has_sink(); }

void Progress::update(int64_t step, double loss, double accuracy, double lr, double per_s) {
  const double elapsed = std::chrono::duration<double>(std::chrono::steady_clock::now() - began_).count();
  const int64_t done = step - start_;
  const double eta = done > 0 ? elapsed / done * (total_ - step) : NAN;
  const std::string acc = std::isnan(accuracy) ? "" : fmt::format(" {} {:.3f}", accuracy_label_, accuracy);
  const std::string stats = fmt::format("loss {:.4f}{} lr {:.2e} {:.1f} {}/s ETA {}", loss, acc, lr, per_s, items_,
                                        format_duration(eta));
  if (tty_) {
    // Redrawn bar: [#####.....] step/total stats
    const int width = 30;
    const int filled = total_ > 0 ? static_cast<int>(width * step / total_) : width;
    std::string bar(filled, '#');
    bar += std::string(width - filled, '.');
    std::fprintf(stderr, "\r[%s] %lld/%lld %s\x1b[K", bar.c_str(), static_cast<long long>(step),
                 static_cast<long long>(total_), stats.c_str());
    std::fflush(stderr);
  } else if (step % every_ == 0 || step == total_) {
    if (simu::log::has_sink()) {  // an embedding program's log (the Python module's logging)
      simu::log::info("step {}/{} {}", step, total_, stats);
      return;
    }
    std::fprintf(stderr, "step %lld/%lld %s\n", static_cast<long long>(step), static_cast<long long>(total_),
                 stats.c_str());
    std::fflush(stderr);
  }
}

void Progress::finish() {
  if (tty_) std::fprintf(stderr, "\n");
}

}  // namespace simu::training
