#!/usr/bin/env bash
# End-to-end test of the train_ss_vae program on the CPU, on the shape world (ctest: TrainSsVaeCli.EndToEnd).
#   bash tests/training/train_ss_vae_cli_test.sh BUILD_DIR REPO_ROOT
# configs/miniature/ss_vae.yaml shrunk to 16^3 grids, 8-channel networks, a global batch of 4, 4 steps:
#  1. (a) 4 steps straight vs (b) 2 steps, then --resume latest to 4: the exported weights are the same
#     bytes and the metrics of steps 3-4 the same values (timings aside).
#  2. (c) --nproc-per-node 2: only rank 0 writes (one metrics line per step and per evaluation, as (a));
#     every step's loss equals (a)'s within 1e-5 relative (the rank split reorders float32 sums of a
#     few hundred terms: ~1e-7).
#  3. --evaluate on (a)'s weights prints the test table and writes weights/eval.json; a fresh run into
#     (a)'s out_dir is refused, naming it.
set -euo pipefail
if [[ $# -ne 2 ]]; then
  echo "usage: $0 BUILD_DIR REPO_ROOT" >&2
  exit 2
fi
BUILD=$(cd "$1" && pwd)
REPO=$(cd "$2" && pwd)
TMP=$(mktemp -d "${TMPDIR:-/tmp}/train_ss_vae_cli.XXXXXX")
trap 'rm -rf "$TMP"' EXIT
fail() { echo "FAIL: $*" >&2; exit 1; }

run() {  # run OUT_DIR STEPS [args...]
  local out=$1 steps=$2
  shift 2
  "$BUILD/train_ss_vae" --config "$REPO/configs/miniature/ss_vae.yaml" \
    --set train.device=cpu --set train.precision=fp32 --set data.resolution=16 --set data.global_batch=4 \
    --set data.workers=2 --set 'model.encoder.channels=[8, 8, 8]' --set 'model.decoder.channels=[8, 8, 8]' \
    --set optim.warmup_steps=1 --set eval.every=2 --set eval.val_per_family=1 --set eval.test_per_family=1 \
    --set run.checkpoint_every=2 --set run.progress=false --set run.out_dir="$out" --set train.steps="$steps" "$@"
}
# A metrics line without its timings.
untimed() { sed -E 's/,?"(shapes_per_s|time\/[a-z_]+)":[^,}]*//g' "$1"; }

# 1. Resume equals uninterrupted.
run "$TMP/a" 4 >"$TMP/a.log" 2>&1 || { cat "$TMP/a.log"; fail "(a) failed"; }
run "$TMP/b" 2 >"$TMP/b.log" 2>&1 || { cat "$TMP/b.log"; fail "(b) failed"; }
run "$TMP/b" 4 --resume latest >>"$TMP/b.log" 2>&1 || { cat "$TMP/b.log"; fail "(b) resume failed"; }
grep -q "resumed from .*step_00000002 at step 2" "$TMP/b.log" || fail "(b) did not resume at step 2"
for f in ss_encoder.safetensors ss_decoder.safetensors ss_encoder.json ss_decoder.json; do
  cmp -s "$TMP/a/weights/$f" "$TMP/b/weights/$f" || fail "resumed weights/$f differs from the uninterrupted run's"
done
diff <(untimed "$TMP/a/metrics.jsonl" | grep -E '"step":(3|4)[,}]') \
     <(untimed "$TMP/b/metrics.jsonl" | grep -E '"step":(3|4)[,}]') >/dev/null ||
  fail "metrics of steps 3-4 differ after the resume"
echo "ok: resume is bit-identical (weights, metrics)"

# 2. Two local ranks.
run "$TMP/c" 4 --nproc-per-node 2 >"$TMP/c.log" 2>&1 || { cat "$TMP/c.log"; fail "(c) failed"; }
[[ $(wc -l <"$TMP/c/metrics.jsonl") == $(wc -l <"$TMP/a/metrics.jsonl") ]] || fail "(c) metrics.jsonl has other lines than (a)"
[[ $(ls "$TMP/c/tensorboard" | wc -l) == 1 ]] || fail "(c) wrote more than one event file"
paste -d' ' <(grep -o '"loss":[-0-9.e]*' "$TMP/a/metrics.jsonl" | cut -d: -f2) \
            <(grep -o '"loss":[-0-9.e]*' "$TMP/c/metrics.jsonl" | cut -d: -f2) |
  awk '{ d = $1 - $2; if (d < 0) d = -d; if (d > 1e-5 * ($1 < 0 ? -$1 : $1)) { print "step " NR ": " $1 " vs " $2; bad = 1 } }
       END { exit bad }' || fail "2 ranks' losses differ from 1 rank's"
[[ $(grep -c '"loss"' "$TMP/a/metrics.jsonl") == 4 ]] || fail "(a) logged $(grep -c '"loss"' "$TMP/a/metrics.jsonl") steps, 4 expected"
echo "ok: 2 ranks == 1 rank (losses within 1e-5), rank 0 alone writes"

# 3. --evaluate and the out-dir check.
run "$TMP/a" 4 --evaluate "$TMP/a/weights" >"$TMP/e.log" 2>&1 || { cat "$TMP/e.log"; fail "--evaluate failed"; }
grep -q "| mug (held out) | 1 |" "$TMP/e.log" || { cat "$TMP/e.log"; fail "--evaluate printed no held-out row"; }
[[ -s "$TMP/a/weights/eval.json" ]] || fail "--evaluate wrote no eval.json"
if run "$TMP/a" 4 >"$TMP/f.log" 2>&1; then fail "a fresh run into a used out_dir was accepted"; fi
grep -q "already holds an earlier run" "$TMP/f.log" || fail "the refusal does not say why"
echo "ok: --evaluate, out-dir check"
