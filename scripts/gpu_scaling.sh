#!/usr/bin/env bash
# Multi-GPU FM-DPO scaling run on the device (issue: 4-/8-GPU scaling): configs/lora64.yaml with the
# real-size model and random weights on a synthetic 256-pair cache, 50 steps on each world size, then
# pairs/s, step time, peak memory per GPU (nvidia-smi, sampled every 0.5 s) and whether the exported
# adapters agree across world sizes. Needs build-gpu/ (scripts/gpu_build_test.sh) and .carry/.
#   OUT=dir bash scripts/gpu_scaling.sh "1 2 4"
set -u
WORLDS="${1:-1 2 4}"
OUT="${OUT:-$PWD/bench-out}"; mkdir -p "$OUT"
export LD_LIBRARY_PATH=$PWD/.carry/prefix/usr/lib/x86_64-linux-gnu:$PWD/.carry/prefix/usr/lib/coacd
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
[ -x build-gpu/train_fmdpo ] || { bash scripts/gpu_build_test.sh -R NONE > $OUT/build.txt 2>&1; grep "configure+build" $OUT/build.txt; }
B=build-gpu
sed -e 's#config: checkpoints/ss_generator.yaml#config: configs/stage1_real.yaml#' -e 's#weights: checkpoints/ss_generator.safetensors#weights: ""#' configs/lora64.yaml > /tmp/lora64_random.yaml
[ -f /tmp/pairs.h5 ] || $B/pairs make --out /tmp/pairs.h5 --n 256 --tokens 4096 --channels 8 --cond-len 2800 --cond-len-min 2800 --cond-channels 1024 --dtype f16 > $OUT/pairs.txt 2>&1; tail -1 $OUT/pairs.txt
for N in $WORLDS; do
  nvidia-smi --query-gpu=index,memory.used --format=csv,noheader,nounits -lms 500 > $OUT/mem$N.txt & SMI=$!
  t0=$(date +%s.%N)
  $B/train_fmdpo --config /tmp/lora64_random.yaml \
    --set data.cache=/tmp/pairs.h5 --set train.steps=50 --set run.out_dir=/tmp/run$N --set run.checkpoint_every=0 \
    --set data.micro_batch=2 --nproc-per-node $N > $OUT/train$N.txt 2>&1; rc=$?
  t1=$(date +%s.%N); kill $SMI
  cp /tmp/run$N/metrics.jsonl $OUT/metrics$N.jsonl 2>/dev/null
  python3 - $N $t0 $t1 $rc $OUT <<'PY'
import json,sys
n,t0,t1,rc,out=int(sys.argv[1]),float(sys.argv[2]),float(sys.argv[3]),sys.argv[4],sys.argv[5]
rows=[json.loads(l) for l in open(f"{out}/metrics{n}.jsonl")] if rc=="0" else []
pps=[r["pairs_per_s"] for r in rows[10:]] or [0]
mem={}
for l in open(f"{out}/mem{n}.txt"):
    p=l.split(",");
    if len(p)==2: mem[p[0].strip()]=max(mem.get(p[0].strip(),0),int(p[1]))
print(f"world {n}: rc {rc} wall {t1-t0:.1f}s steps {len(rows)} median pairs/s (steps 11-50) {sorted(pps)[len(pps)//2]:.2f} step ms {16/sorted(pps)[len(pps)//2]*1e3:.0f} loss last {rows[-1]['loss'] if rows else 'n/a'} peak MiB/GPU {max(mem.values()) if mem else 0}")
def med(k):
    v=sorted(r.get(k,0) for r in rows[10:]) or [0]
    return v[len(v)//2]*1e3
if rows: print(f"world {n}: rank-0 median ms per step: step {med('time/step_s'):.0f} = data wait {med('time/data_wait_s'):.0f} + compute {med('time/compute_s'):.0f} + all-reduce {med('time/allreduce_s'):.0f} + optimizer {med('time/optimizer_s'):.0f} (+ metrics)")
PY
  [ "$rc" = 0 ] || tail -5 $OUT/train$N.txt
done
python3 - <<'PY'
import json,struct,numpy as np
def load(p):
    b=open(p,'rb').read(); n=struct.unpack('<Q',b[:8])[0]; h=json.loads(b[8:8+n]); d=b[8+n:]; out={}
    for k,v in h.items():
        if k=='__metadata__': continue
        s,e=v['data_offsets']; a=np.frombuffer(d[s:e],dtype={'F32':np.float32,'F16':np.float16,'BF16':np.uint16}[v['dtype']])
        out[k]=a.astype(np.float64) if v['dtype']!='BF16' else None
    return out
import os
runs={n:load(f"/tmp/run{n}/adapter/adapter_model.safetensors") for n in (1,2,4,8) if os.path.exists(f"/tmp/run{n}/adapter/adapter_model.safetensors")}
for n in [m for m in (2,4,8) if m in runs and 1 in runs]:
    num=max(np.abs(runs[n][k]-runs[1][k]).max() for k in runs[1]); den=max(np.abs(runs[1][k]).max() for k in runs[1])
    dnum=max(np.abs(runs[1][k]-0).max() for k in runs[1] if 'lora_B' in k)
    print(f"adapters world {n} vs 1: max|diff| {num:.3e}, max|A,B| {den:.3e}, rel {num/den:.2e}; max|lora_B| (moved from 0) {dnum:.3e}; lora_B rel diff {max(np.abs(runs[n][k]-runs[1][k]).max() for k in runs[1] if 'lora_B' in k)/dnum:.2e}")
PY
