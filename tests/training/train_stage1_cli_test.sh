#!/usr/bin/env bash
# End-to-end test of build_stage1_data and train_stage1 on the CPU (ctest: TrainStage1Cli.EndToEnd).
#   bash tests/training/train_stage1_cli_test.sh BUILD_DIR REPO_ROOT
# A tiny model (one block, 2^3 shape latent, one-block ViTs at 28 px, point maps at 8 px), 8^3 occupancy
# and random-linear shape targets (no VAE needed):
#  1. build_stage1_data writes a cache of 3 train and 1 val world scenes with 2 threads, and again with
#     1 thread: the two files hold the same samples (the writer keeps scene order); the cache has train
#     and val samples and no test ones.
#  2. train_stage1: 6 steps in one run (a) and in two (b: run.stop_at_step=3, then --resume latest):
#     the exported weights, the last checkpoint's parameters, optimizer and EMA state are bit-identical,
#     and (b)'s first run exported nothing.
#  3. A fresh run into an out_dir that holds a run is refused (naming run.out_dir), --overwrite replaces it.
set -euo pipefail

if [[ $# -ne 2 ]]; then
  echo "usage: $0 BUILD_DIR REPO_ROOT" >&2
  exit 2
fi
BUILD=$(cd "$1" && pwd)
REPO=$(cd "$2" && pwd)
T=$(mktemp -d "${TMPDIR:-/tmp}/train_stage1_cli.XXXXXX")
trap 'rm -rf "$T"' EXIT
fail() {
  echo "FAIL: $*" >&2
  exit 1
}
t0=$(date +%s)

# The tiny configs.
cat >"$T/preprocess.yaml" <<'EOF'
preset: released
image_size: 28
pointmap_size: 8
EOF
cat >"$T/generator.yaml" <<'EOF'
generator: {kind: ShortCut, time_scale: 1000.0, inference_steps: 4, rescale_t: 3.0, no_shortcut: true,
            cfg_strength: 7.0, cfg_interval: [0, 500], unconditional_handling: add_flag}
flow_model:
  in_channels: 4
  model_channels: 32
  cond_channels: 16
  out_channels: 4
  num_blocks: 1
  num_heads: 2
  mlp_ratio: 2
  is_shortcut_model: true
  force_zeros_cond: true
  latents:
    - {name: shape, in_channels: 4, pos_embedder: shape, resolution: 2, patch_size: 1}
    - {name: 6drotation_normalized, in_channels: 6, pos_embedder: learnt, token_len: 1}
    - {name: scale, in_channels: 3, pos_embedder: learnt, token_len: 1}
    - {name: translation, in_channels: 3, pos_embedder: learnt, token_len: 1}
    - {name: translation_scale, in_channels: 1, pos_embedder: learnt, token_len: 1}
  share_groups:
    6drotation_normalized: [6drotation_normalized, scale, translation, translation_scale]
EOF
cat >"$T/embedder.json" <<'EOF'
{"vit": {"img_size": 28, "patch_size": 14, "embed_dim": 16, "depth": 1, "num_heads": 2, "mlp_ratio": 2,
         "init_values": 1.0, "ffn_layer": "mlp", "block_chunks": 0, "num_register_tokens": 1},
 "dino_image_input_size": 28, "dino_mask_input_size": 28,
 "pointpatch": {"input_size": 8, "patch_size": 4, "embed_dim": 16, "remap_output": "linear", "block_heads": 2,
                "block_mlp_ratio": 2.0},
 "fuser": {"embedder_list": [["dino_image", [["image", "cropped"], ["rgb_image", "full"]]],
                             ["dino_mask", [["mask", "cropped"], ["rgb_image_mask", "full"]]],
                             ["pointpatch", [["pointmap", "cropped"], ["rgb_pointmap", "full"]]]],
           "use_pos_embedding": "learned", "projection_pre_norm": true, "projection_net_hidden_dim_multiplier": 1.0}}
EOF
cat >"$T/train.yaml" <<EOF
model: {generator: $T/generator.yaml, embedder: $T/embedder.json}
targets: {kind: random_linear, seed: 3}
objective: {p_unconditional: 0.3, shortcut_fraction: 0.25}
ema: {decay: 0.9}
optim: {lr: 0.003, warmup_steps: 2, schedule: cosine}
data: {cache: $T/s1.h5, global_batch: 4, micro_batch: 2}
train: {steps: 6, device: cpu, precision: fp32, seed: 5}
run: {out_dir: $T/a, checkpoint_every: 2, keep_last: 5, progress: false}
EOF

# 1. The cache, with 2 threads and with 1.
B="$BUILD/build_stage1_data --train 3 --val 1 --seed 40 --resolution 8 --preprocess $T/preprocess.yaml"
$B --out "$T/s1.h5" --threads 2 >"$T/build2.log" 2>&1 || { cat "$T/build2.log"; fail "build_stage1_data"; }
$B --out "$T/s1_one.h5" --threads 1 >"$T/build1.log" 2>&1 || { cat "$T/build1.log"; fail "build_stage1_data --threads 1"; }
grep -q "wrote .* samples of 4 scenes" "$T/build2.log" || fail "no summary line: $(cat "$T/build2.log")"
PY=${SIMU_PYTHON:-$REPO/.deps/venv/bin/python}
PY=$(command -v "$PY" || echo "$PY")
if "$PY" -c 'import h5py' 2>/dev/null; then
  "$PY" - "$T/s1.h5" "$T/s1_one.h5" <<'PYEOF' || fail "the 1- and 2-thread caches differ"
import sys, h5py, numpy as np
a, b = h5py.File(sys.argv[1], "r"), h5py.File(sys.argv[2], "r")
assert sorted(a.keys()) == sorted(b.keys())
for k in a.keys():
    x, y = a[k][:], b[k][:]
    assert x.shape == y.shape and (np.array_equal(x, y, equal_nan=True) if x.dtype.kind == "f" else np.array_equal(x, y)), k
s = a["split"][:]
assert (s == 0).sum() > 0 and (s == 1).sum() > 0 and (s == 2).sum() == 0, s
assert a["occupancy"].shape[1:] == (8, 8, 8) and a["image"].shape[1:] == (3, 28, 28)
PYEOF
else
  cmp -s "$T/s1.h5" "$T/s1_one.h5" || echo "note: no h5py; the caches' bytes differ (timestamps), not compared"
fi
echo "ok 1: build_stage1_data, 1 and 2 threads give the same samples ($(( $(date +%s) - t0 )) s)"

# 2. One run == two runs (stop at step 3, resume).
TR="$BUILD/train_stage1 --config $T/train.yaml"
$TR >"$T/a.log" 2>&1 || { cat "$T/a.log"; fail "train_stage1 (a)"; }
$TR --set run.out_dir="$T/b" --set run.stop_at_step=3 >"$T/b1.log" 2>&1 || { cat "$T/b1.log"; fail "train_stage1 (b) first run"; }
[[ ! -e "$T/b/model" ]] || fail "a run stopped at step 3 exported its model"
$TR --set run.out_dir="$T/b" --resume latest >"$T/b2.log" 2>&1 || { cat "$T/b2.log"; fail "train_stage1 (b) resumed"; }
cmp "$T/a/model/ss_generator.safetensors" "$T/b/model/ss_generator.safetensors" || fail "exported weights differ"
for f in model.safetensors optimizer.safetensors extra.safetensors; do
  cmp "$T/a/checkpoints/step_00000006/$f" "$T/b/checkpoints/step_00000006/$f" || fail "checkpoint $f differs"
done
echo "ok 2: 6 steps == 3 steps + --resume latest, bit for bit ($(( $(date +%s) - t0 )) s)"

# 3. An earlier run is not overwritten by accident.
if $TR >"$T/c.log" 2>&1; then fail "a fresh run overwrote run.out_dir"; fi
grep -q "already holds an earlier run" "$T/c.log" || fail "unexpected error: $(cat "$T/c.log")"
$TR --overwrite >"$T/d.log" 2>&1 || { cat "$T/d.log"; fail "--overwrite"; }
echo "ok 3: an earlier run is refused, --overwrite replaces it ($(( $(date +%s) - t0 )) s)"
echo "PASS: build_stage1_data + train_stage1 end-to-end ($(( $(date +%s) - t0 )) s)"
