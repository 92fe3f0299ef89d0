#!/usr/bin/env bash
# Fuzzing harness (docs/fuzzing.md): libFuzzer targets of fuzz/ built with clang and
# AddressSanitizer + UndefinedBehaviorSanitizer in their own build dir.
#   scripts/fuzz.sh --build-only                 configure + build the targets
#   scripts/fuzz.sh --smoke                      replay every seed and regression input, then fuzz each
#                                                target for SIMU_FUZZ_SMOKE_S seconds (default 8); part of
#                                                ./run test (ctest Fuzz.Smoke)
#   scripts/fuzz.sh --long SECONDS [TARGET...]   fuzz each target for SECONDS (working corpus and
#                                                crashes under <build>/work/<target>); prints executions
# Options: --build DIR (default build-fuzz), --jobs N (--long: libFuzzer fork mode, N processes sharing
#   one corpus and one execution count), --runs N (--long: stop a target after N executions, or at
#   SECONDS, whichever comes first), --no-build (use the targets as built; with --long no compiler is
#   needed, so targets copied with the libraries they link run on a many-core machine too).
#   fuzz_pair_cache --long fuzzes the reads behind the HDF5 crash guard (SIMU_HDF5_ISOLATE=0, libFuzzer
#   fork mode keeps going past libhdf5 1.10's own crashes; set ASAN_OPTIONS=symbolize=0 there: each such
#   crash is otherwise symbolised) and then replays every crash/hang input with the guard on: only a
#   failure there counts. A later --long run continues the same work dir (corpus, crash inputs, and the
#   execution total in <work>/executions.txt); --no-triage skips the replay (a run split over calls),
#   --triage-only replays what the runs so far collected. Delete <work> to start afresh.
# Exit status: 0 clean, 1 a crash / sanitizer report / build failure, 77 clang or libFuzzer missing.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BUILD="$ROOT/build-fuzz"
MODE=""
SECS=0
JOBS=1
RUNS=0
BUILD_TARGETS=1
TRIAGE=1
TARGETS=()
while (($#)); do
  case "$1" in
    --build-only) MODE=build ;;
    --smoke) MODE=smoke ;;
    --long) MODE=long; SECS="$2"; shift ;;
    --build) BUILD="$2"; shift ;;
    --jobs) JOBS="$2"; shift ;;
    --runs) RUNS="$2"; shift ;;
    --no-build) BUILD_TARGETS=0 ;;
    --no-triage) TRIAGE=0 ;;
    --triage-only) MODE=long; TRIAGE=2 ;;
    -h|--help) sed -n 2,21p "$0"; exit 0 ;;
    fuzz_*) TARGETS+=("$1") ;;
    *) echo "fuzz.sh: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
  shift
done
[[ -n $MODE ]] || { sed -n 2,21p "$0"; exit 2; }
((${#TARGETS[@]})) || TARGETS=(fuzz_safetensors fuzz_peft fuzz_config fuzz_scene fuzz_pair_cache fuzz_manifest fuzz_depth)

# Prebuilt targets (--no-build, e.g. copied to a many-core machine with the libraries they link): no compiler needed.
if ((!BUILD_TARGETS)) && [[ $MODE == long ]]; then
  for t in "${TARGETS[@]}"; do [[ -x $BUILD/$t ]] || { echo "fuzz.sh: --no-build: $BUILD/$t is missing" >&2; exit 1; }; done
else
# clang with libFuzzer (Debian: clang + libclang-rt-dev, installed by scripts/setup.sh).
CXX="${SIMU_FUZZ_CXX:-$(command -v clang++ || true)}"
if [[ -z $CXX ]]; then echo "SKIP: clang++ not found (apt-get install clang libclang-rt-dev)"; exit 77; fi
if ! echo 'extern "C" int LLVMFuzzerTestOneInput(const unsigned char*, unsigned long){return 0;}' |
     "$CXX" -x c++ -fsanitize=fuzzer,address,undefined -o /dev/null - 2>/dev/null; then
  echo "SKIP: $CXX cannot link libFuzzer (apt-get install libclang-rt-dev)"; exit 77
fi
PY="${SIMU_PYTHON:-$ROOT/.deps/venv/bin/python}"
TORCH_DIR="${SIMU_TORCH_DIR:-$("$PY" -c 'import torch, os; print(os.path.dirname(torch.__file__))')}"
C="${SIMU_FUZZ_CC:-$(command -v clang)}"
if ! [[ -f $BUILD/build.ninja ]]; then
  cmake -S "$ROOT/fuzz" -B "$BUILD" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_CXX_COMPILER="$CXX" \
    -DCMAKE_C_COMPILER="$C" -DSIMU_TORCH_DIR="$TORCH_DIR" >"$BUILD.configure.log" 2>&1 ||
    { cat "$BUILD.configure.log" >&2; exit 1; }
fi
if ((BUILD_TARGETS)); then
  cmake --build "$BUILD" -j"${JOBS_BUILD:-2}" --target "${TARGETS[@]}" >"$BUILD/build.log" 2>&1 ||
    { tail -n 40 "$BUILD/build.log" >&2; echo "fuzz.sh: build failed ($BUILD/build.log)" >&2; exit 1; }
fi
fi
[[ $MODE == build ]] && exit 0

# Sanitizers: any report aborts the run (a test failure); leaks are reported too.
export ASAN_OPTIONS="${ASAN_OPTIONS:-abort_on_error=1:detect_leaks=1:symbolize=1:allocator_may_return_null=1}"
export UBSAN_OPTIONS="${UBSAN_OPTIONS:-halt_on_error=1:print_stacktrace=1}"
# Leaks inside third-party libraries (each one documented in the file) are not reports.
export LSAN_OPTIONS="${LSAN_OPTIONS:-suppressions=$ROOT/fuzz/lsan.supp:print_suppressions=0}"
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
export SIMU_FUZZ_TMP="$TMP"
# libhdf5 1.10 loops forever on some corrupt heaps; the pair cache reader stops its reading process
# after this many silent seconds (a clean error), well before libFuzzer's own -timeout.
export SIMU_HDF5_TIMEOUT_S="${SIMU_HDF5_TIMEOUT_S:-2}"
status=0
for t in "${TARGETS[@]}"; do
  exe="$BUILD/$t"
  seeds="$ROOT/fuzz/corpus/$t"
  regress="$ROOT/fuzz/regressions/$t"
  dirs=("$seeds")
  [[ -d $regress ]] && dirs+=("$regress")
  if [[ $MODE == smoke ]]; then
    # 1. Every committed input once (seeds + regressions): none may crash or report.
    files=()
    for d in "${dirs[@]}"; do for f in "$d"/*; do [[ -f $f ]] && files+=("$f"); done; done
    if ! "$exe" -rss_limit_mb=4096 -timeout=30 "${files[@]}" >"$TMP/$t.replay.log" 2>&1; then
      tail -n 60 "$TMP/$t.replay.log" >&2; echo "FAIL: $t: a committed input crashed (log above)" >&2; status=1; continue
    fi
    # 2. A short fuzzing run from the seeds (new inputs go to a scratch corpus, not the tree).
    mkdir -p "$TMP/corpus-$t"
    if ! "$exe" -max_total_time="${SIMU_FUZZ_SMOKE_S:-8}" -rss_limit_mb=4096 -timeout=30 -max_len=65536 \
         -artifact_prefix="$TMP/" -print_final_stats=1 "$TMP/corpus-$t" "${dirs[@]}" >"$TMP/$t.fuzz.log" 2>&1; then
      tail -n 60 "$TMP/$t.fuzz.log" >&2
      for a in "$TMP"/crash-* "$TMP"/timeout-* "$TMP"/leak-* "$TMP"/oom-*; do
        [[ -f $a ]] && { mkdir -p "$BUILD/artifacts"; cp "$a" "$BUILD/artifacts/$t-$(basename "$a")"; }
      done
      echo "FAIL: $t: fuzzing found a crash (input saved under $BUILD/artifacts/)" >&2; status=1; continue
    fi
    execs=$(grep -m1 -o 'stat::number_of_executed_units: *[0-9]*' "$TMP/$t.fuzz.log" | grep -o '[0-9]*$' || echo '?')
    echo "ok: $t: ${#files[@]} committed inputs replayed, $execs executions in ${SIMU_FUZZ_SMOKE_S:-8} s"
  else
    work="$BUILD/work/$t"
    mkdir -p "$work/corpus" "$work/crashes"
    # Inputs a little larger than the largest seed: text parsers run faster on short inputs.
    case $t in
      fuzz_pair_cache) maxlen=65536 ;;
      fuzz_peft) maxlen=32768 ;;
      *) maxlen=8192 ;;
    esac
    args=(-max_total_time="$SECS" -rss_limit_mb=4096 -timeout=30 -max_len=$maxlen -artifact_prefix="$work/crashes/"
          -print_final_stats=1)
    ((RUNS > 0)) && args+=(-runs="$RUNS")
    start=$(date +%s)
    if [[ $t == fuzz_pair_cache ]]; then
      # Behind the guard: libhdf5 1.10's own crashes end a fork-mode child, libFuzzer starts another.
      # The work dir carries over between runs: corpus, crash inputs, and one line per run in executions.txt.
      execs=0 cpu=0
      if ((TRIAGE < 2)); then
        TIMEFORMAT='%U %S'
        # libFuzzer's fork mode lets its last jobs finish past -max_total_time (a job runs up to 300 s):
        # an interrupt at the deadline ends them (the execution count so far is in the log).
        { time SIMU_HDF5_ISOLATE=0 timeout -s INT -k 30 $((SECS + 5)) "$exe" "${args[@]}" -fork="$JOBS" -ignore_crashes=1 -ignore_timeouts=1 -ignore_ooms=1 -timeout=5 \
          "$work/corpus" "${dirs[@]}" >"$work/fuzz.log" 2>&1; } 2>"$work/cpu.txt" || true
        cpu=$(awk '{printf "%.0f", $1 + $2}' "$work/cpu.txt")
        execs=$(grep -o '^#[0-9]*' "$work/fuzz.log" | tail -n 1 | tr -d '#')
        echo "${execs:-0} $(( $(date +%s) - start )) $cpu" >>"$work/executions.txt"
      fi
      total=$(awk '{e += $1; w += $2; c += $3} END {printf "%d executions in %d s (%d s CPU) over %d run(s)", e, w, c, NR}' \
        "$work/executions.txt" 2>/dev/null || echo "no runs")
      nart=$(find "$work/crashes" -type f | wc -l)
      if ((TRIAGE == 0)); then
        echo "ok: $t: ${execs:-?} executions in $(( $(date +%s) - start )) s ($cpu s CPU) behind the guard, this run;" \
          "total $total; $nart libhdf5 crash/hang inputs so far, not replayed yet (--triage-only); log $work/fuzz.log"
        continue
      fi
      # Triage with the guard on (as users run it): every input must end cleanly, each in its own process
      # (in parallel); the ones that do not are listed in $work/failing.txt, their logs under $work/triage/.
      r=ok
      rm -rf "$work/triage" && mkdir -p "$work/triage"
      : >"$work/failing.txt"
      if ((nart)); then
        find "$work/crashes" -type f -print0 |
          xargs -0 -P "$(nproc)" -I{} sh -c 'timeout 120 "$0" -rss_limit_mb=4096 -timeout=60 "$1" >"$2/$(basename "$1").log" 2>&1 || echo "$1"' \
            "$exe" {} "$work/triage" >>"$work/failing.txt" || true
      fi
      nfail=$(wc -l <"$work/failing.txt")
      ((nfail)) && { r=CRASH; status=1; }
      echo "$r: $t: total $total behind the guard; $nart libhdf5 crash/hang inputs, $nfail of them failing with the" \
        "guard on (listed in $work/failing.txt); triage $(( $(date +%s) - start )) s; corpus $(ls "$work/corpus" | wc -l) files," \
        "log $work/fuzz.log"
      continue
    fi
    # CPU seconds beside wall seconds: on a shared machine the CPU rate is the one to compare.
    # --jobs N > 1: libFuzzer's fork mode with N parallel processes (one corpus, one execution count).
    ((JOBS > 1)) && args+=(-fork="$JOBS")
    TIMEFORMAT='%U %S'
    if { time "$exe" "${args[@]}" "$work/corpus" "${dirs[@]}" >"$work/fuzz.log" 2>&1; } 2>"$work/cpu.txt"; then
      r=ok
    else
      r=CRASH; status=1
    fi
    cpu=$(awk '{printf "%.0f", $1 + $2}' "$work/cpu.txt")
    if ((JOBS > 1)); then
      execs=$(grep -o '^#[0-9]*' "$work/fuzz.log" | tail -n 1 | tr -d '#')
    else
      execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$work/fuzz.log" | grep -o '[0-9]*$' | awk '{s+=$1} END {print s+0}')
    fi
    echo "$r: $t: $execs executions in $(( $(date +%s) - start )) s ($cpu s CPU, $(( execs / (cpu > 0 ? cpu : 1) )) per CPU second)," \
      "corpus $(ls "$work/corpus" | wc -l) files, log $work/fuzz.log"
    [[ $r == ok ]] || ls "$work/crashes"
  fi
done
exit $status
