#!/usr/bin/env bash
# End-to-end test of the train_fmdpo program on the CPU (ctest: TrainFmdpoCli.EndToEnd).
#   bash tests/training/train_fmdpo_cli_test.sh BUILD_DIR REPO_ROOT
# Fixture model: $SIMU_SHARED_DIR/fixtures, else REPO_ROOT/../shared/fixtures. Comparisons run in
# $SIMU_PYTHON, else REPO_ROOT/.deps/venv/bin/python (torch, numpy, safetensors, tensorboard).
#
# On a synthetic cache and configs/tiny.yaml (global batch 4 = micro 2 x ...), 6 steps:
#  1. (a) one process, (b) train_fmdpo --nproc-per-node 2, (c) torchrun --nproc-per-node 2 --no-python
#     train_fmdpo: final PEFT adapters, checkpoints (adapter + optimizer) and the non-timing metrics of
#     every step are bit-identical to (a). Exact equality is expected, not a tolerance: every run does
#     the same micro-batch forwards (micro 2), the loss is scaled by 1/share (1/4 or 1/2: powers of two,
#     so the gradients scale exactly), and averaging two ranks adds the same two fp32 gradients that one
#     process accumulates (a + b is commutative); metrics are float32 terms summed in float64 (exact for
#     a few terms). Measured bit-identical, also with OMP_NUM_THREADS 1..8.
#  2. Only rank 0 writes: (b) and (c) form a world of 2 (rank 0 logs "world 2"), their out_dir holds
#     the same files as (a)'s (one metrics.jsonl with one line per step, one event file, the same
#     checkpoints), nothing named after rank 1 anywhere under the test's dir (TMPDIR included: the
#     launcher's per-rank heartbeat files are removed), no rank-1 log text in out_dir, and the
#     progress lines are printed once.
#  3. Resume equals uninterrupted, with LoRA dropout 0.1 (so the RNG state must be restored):
#     (d) is SIGKILLed right after its step-4 checkpoint lands (SIMU_CHECKPOINT_STALL_MS slows the
#     checkpoint writer so the kill always comes before the end), then `--resume latest` finishes it;
#     its adapter and metrics lines (steps 5-6, and 1-4) equal an uninterrupted run (e) bit for bit.
#  4. TensorBoard's EventAccumulator reads run.out_dir/tensorboard: one 'loss' value per step equal to
#     metrics.jsonl's loss in float32, and the same tags as the metrics keys.
#  5. (a)'s metrics.jsonl lines carry loss, accuracy (in [0,1]), margin, grad_norm, lr, pairs_per_s,
#     time/*, and completion|preservation/{policy,ref}_{pos,neg}.
#  6. An inputs-mode cache (pairs make --cond-mode inputs; it validates): train_fmdpo loads the condition
#     embedder named by model.embedder_config (the demo's small one, random weights seeded by train.seed)
#     and runs it in the step; one process (f) and --nproc-per-node 2 (g) give bit-identical adapters.
# Without torchrun (or the venv python it needs) part (c) is skipped ("SKIP: ..."); the rest always runs.
set -euo pipefail

if [[ $# -ne 2 ]]; then
  echo "usage: $0 BUILD_DIR REPO_ROOT" >&2
  exit 2
fi
BUILD=$(cd "$1" && pwd)
REPO=$(cd "$2" && pwd)
# The project's python (CMake's SIMU_PYTHON, passed by ctest), else the venv of scripts/setup.sh.
PY=${SIMU_PYTHON:-$REPO/.deps/venv/bin/python}
PY=$(command -v "$PY" || echo "$PY")  # a bare name ("python3") -> its path
TORCHRUN=$(dirname "$PY")/torchrun
FIX=${SIMU_SHARED_DIR:-$REPO/../shared}/fixtures
TRAIN=$BUILD/train_fmdpo
PAIRS=$BUILD/pairs
STEPS=6

fail() {
  echo "FAIL: $*" >&2
  exit 1
}
for f in "$TRAIN" "$PAIRS"; do [[ -x $f ]] || fail "$f not found (build the project first)"; done
for f in ss_generator_small.json ss_generator_small.safetensors; do
  [[ -f $FIX/$f ]] || fail "fixture $FIX/$f not found (set SIMU_SHARED_DIR)"
done
[[ -x $PY ]] || fail "$PY not found: the comparisons need the venv python (run scripts/setup.sh)"

WORK=$(mktemp -d "${TMPDIR:-/tmp}/train_fmdpo_cli.XXXXXX")
BG_PID=
cleanup() {
  if [[ -n $BG_PID ]] && kill -0 "$BG_PID" 2>/dev/null; then kill -9 "$BG_PID" 2>/dev/null || true; fi
  if [[ -n ${KEEP_WORK:-} ]]; then echo "work dir kept: $WORK" >&2; else rm -rf "$WORK"; fi
}
trap cleanup EXIT
# Every temporary file of the programs (launcher heartbeats, torchrun's logs) lands under $WORK.
export TMPDIR=$WORK/tmp
mkdir -p "$TMPDIR"
cd "$REPO"
SECONDS=0

# Runs a command with a time limit, output to LOG; fails with the log's tail if it does not exit 0.
run_logged() {
  local name=$1 log=$2
  shift 2
  local rc=0
  timeout 300 "$@" >"$log" 2>&1 || rc=$?
  if [[ $rc -ne 0 ]]; then
    tail -n 30 "$log" >&2
    fail "run $name exited with status $rc (log above: $log)"
  fi
}

CACHE=$WORK/pairs.h5
run_logged pairs "$WORK/pairs.log" "$PAIRS" make --out "$CACHE" --n 16 --tokens 64 --channels 8 --cond-len 10 \
  --cond-len-min 10 --cond-channels 48
# Common options: fixture model by absolute path, the cache, 6 steps, a checkpoint every 2 steps.
COMMON=(--config "$REPO/configs/tiny.yaml" --set "model.config=$FIX/ss_generator_small.json"
  --set "model.weights=$FIX/ss_generator_small.safetensors" --set "data.cache=$CACHE" --set "train.steps=$STEPS"
  --set run.checkpoint_every=2 --set run.keep_last=2)

# Comparison helpers (python).
CHECK=$WORK/check.py
cat >"$CHECK" <<'PYEOF'
import json, math, os, sys
import numpy as np
from safetensors.numpy import load_file

def die(msg):
    print("FAIL: " + msg, file=sys.stderr)
    sys.exit(1)

TIMING = lambda k: k.startswith("time/") or k == "pairs_per_s"

def metrics(path):
    rows = []
    with open(path) as f:
        for i, line in enumerate(f, 1):
            try:
                rows.append(json.loads(line))
            except ValueError as e:
                die(f"{path}:{i}: not JSON ({e}): {line[:80]!r}")
    return rows

def steps_ok(path, rows, steps):
    got = [r.get("step") for r in rows]
    if got != list(range(1, steps + 1)):
        die(f"{path}: steps {got}, expected exactly one line per step 1..{steps}")

def cmd_adapters(a, b, what):
    # Bit-exact: same names, dtypes, shapes and bytes.
    ta, tb = load_file(a), load_file(b)
    if sorted(ta) != sorted(tb):
        die(f"{what}: tensor names differ: {sorted(set(ta) ^ set(tb))[:5]} ({a} vs {b})")
    bad = []
    for k in sorted(ta):
        x, y = ta[k], tb[k]
        if x.dtype != y.dtype or x.shape != y.shape:
            bad.append(f"{k}: {x.dtype}{list(x.shape)} vs {y.dtype}{list(y.shape)}")
        elif not np.array_equal(np.ascontiguousarray(x).view(np.uint8), np.ascontiguousarray(y).view(np.uint8)):
            d = np.abs(x.astype(np.float64) - y.astype(np.float64))
            bad.append(f"{k}: max |diff| {d.max():.3e} ({int((d > 0).sum())} of {d.size} values differ)")
    if bad:
        die(f"{what}: tensors not bit-identical ({len(bad)} of {len(ta)} tensors):\n  " + "\n  ".join(bad[:8])
            + f"\n  files: {a} vs {b}")

def cmd_metrics(a, b, steps, first, what):
    # Non-timing values of steps first..steps, exactly; both files one line per step.
    ra, rb = metrics(a), metrics(b)
    steps_ok(a, ra, steps)
    steps_ok(b, rb, steps)
    bad = []
    for x, y in zip(ra[first - 1:], rb[first - 1:]):
        kx = {k for k in x if not TIMING(k)}
        ky = {k for k in y if not TIMING(k)}
        if kx != ky:
            bad.append(f"step {x['step']}: keys differ: {sorted(kx ^ ky)}")
            continue
        for k in sorted(kx):
            if x[k] != y[k]:
                bad.append(f"step {x['step']} {k}: {x[k]!r} vs {y[k]!r}")
    if bad:
        die(f"{what}: metrics differ ({a} vs {b}):\n  " + "\n  ".join(bad[:10]))

def cmd_keys(path, steps):
    rows = metrics(path)
    steps_ok(path, rows, steps)
    need = ["loss", "accuracy", "margin", "grad_norm", "lr", "pairs_per_s", "time/step_s", "time/data_wait_s",
            "time/compute_s", "time/allreduce_s", "time/optimizer_s"]
    need += [f"{kind}/{side}_{pn}" for kind in ("completion", "preservation") for side in ("policy", "ref")
             for pn in ("pos", "neg")]
    for r in rows:
        s = r["step"]
        missing = [k for k in need if k not in r]
        if missing:
            die(f"{path}: step {s}: missing keys {missing} (the per-kind keys are omitted when a global batch "
                f"has no pair of that kind)")
        bad = [k for k in need if not isinstance(r[k], (int, float)) or not math.isfinite(r[k])]
        if bad:
            die(f"{path}: step {s}: non-finite or non-numeric {[(k, r[k]) for k in bad]}")
        if not 0.0 <= r["accuracy"] <= 1.0:
            die(f"{path}: step {s}: accuracy {r['accuracy']} not in [0, 1]")
        if not (r["lr"] > 0 and r["grad_norm"] >= 0 and r["pairs_per_s"] > 0 and r["loss"] >= 0):
            die(f"{path}: step {s}: implausible lr/grad_norm/pairs_per_s/loss {r}")

def cmd_tensorboard(out_dir, steps):
    # A killed + resumed run must show one point per step too: the resumed writer's SessionLog.START
    # makes TensorBoard drop what the killed run logged after its checkpoint.
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    tbdir = os.path.join(out_dir, "tensorboard")
    ea = EventAccumulator(tbdir, size_guidance={"scalars": 0})
    ea.Reload()
    rows = metrics(os.path.join(out_dir, "metrics.jsonl"))
    tags = set(ea.Tags()["scalars"])
    want = {k for r in rows for k in r if k != "step"}
    if tags != want:
        die(f"{tbdir}: scalar tags {sorted(tags)} != metrics.jsonl keys {sorted(want)}")
    loss = ea.Scalars("loss")
    if [e.step for e in loss] != list(range(1, steps + 1)):
        die(f"{tbdir}: 'loss' has steps {[e.step for e in loss]}, expected one value per step 1..{steps}")
    for e, r in zip(loss, rows):
        if np.float32(e.value) != np.float32(r["loss"]):
            die(f"{tbdir}: step {e.step}: TensorBoard loss {e.value!r} != float32(metrics loss {r['loss']!r})")

cmd = sys.argv[1]
if cmd == "adapters": cmd_adapters(sys.argv[2], sys.argv[3], sys.argv[4])
elif cmd == "metrics": cmd_metrics(sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), sys.argv[6])
elif cmd == "keys": cmd_keys(sys.argv[2], int(sys.argv[3]))
elif cmd == "tensorboard": cmd_tensorboard(sys.argv[2], int(sys.argv[3]))
else: die(f"unknown check {cmd}")
PYEOF
check() { "$PY" "$CHECK" "$@"; }

# Files of an out_dir, relative, with the event file's host.pid suffix normalised.
listing() { (cd "$1" && find . -mindepth 1 | sed -E 's#(events\.out\.tfevents)\..*#\1.X#' | LC_ALL=C sort); }

# ---- 1. one process, launcher, torchrun --------------------------------------------------------
A=$WORK/a
run_logged a "$WORK/a.log" "$TRAIN" "${COMMON[@]}" --set "run.out_dir=$A"
[[ -f $A/adapter/adapter_model.safetensors ]] || fail "(a) wrote no $A/adapter/adapter_model.safetensors"

B=$WORK/b
run_logged b "$WORK/b.log" "$TRAIN" --nproc-per-node 2 "${COMMON[@]}" --set "run.out_dir=$B"
MULTI=(b)

C=$WORK/c
if [[ ! -x $TORCHRUN ]]; then
  echo "SKIP: $TORCHRUN not found: the torchrun run (c) is skipped"
elif ! "$PY" -c 'import torch.distributed.run' 2>/dev/null; then
  echo "SKIP: $PY cannot import torch.distributed.run: the torchrun run (c) is skipped"
else
  PORT=$("$PY" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
  run_logged c "$WORK/c.log" "$TORCHRUN" --nnodes 1 --nproc-per-node 2 --master-addr 127.0.0.1 --master-port "$PORT" \
    --no-python "$TRAIN" "${COMMON[@]}" --set "run.out_dir=$C"
  MULTI+=(c)
fi

for x in "${MULTI[@]}"; do
  D=$WORK/$x
  [[ -f $D/adapter/adapter_model.safetensors ]] || fail "($x) wrote no $D/adapter/adapter_model.safetensors"
  check adapters "$A/adapter/adapter_model.safetensors" "$D/adapter/adapter_model.safetensors" \
    "final adapter of ($x) 2 ranks vs (a) 1 process"
  for ck in "$A"/checkpoints/step_*; do
    s=$(basename "$ck")
    for f in adapter optimizer; do
      [[ -f $D/checkpoints/$s/$f.safetensors ]] || fail "($x) has no checkpoints/$s/$f.safetensors, (a) has"
      check adapters "$ck/$f.safetensors" "$D/checkpoints/$s/$f.safetensors" "checkpoint $s/$f of ($x) vs (a)"
    done
  done
  check metrics "$A/metrics.jsonl" "$D/metrics.jsonl" "$STEPS" 1 "metrics.jsonl of ($x) vs (a)"
done
echo "ok 1: 1 process, --nproc-per-node 2${MULTI[1]:+, torchrun} give bit-identical adapters, checkpoints, metrics ($SECONDS s)"

# ---- 2. only rank 0 writes ---------------------------------------------------------------------
listing "$A" >"$WORK/a.files"
for x in "${MULTI[@]}"; do
  D=$WORK/$x
  grep -q "world 2" "$WORK/$x.log" || fail "($x): rank 0 did not log a world of 2 ranks (rendezvous env ignored?): $WORK/$x.log"
  n=$(grep -c "^step $STEPS/$STEPS " "$WORK/$x.log" || true)
  [[ $n -eq 1 ]] || fail "($x): the progress line 'step $STEPS/$STEPS' was printed $n times (only rank 0 reports)"
  listing "$D" >"$WORK/$x.files"
  diff -u "$WORK/a.files" "$WORK/$x.files" >&2 ||
    fail "($x): files under out_dir differ from the 1-process run (a) (diff above: - a, + $x)"
  n=$(find "$D/tensorboard" -name 'events.out.tfevents.*' | wc -l)
  [[ $n -eq 1 ]] || fail "($x): $n TensorBoard event files, expected 1 (rank 0's)"
  if grep -rlE --exclude='*.safetensors' --exclude='events.out.tfevents.*' 'rank 1' "$D" >&2; then fail "($x): rank-1 log text in the files above"; fi
done
# Anything named after rank 1 anywhere under the test's dir (out dirs and TMPDIR; torchrun's own
# per-rank log folders torchelastic_*/.../attempt_N/<rank> are not the program's).
named=$(find "$WORK" -iname '*rank*1*' -o -iname '*rank*_1*' -o -iname '*.1.log' -o -iname '*_1.jsonl' | grep -v '/torchelastic_' || true)
[[ -z $named ]] || fail "files named after rank 1: $named"
left=$(find "$TMPDIR" -maxdepth 1 -name 'simu_launch_*' | head -n 3)
[[ -z $left ]] || fail "--nproc-per-node left its per-rank heartbeat dir behind: $left"
echo "ok 2: only rank 0 wrote into out_dir (${MULTI[*]}) ($SECONDS s)"

# ---- 3. kill -9 after the step-4 checkpoint, resume == uninterrupted (LoRA dropout 0.1) --------
DROP=(--set lora.dropout=0.1)
E=$WORK/e
run_logged e "$WORK/e.log" "$TRAIN" "${COMMON[@]}" "${DROP[@]}" --set "run.out_dir=$E"
check adapters "$A/adapter/adapter_model.safetensors" "$E/adapter/adapter_model.safetensors" "dropout check" 2>/dev/null &&
  fail "lora.dropout=0.1 did not change the trained adapter: the resume test would not exercise the RNG restore"

D=$WORK/d
CK4=$D/checkpoints/step_00000004
# The stall pauses the checkpoint writer 3 x 500 ms before each checkpoint lands, so after step 4's
# lands the run needs > 1.5 s more (steps 5-6, then step 6's checkpoint): the kill comes first.
SIMU_CHECKPOINT_STALL_MS=500 "$TRAIN" "${COMMON[@]}" "${DROP[@]}" --set "run.out_dir=$D" >"$WORK/d1.log" 2>&1 &
BG_PID=$!
deadline=$((SECONDS + 300))
until [[ -f $CK4/train_state.json ]]; do
  kill -0 "$BG_PID" 2>/dev/null || break
  [[ $SECONDS -lt $deadline ]] || break
  sleep 0.05
done
kill -9 "$BG_PID" 2>/dev/null || true
rc=0
{ wait "$BG_PID"; } 2>/dev/null || rc=$?  # (silences bash's "Killed" job report)
BG_PID=
[[ -f $CK4/train_state.json ]] || { tail -n 20 "$WORK/d1.log" >&2; fail "(d) ended (status $rc) without writing $CK4"; }
if [[ $rc -ne 137 || -d $D/checkpoints/step_00000006 || -d $D/adapter ]]; then
  fail "(d) was not killed mid-run (status $rc; step_00000006 or adapter/ exists): it finished too fast"
fi
run_logged d-resume "$WORK/d2.log" "$TRAIN" "${COMMON[@]}" "${DROP[@]}" --set "run.out_dir=$D" --resume latest
grep -qE "resumed from .*/checkpoints/step_00000004 at step 4 " "$WORK/d2.log" || fail "(d) resume did not start from $CK4 at step 4: $WORK/d2.log"
check adapters "$E/adapter/adapter_model.safetensors" "$D/adapter/adapter_model.safetensors" \
  "final adapter of killed+resumed (d) vs uninterrupted (e)"
check metrics "$E/metrics.jsonl" "$D/metrics.jsonl" "$STEPS" 5 "metrics.jsonl steps 5-$STEPS of resumed (d) vs (e)"
check metrics "$E/metrics.jsonl" "$D/metrics.jsonl" "$STEPS" 1 "metrics.jsonl steps 1-$STEPS of resumed (d) vs (e)"
echo "ok 3: SIGKILL after step 4 + --resume latest == uninterrupted, with dropout ($SECONDS s)"

# ---- 4. TensorBoard ----------------------------------------------------------------------------
for x in a "${MULTI[@]}" e; do check tensorboard "$WORK/$x" "$STEPS"; done
# The killed + resumed run: one point per step, the resumed run's (none left from after the kill).
check tensorboard "$D" "$STEPS"
echo "ok 4: TensorBoard event files load, 'loss' matches metrics.jsonl ($SECONDS s)"

# ---- 5. metrics keys ---------------------------------------------------------------------------
check keys "$A/metrics.jsonl" "$STEPS"
echo "ok 5: metrics.jsonl keys and ranges ($SECONDS s)"

# ---- 6. inputs-mode cache ------------------------------------------------------------------------
# The demo embedder with its image ViT at 70 px: 136 tokens x 48 channels (the small generator's).
# Inputs stored at the ViTs' and point embedder's own sizes (70, 32), so the embedder resizes nothing:
# LibTorch's CPU bilinear resize rounds differently with 1 thread (each of 2 ranks) than with 2.
EMB=$WORK/embedder.json
"$PY" -c "import json, sys; j = json.load(open(sys.argv[1])); j['dino_image_input_size'] = 70; json.dump(j, open(sys.argv[2], 'w'))" \
  "$REPO/configs/demo_embedder_small.json" "$EMB"
ICACHE=$WORK/inputs.h5
run_logged pairs-inputs "$WORK/pairs_inputs.log" "$PAIRS" make --out "$ICACHE" --n 8 --tokens 64 --channels 8 \
  --cond-mode inputs --cond-len 136 --cond-channels 48 --input-size 70 --pointmap-size 32
run_logged validate-inputs "$WORK/validate_inputs.log" "$PAIRS" validate "$ICACHE"
INPUTS=(--config "$REPO/configs/tiny.yaml" --set "model.config=$FIX/ss_generator_small.json" --set "model.weights=''"
  --set "model.embedder_config=$EMB" --set "data.cache=$ICACHE" --set train.steps=2 --set run.checkpoint_every=0)
run_logged f "$WORK/f.log" "$TRAIN" "${INPUTS[@]}" --set "run.out_dir=$WORK/f"
run_logged g "$WORK/g.log" "$TRAIN" "${INPUTS[@]}" --set "run.out_dir=$WORK/g" --nproc-per-node 2
grep -q "condition embedder .* runs in the step" "$WORK/f.log" || fail "(f) did not load the condition embedder: $WORK/f.log"
check adapters "$WORK/f/adapter/adapter_model.safetensors" "$WORK/g/adapter/adapter_model.safetensors" \
  "inputs-mode cache: adapter of one process (f) vs --nproc-per-node 2 (g)"
echo "ok 6: inputs-mode cache: embedder in the step, 1 process == 2 ranks ($SECONDS s)"
echo "PASS: train_fmdpo end-to-end ($SECONDS s)"
