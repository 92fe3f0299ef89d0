#!/usr/bin/env bash
# One pass of a numerics-heavy CPU suite (models, lora or training) under a CPU kernel set other than
# the machine's best: ATen's ATEN_CPU_CAPABILITY one step down (AVX-512 -> avx2, AVX2 -> default).
# The tolerances of these suites must hold on any kernel set (tests/tolerance.h); the ordinary ctest
# pass runs them on the best one. Registered with ctest as CpuCapability.<suite>, so `./run test` runs
# it; it records what ran in BUILD/capability_passes/<suite> for scripts/capability_report.sh.
#   scripts/capability_pass.sh BUILD_DIR SUITE [gtest args...]
# Exit status: the suite's; 77 (ctest: skipped) when torch has only its default kernels here.
set -euo pipefail
BUILD="${1:?usage: capability_pass.sh BUILD_DIR SUITE [gtest args...]}"
SUITE="${2:?usage: capability_pass.sh BUILD_DIR SUITE [gtest args...]}"
shift 2
EXE="$BUILD/test_$SUITE"
PROBE="$BUILD/test_models"
[[ -x $EXE ]] || { echo "capability_pass: $EXE is not built" >&2; exit 1; }
[[ -x $PROBE ]] || { echo "capability_pass: $PROBE (the capability probe) is not built" >&2; exit 1; }

# What torch reports with the given env arguments (tests/models/cpu_capability_test.cpp prints it;
# its own failure, a request not honoured, is checked below from the value).
capability() {
  { env "$@" "$PROBE" --gtest_filter='CpuCapability.*' 2>&1 || true; } |
    sed -n 's/^\[cpu capability\] \([A-Z0-9_]*\).*/\1/p' | head -n 1
}

best="$(capability -u ATEN_CPU_CAPABILITY)"
case "$best" in
  AVX512*) other=avx2 ;;
  AVX2) other=default ;;
  *)
    echo "capability_pass: torch's best kernel set here is '${best:-unknown}': no other to run $SUITE under"
    mkdir -p "$BUILD/capability_passes"
    echo "test_$SUITE: skipped (best kernel set ${best:-unknown}, none below it)" >"$BUILD/capability_passes/$SUITE"
    exit 77
    ;;
esac
# The request must be honoured (the probe fails otherwise), or this pass would exercise nothing new.
got="$(capability ATEN_CPU_CAPABILITY="$other")"
if [[ ${got,,} != "$other" ]]; then
  echo "capability_pass: ATEN_CPU_CAPABILITY=$other gave '$got'" >&2
  exit 1
fi

echo "capability_pass: test_$SUITE under ATEN_CPU_CAPABILITY=$other (machine best: $best)"
start=$SECONDS
rc=0
ATEN_CPU_CAPABILITY="$other" "$EXE" --gtest_brief=1 "$@" || rc=$?
mkdir -p "$BUILD/capability_passes"
status=passed
((rc == 0)) || status="FAILED (status $rc)"
echo "test_$SUITE: $got ($status, $((SECONDS - start)) s)" >"$BUILD/capability_passes/$SUITE"
exit $rc
