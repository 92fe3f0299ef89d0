// Benchmark helper: where the GPU time of one call goes (PyTorch's Kineto profiler, CUPTI kernels).
#pragma once

#include <torch/csrc/autograd/profiler_kineto.h>
#include <torch/cuda.h>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <functional>
#include <map>
#include <set>
#include <string>
#include <vector>

namespace simu::bench {

// Where the GPU waits: from the CUDA activities of one profiled call (kernels, copies, memsets), the
// span from the first start to the last end, the time any stream is busy (the union of the activity
// intervals) and the idle rest, by gap size; per stream its activity count, busy time (union) and the
// time it waits between its first and last activity; and the largest whole-GPU gaps with the
// activities on either side. Method: CUPTI timestamps as Kineto reports them (ns), no extra syncs.
inline void print_gpu_timeline(const std::vector<torch::autograd::profiler::KinetoEvent>& events, int top_gaps = 6) {
  struct Act {
    uint64_t start, end;
    int64_t stream;
    std::string name;
  };
  std::vector<Act> acts;
  for (const auto& e : events)
    if (e.deviceType() == c10::DeviceType::CUDA && e.endNs() > e.startNs())
      acts.push_back({e.startNs(), e.endNs(), e.deviceResourceId(), e.name()});
  if (acts.empty()) return;
  std::sort(acts.begin(), acts.end(), [](const Act& a, const Act& b) { return a.start < b.start; });
  // Union of intervals: busy time and the gaps between busy runs (whole GPU).
  struct Gap {
    double us;
    size_t before, after;  // indices into acts: the activity ending last before it, the one starting it
  };
  std::vector<Gap> gaps;
  double busy_ns = 0;
  uint64_t run_start = acts[0].start, run_end = acts[0].end;
  size_t run_last = 0;
  for (size_t i = 1; i < acts.size(); ++i) {
    if (acts[i].start > run_end) {
      busy_ns += static_cast<double>(run_end - run_start);
      gaps.push_back({static_cast<double>(acts[i].start - run_end) * 1e-3, run_last, i});
      run_start = acts[i].start;
    }
    if (acts[i].end >= run_end) {
      run_end = acts[i].end;
      run_last = i;
    }
  }
  busy_ns += static_cast<double>(run_end - run_start);
  const double span_ms = static_cast<double>(run_end - acts[0].start) * 1e-6;
  double small = 0, mid = 0, big = 0;
  int n_small = 0, n_mid = 0, n_big = 0;
  for (const auto& g : gaps) {
    if (g.us < 20) {
      small += g.us, ++n_small;
    } else if (g.us < 200) {
      mid += g.us, ++n_mid;
    } else {
      big += g.us, ++n_big;
    }
  }
  fmt::print("timeline: span {:.2f} ms (first GPU activity to last), busy (any stream) {:.2f} ms ({:.1f}%), idle {:.2f} ms: "
             "{} gaps < 20 us ({:.2f} ms), {} of 20-200 us ({:.2f} ms), {} >= 200 us ({:.2f} ms)\n",
             span_ms, busy_ns * 1e-6, span_ms > 0 ? 100 * busy_ns * 1e-6 / span_ms : 0.0, span_ms - busy_ns * 1e-6, n_small,
             small * 1e-3, n_mid, mid * 1e-3, n_big, big * 1e-3);
  // Per stream: busy union and the waits between its own activities.
  std::map<int64_t, std::vector<const Act*>> by_stream;
  for (const auto& a : acts) by_stream[a.stream].push_back(&a);
  // The busiest streams only (graph replays spread their branches over many streams).
  std::vector<std::pair<int64_t, double>> order;
  for (const auto& [stream, list] : by_stream) {
    double k = 0;
    for (const auto* a : list) k += static_cast<double>(a->end - a->start);
    order.push_back({stream, k});
  }
  std::sort(order.begin(), order.end(), [](const auto& a, const auto& b) { return a.second > b.second; });
  if (order.size() > 4) {
    double rest = 0;
    for (size_t i = 4; i < order.size(); ++i) rest += order[i].second;
    fmt::print("  (the 4 busiest of {} streams below; the other {} hold {:.2f} ms of activity time)\n", order.size(),
               order.size() - 4, rest * 1e-6);
    order.resize(4);
  }
  for (const auto& [stream, unused] : order) {
    const auto& list = by_stream[stream];
    double sb = 0;
    uint64_t s0 = list[0]->start, e0 = list[0]->end;
    for (size_t i = 1; i < list.size(); ++i) {
      if (list[i]->start > e0) {
        sb += static_cast<double>(e0 - s0);
        s0 = list[i]->start;
      }
      e0 = std::max(e0, list[i]->end);
    }
    sb += static_cast<double>(e0 - s0);
    const double sspan = static_cast<double>(e0 - list[0]->start) * 1e-6;
    fmt::print("  stream {}: {} activities, busy {:.2f} ms, waits {:.2f} ms between its first and last\n", stream, list.size(),
               sb * 1e-6, sspan - sb * 1e-6);
  }
  std::sort(gaps.begin(), gaps.end(), [](const Gap& a, const Gap& b) { return a.us > b.us; });
  auto cut = [](std::string n) {
    if (n.size() > 60) n = n.substr(0, 60) + "...";
    for (auto& ch : n)
      if (ch == '|') ch = '/';
    return n;
  };
  if (!gaps.empty()) fmt::print("| largest gaps us | after | before |\n|---|---|---|\n");
  for (int i = 0; i < std::min<int>(top_gaps, static_cast<int>(gaps.size())); ++i)
    fmt::print("| {:.1f} | {} | {} |\n", gaps[i].us, cut(acts[gaps[i].before].name), cut(acts[gaps[i].after].name));
}

// Runs fn once under the profiler and prints the `top` GPU kernels by total time (name cut to 90
// characters), their share of all kernel time, and kernel time versus the wall time of the call.
inline void print_gpu_kernel_profile(const std::string& title, const std::function<void()>& fn, int top = 20) {
  namespace prof = torch::autograd::profiler;
  namespace impl = torch::profiler::impl;
  const impl::ProfilerConfig cfg(impl::ProfilerState::KINETO);
  const std::set<impl::ActivityType> acts{impl::ActivityType::CPU, impl::ActivityType::CUDA};
  prof::prepareProfiler(cfg, acts);
  torch::cuda::synchronize();
  prof::enableProfiler(cfg, acts);
  const auto t0 = std::chrono::steady_clock::now();
  fn();
  torch::cuda::synchronize();
  const double wall_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  const auto result = prof::disableProfiler();
  // Sum kernel durations by name.
  std::map<std::string, std::pair<double, int>> by_name;  // name -> (ms, count)
  double total = 0;
  for (const auto& e : result->events()) {
    if (e.deviceType() != c10::DeviceType::CUDA) continue;
    const double ms = static_cast<double>(e.durationNs()) * 1e-6;
    auto& slot = by_name[e.name()];
    slot.first += ms;
    slot.second += 1;
    total += ms;
  }
  std::vector<std::pair<std::string, std::pair<double, int>>> rows(by_name.begin(), by_name.end());
  std::sort(rows.begin(), rows.end(), [](const auto& a, const auto& b) { return a.second.first > b.second.first; });
  fmt::print("\nprofile: {}: wall {:.2f} ms (profiled), GPU kernel time {:.2f} ms ({:.0f}% of wall), {} kernel names\n",
             title, wall_ms, total, wall_ms > 0 ? 100 * total / wall_ms : 0.0, rows.size());
  print_gpu_timeline(result->events());
  fmt::print("| kernel | calls | ms | % of kernel time |\n|---|---|---|---|\n");
  for (int i = 0; i < std::min<int>(top, static_cast<int>(rows.size())); ++i) {
    std::string name = rows[i].first;
    if (name.size() > 90) name = name.substr(0, 90) + "...";
    for (auto& ch : name)
      if (ch == '|') ch = '/';
    fmt::print("| {} | {} | {:.3f} | {:.1f}% |\n", name, rows[i].second.second, rows[i].second.first,
               total > 0 ? 100 * rows[i].second.first / total : 0.0);
  }
}

// Like print_gpu_kernel_profile, but groups kernel time by the ATen call chain that launched each
// kernel (the op that launched it and the ops around it on the same thread, outermost first, with the
// launching op's input shapes): shows which tensor operation a copy or an elementwise kernel serves.
inline void print_gpu_op_profile(const std::string& title, const std::function<void()>& fn, int top = 30) {
  namespace prof = torch::autograd::profiler;
  namespace impl = torch::profiler::impl;
  const impl::ProfilerConfig cfg(impl::ProfilerState::KINETO, /*report_input_shapes=*/true);
  const std::set<impl::ActivityType> acts{impl::ActivityType::CPU, impl::ActivityType::CUDA};
  prof::prepareProfiler(cfg, acts);
  torch::cuda::synchronize();
  prof::enableProfiler(cfg, acts);
  fn();
  torch::cuda::synchronize();
  const auto result = prof::disableProfiler();
  struct Op {
    std::string name, shapes;
    uint64_t start, end, thread;
  };
  std::vector<Op> ops;
  std::map<uint64_t, size_t> by_corr;
  for (const auto& e : result->events()) {
    if (e.deviceType() != c10::DeviceType::CPU || e.isAsync()) continue;
    std::string shapes;
    if (e.hasShapes()) {
      int n = 0;
      for (const auto& sh : e.shapes()) {
        if (n++ == 2) break;
        shapes += "[" + fmt::format("{}", fmt::join(sh, ",")) + "]";
      }
    }
    by_corr[e.correlationId()] = ops.size();
    ops.push_back({e.name(), shapes, e.startNs(), e.endNs(), e.startThreadId()});
  }
  std::map<std::string, std::pair<double, int>> by_key;
  double total = 0;
  for (const auto& e : result->events()) {
    if (e.deviceType() != c10::DeviceType::CUDA) continue;
    const double ms = static_cast<double>(e.durationNs()) * 1e-6;
    total += ms;
    std::string kname = e.name().substr(0, 40);
    std::string key;
    const auto it = by_corr.find(e.linkedCorrelationId());
    if (it == by_corr.end()) {
      key = "(no ATen op) " + kname;
    } else {
      const Op& op = ops[it->second];
      // Enclosing ops on the launching thread, outermost first (at most 3).
      std::vector<const Op*> outer;
      for (const auto& o : ops)
        if (&o != &op && o.thread == op.thread && o.start <= op.start && o.end >= op.end) outer.push_back(&o);
      std::sort(outer.begin(), outer.end(), [](const Op* a, const Op* b) { return a->start < b->start || (a->start == b->start && a->end > b->end); });
      if (outer.size() > 3) outer.erase(outer.begin(), outer.end() - 3);
      for (const auto* o : outer) key += o->name + " > ";
      key += op.name + " " + op.shapes + " / " + kname;
    }
    auto& slot = by_key[key];
    slot.first += ms;
    slot.second += 1;
  }
  std::vector<std::pair<std::string, std::pair<double, int>>> rows(by_key.begin(), by_key.end());
  // The first `top` rows, the key made table-safe, the last column from `last` (ms, calls).
  auto print_rows = [&](const std::function<std::string(double, int)>& last) {
    for (int i = 0; i < std::min<int>(top, static_cast<int>(rows.size())); ++i) {
      std::string k = rows[i].first;
      for (auto& ch : k)
        if (ch == '|') ch = '/';
      fmt::print("| {} | {} | {:.3f} | {} |\n", k, rows[i].second.second, rows[i].second.first,
                 last(rows[i].second.first, rows[i].second.second));
    }
  };
  std::sort(rows.begin(), rows.end(), [](const auto& a, const auto& b) { return a.second.first > b.second.first; });
  fmt::print("\nop profile: {}: GPU kernel time {:.2f} ms\n| call chain [input shapes] / kernel | calls | ms | % |\n|---|---|---|---|\n",
             title, total);
  print_rows([&](double ms, int) { return fmt::format("{:.1f}%", total > 0 ? 100 * ms / total : 0.0); });
  // The same rows by launches: where the many short kernels (and their gaps) come from.
  int64_t launches = 0;
  for (const auto& r : rows) launches += r.second.second;
  std::sort(rows.begin(), rows.end(), [](const auto& a, const auto& b) { return a.second.second > b.second.second; });
  fmt::print("\nop launches: {}: {} GPU activities\n| call chain [input shapes] / kernel | calls | ms | us per call |\n"
             "|---|---|---|---|\n",
             title, launches);
  print_rows([](double ms, int calls) { return fmt::format("{:.1f}", 1000 * ms / std::max(1, calls)); });
}

// Whether a benchmark of the real-size model can run on `dev`: CUDA, or the CPU with --small (a smoke
// run). Otherwise prints why (a missing device is not an error for a benchmark) and returns false.
inline bool device_usable(const std::string& name, const torch::Device& dev, bool small) {
  if (dev.is_cuda() && !torch::cuda::is_available()) {
    fmt::print("{} needs a CUDA device (none here); for a CPU smoke run use --device cpu --small\n", name);
    return false;
  }
  if (!dev.is_cuda() && !small) {
    fmt::print("{} measures the real model on CUDA; on CPU only --device cpu --small is supported\n", name);
    return false;
  }
  return true;
}

}  // namespace simu::bench
