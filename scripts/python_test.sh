#!/usr/bin/env bash
# The Python module's checks (./run test runs them after ctest; CI with it): the types (mypy on the
# package, the example and the tests; mypy.stubtest of the _core stubs against the built module), the
# pytest suite (tests/python) and the example (examples/lift_probe_mujoco.py) on the small models.
#   scripts/python_test.sh [pytest args]      SIMU_SKIP_PYTHON_TESTS=1 skips all of it
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BUILD="${BUILD_DIR:-$ROOT/build}"
PY="${SIMU_PYTHON:-$ROOT/.deps/venv/bin/python}"
if [ "${SIMU_SKIP_PYTHON_TESTS:-0}" = 1 ]; then echo "[python] skipped (SIMU_SKIP_PYTHON_TESTS=1)"; exit 0; fi
if ! ls "$BUILD"/python/simuscene/_core*.so >/dev/null 2>&1; then
  echo "[python] error: $BUILD/python/simuscene/_core*.so not built (CMake: SIMU_BUILD_PYTHON, Python headers)" >&2
  exit 1
fi
export PYTHONPATH="$BUILD/python${PYTHONPATH:+:$PYTHONPATH}" SIMU_BUILD_DIR="$BUILD"
export SIMU_SHARED_DIR="${SIMU_SHARED_DIR:-$ROOT/../shared}"
cd "$ROOT"
echo "[python] mypy (package, example, tests) and stubtest (_core.pyi against the built module)"
"$PY" -m mypy --config-file python/mypy.ini python/simuscene examples tests/python
"$PY" -m mypy.stubtest simuscene._core --mypy-config-file python/mypy.ini --allowlist python/stubtest_allowlist.txt
echo "[python] example: examples/lift_probe_mujoco.py (small models)"
"$PY" examples/lift_probe_mujoco.py --out "$BUILD/python-example" >"$BUILD/python-example.log" 2>&1 ||
  { tail -n 40 "$BUILD/python-example.log" >&2; echo "[python] the example failed: $BUILD/python-example.log" >&2; exit 1; }
tail -n 1 "$BUILD/python-example.log"
echo "[python] pytest tests/python"
exec "$PY" -m pytest -q tests/python "$@"
