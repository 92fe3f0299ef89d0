// Observability of a training run: TensorBoard scalar event files, metrics as JSON lines, progress.
//
// TensorBoard files are written by hand: each record is TFRecord-framed (length, masked CRC32C of
// the length, payload, masked CRC32C of the payload) and the payload is a minimal protobuf `Event`
// (wall_time = 1, step = 2, file_version = 3, summary = 5 { value = 1 { tag = 1, simple_value = 2 } }).
#pragma once

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <map>
#include <string>

namespace simu::training {

// CRC-32C (Castagnoli) of bytes, and TFRecord's masked form ((crc >> 15 | crc << 17) + 0xa282ead8).
uint32_t crc32c(const void* data, size_t size, uint32_t crc = 0);
uint32_t masked_crc32c(const void* data, size_t size);

// Writes `events.out.tfevents.<unix time>.<host>.<pid>` into a directory; one record per scalar.
class TensorBoardWriter {
 public:
  // Creates dir; writes the file_version record ("brain.Event:2"). Throws simu::Error naming the file.
  explicit TensorBoardWriter(const std::string& dir);
  ~TensorBoardWriter();
  TensorBoardWriter(const TensorBoardWriter&) = delete;
  TensorBoardWriter& operator=(const TensorBoardWriter&) = delete;
  // Appends scalars (one Event each) at step; flushes after each call.
  void add_scalars(int64_t step, const std::map<std::string, double>& scalars);
  // Appends a SessionLog START event at step (Event field 7, status START): TensorBoard then drops the
  // points of earlier files at steps >= step (what a killed run logged after its last checkpoint).
  // A resumed run writes it at its first new step.
  void session_start(int64_t step);
  const std::string& path() const { return path_; }

 private:
  void write_record(const std::string& payload);
  std::string path_;
  std::FILE* file_ = nullptr;
};

// Appends one JSON object per line ({"step": .., key: value, ...}) to a file, flushed per line.
class MetricsWriter {
 public:
  // append: keep existing lines (a resumed run); lines with step > resume_step are dropped first.
  MetricsWriter(const std::string& path, int64_t resume_step = -1);
  ~MetricsWriter();
  MetricsWriter(const MetricsWriter&) = delete;
  MetricsWriter& operator=(const MetricsWriter&) = delete;
  void write(int64_t step, const std::map<std::string, double>& values);

 private:
  std::FILE* file_ = nullptr;
};

// Progress display: a redrawn bar on a terminal, one plain line per `every` steps otherwise.
class Progress {
 public:
  // accuracy_label and items name the accuracy and the rate's unit on the line ("acc", "pairs": FM-DPO;
  // "iou", "shapes": the sparse-structure VAE).
  Progress(int64_t total_steps, int64_t start_step, bool tty, int64_t every = 1, std::string accuracy_label = "acc",
           std::string items = "pairs");
  // Shows step (1-based count of finished steps), loss, accuracy (omitted when NaN), lr, items/s and
  // the ETA.
  void update(int64_t step, double loss, double accuracy, double lr, double pairs_per_s);
  void finish();
  // True when stderr is a terminal.
  static bool stderr_is_tty();

 private:
  int64_t total_, start_, every_;
  bool tty_;
  std::string accuracy_label_, items_;
  std::chrono::steady_clock::time_point began_;
};

// Formats seconds as "1h02m03s" / "2m03s" / "3s".
std::string format_duration(double seconds);

}  // namespace simu::training
