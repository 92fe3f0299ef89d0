# Sourced by the FM-DPO experiment scripts (fmdpo_gt_pairs.sh, fmdpo_beta_val.sh, fmdpo_v3.sh): the one
# evaluation they share, so that every adapter is judged by the same command. Needs BUILD.
#   ev OUT_DIR ADAPTER WORLD COUNT [extra eval_lift args...]
# runs eval_lift on WORLD (val | test | heldout), COUNT objects, eval seed 0, clean point maps, the
# amodal crop (the resampler's input), the translation-scale alignment, base and base + ADAPTER on the
# same objects and noise (--compare-adapter: paired deltas with 95% bootstrap intervals), one sample per
# object (--samples 1 --select first: as the documented tables were made, before eval_lift's best of 4), one thread,
# into OUT_DIR (its log: OUT_DIR.log). Exported, for xargs -P.
ev() {
  local out="$1" adapter="$2" world="$3" count="$4"
  shift 4
  OMP_NUM_THREADS=1 "$BUILD/eval_lift" --world "$world" --count "$count" --seed 0 --depth clean --amodal-crop \
    --align simuscene --device cpu --no-pictures --overwrite --samples 1 --select first --compare-adapter "$adapter" \
    --out "$out" "$@" >"$out.log" 2>&1
}
export -f ev
# The 40-70% rows: test or val scenes with one target in that visibility range.
OCC="--visible 40-70 --set scene.targets=1 --set scene.visible_min=0.4 --set scene.visible_max=0.7"
