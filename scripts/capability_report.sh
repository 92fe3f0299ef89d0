#!/usr/bin/env bash
# Prints which CPU kernel sets a test run exercised: the ordinary ctest pass (torch's choice in this
# environment, as tests/models/cpu_capability_test.cpp reports it) and the extra passes of
# scripts/capability_pass.sh (BUILD/capability_passes/*). `./run test` calls it after ctest.
#   scripts/capability_report.sh BUILD_DIR
set -uo pipefail
BUILD="${1:?usage: capability_report.sh BUILD_DIR}"
PROBE="$BUILD/test_models"
echo "CPU kernel sets exercised:"
if [[ -x $PROBE ]]; then
  line="$("$PROBE" --gtest_filter='CpuCapability.*' 2>&1 | sed -n 's/^\[cpu capability\] //p' | head -n 1)"
  echo "  every suite (ctest): ${line:-unknown (the probe printed nothing)}"
else
  echo "  every suite (ctest): unknown ($PROBE is not built)"
fi
shopt -s nullglob
passes=("$BUILD"/capability_passes/*)
if ((${#passes[@]} == 0)); then
  echo "  no other kernel set (the CpuCapability.* ctest passes did not run)"
else
  for f in "${passes[@]}"; do echo "  $(cat "$f")"; done
fi
