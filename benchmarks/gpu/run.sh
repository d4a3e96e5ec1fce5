#!/usr/bin/env bash
# GPU measurements for neural-brdf, in one device call (the wheels it needs in .whl/: see benchmarks/gpu/README.md):
#   bash benchmarks/gpu/run.sh
# a. render cost, neural_brdf vs roughconductor, BSDF-bound scene (benchmarks/bsdf_bound.py
#    --variant cuda_ad_rgb), at 256x256x64 spp (the CPU figures' size) and 1024x1024x128 spp
# b. training speed on CUDA (benchmarks/training_speed.py --device cuda), plus a CPU
#    baseline of gold on the same machine
# c. an images fit (inverse rendering) in cuda_ad_rgb on the example scenes
# d. issue 30: textured files against the compact file and Mitsuba's textured principled
#    (benchmarks/gpu/textured_cost.py; its --train makes the files on a CPU first)
# e. issue 29: benchmarks/images_any.py --variant cuda_ad_rgb on $IMAGES_ONLY
# f. issue 29: one image-fit step, the neural plugin's evaluators against roughconductor
#    (benchmarks/image_step.py --variant cuda_ad_rgb)
# PARTS="presets textured images_any image_step" picks (a)-(c), (d), (e), (f).
# Everything lands in $OUT: log.txt, env.txt, bsdf_bound_cuda.json,
# bsdf_bound_cuda_large.json, images_cuda_metrics.json, images_cuda_log.csv,
# training_speed_cuda.json, training_speed_cpu.json, textured_cost.json, images_any_cuda.json,
# image_step_cuda.json.
# A dry run on a CPU machine: VARIANT=llvm_ad_rgb SKIP_WHEELS=1 SMALL=1 OUT=/tmp/gpuout bash benchmarks/gpu/run.sh
set -uo pipefail
export PYTHONUNBUFFERED=1
cd "$(dirname "$0")/../.." || exit 1  # the repo root

VARIANT=${VARIANT:-cuda_ad_rgb}
case "$VARIANT" in cuda_*) DEVICE=cuda ;; *) DEVICE=cpu ;; esac
PARTS=${PARTS:-presets textured images_any image_step}  # which of (a)-(c), (d), (e), (f) to run
IMAGES_ONLY=${IMAGES_ONLY:-orange_plastic brushed_gold}  # (e)'s materials
SMALL=${SMALL:-0}          # 1: tiny sizes, for a dry run on a CPU
BUDGET=${BUDGET:-360}      # seconds: a step is skipped, or cut short, past this
OUT=${OUT:?set OUT}
mkdir -p "$OUT"
T0=$(date +%s)
WORK=$(mktemp -d /tmp/nbrdf-gpu.XXXX)

if [ "$SMALL" = 1 ]; then
  RES=64; SPP=8; REP=2; RES_L=128; SPP_L=16
  TS_STEPS=100; TS_REP=1; TS_MANY=2
  EX_RES=32; EX_SPP=32; EX_STEPS=10; EX_START_TRAIN=300; EX_EXTRA=(--set images.start_steps=20)
  MODEL_SET=(--set train.steps=300)
  IA_STEPS=10; IS_ROUNDS=1
else
  RES=256; SPP=64; REP=4; RES_L=1024; SPP_L=128
  TS_STEPS=500; TS_REP=2; TS_MANY=8
  EX_RES=96; EX_SPP=128; EX_STEPS=60; EX_START_TRAIN=300; EX_EXTRA=()
  MODEL_SET=()
  IA_STEPS=150; IS_ROUNDS=8
fi

want() { case " $PARTS " in *" $1 "*) return 0 ;; esac; return 1; }
left() { echo $((BUDGET - ($(date +%s) - T0))); }
# step NAME MAX_SECONDS CMD...: run CMD under timeout min(MAX, time left); never stops the script
step() {
  local name=$1 max=$2; shift 2
  local l; l=$(left)
  if [ "$l" -lt 20 ]; then echo "=== SKIP $name: budget spent ($BUDGET s)"; return 0; fi
  [ "$l" -lt "$max" ] && max=$l
  echo "=== $name (timeout ${max}s, t=$(( $(date +%s) - T0 ))s)"
  local s; s=$(date +%s)
  timeout --kill-after=10 "$max" "$@"
  local rc=$?
  echo "=== $name: rc=$rc in $(( $(date +%s) - s ))s"
  return 0
}

main() {
if [ "${SKIP_WHEELS:-0}" != 1 ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || { echo "wheel install failed"; return 1; }
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
fi
echo "variant $VARIANT, device $DEVICE, small $SMALL, budget $BUDGET s; wheels in $(( $(date +%s) - T0 ))s"

{
  nvidia-smi -L 2>&1 || echo "no nvidia-smi"
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv 2>&1 || true
  echo "optix/cuda libs:"; ldconfig -p 2>/dev/null | grep -iE 'libnvoptix|libcuda\.so' || echo "  (none in ldconfig)"
  ls /usr/local/nvidia/lib64 2>/dev/null | grep -iE 'optix|libcuda\.so' || true
  nproc; free -g | head -2
} 2>&1 | tee "$OUT/env.txt"

step env-check 90 python3 - "$VARIANT" <<'EOF' 2>&1 | tee -a "$OUT/env.txt"
import platform, sys, time
import torch
print("python", platform.python_version(), "torch", torch.__version__,
      "cuda", torch.cuda.is_available(),
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
import drjit as dr
import mitsuba as mi
import numpy, onnx, onnxruntime, pydantic
print("mitsuba", mi.__version__, "drjit", dr.__version__, "numpy", numpy.__version__,
      "onnx", onnx.__version__, "onnxruntime", onnxruntime.__version__, "pydantic", pydantic.__version__)
t = time.perf_counter()
mi.set_variant(sys.argv[1])
import neural_brdf.renderers.mitsuba  # noqa: F401  registers the plugins
sc = mi.load_dict(mi.cornell_box())
img = mi.render(sc, spp=16)
print("set_variant", mi.variant(), "cornell box mean", dr.mean(img, axis=None),
      f"{time.perf_counter() - t:.2f} s")
EOF

if want presets; then
# models for (a): the compact gold preset (32 relu + 32x32x4 grid) and the 3x64 silu MLP,
# trained on the CPU side by side (the render benchmark needs their files, not their speed)
M=$WORK/models
step train-models 150 bash -c "
  python3 -m neural_brdf train gold --out $M/compact_gold --set train.progress=false ${MODEL_SET[*]} > $M.gold.log 2>&1 &
  python3 -m neural_brdf train mlp/gold --out $M/gold_3x64_silu --set train.progress=false ${MODEL_SET[*]} > $M.mlp.log 2>&1 &
  wait; tail -n 2 $M.gold.log $M.mlp.log; ls $M/*/model.onnx"

# (a) the BSDF-bound render benchmark in $VARIANT
step bsdf-bound 150 python3 benchmarks/bsdf_bound.py --variant "$VARIANT" \
  --resolution $RES --spp $SPP --repeats $REP --out "$OUT/bsdf_bound_cuda.json" \
  compact_gold=$M/compact_gold/model.onnx gold_3x64_silu=$M/gold_3x64_silu/model.onnx
step bsdf-bound-large 120 python3 benchmarks/bsdf_bound.py --variant "$VARIANT" \
  --resolution $RES_L --spp $SPP_L --repeats $REP --out "$OUT/bsdf_bound_cuda_large.json" \
  compact_gold=$M/compact_gold/model.onnx gold_3x64_silu=$M/gold_3x64_silu/model.onnx

# (c) an images fit in $VARIANT: the example scenes written in that variant (the module's
# main() sets llvm_ad_rgb), then neural-brdf train on them
EX=$WORK/ex
step images-scenes 60 python3 - "$VARIANT" "$EX" $EX_RES $EX_SPP $EX_STEPS <<'EOF'
import sys, time
import mitsuba as mi
mi.set_variant(sys.argv[1])
from neural_brdf.inverse import scene
t = time.perf_counter()
files = scene.write(sys.argv[2], resolution=int(sys.argv[3]), spp=int(sys.argv[4]), steps=int(sys.argv[5]))
print(f"wrote {len(files)} files in {time.perf_counter() - t:.2f} s ({mi.variant()})")
EOF
step images-fit 200 python3 -m neural_brdf train "$EX/fit.yaml" --out "$EX/run" \
  --set train.device=$DEVICE --set target.variant=$VARIANT --set train.progress=false \
  --set train.steps=$EX_STEPS --set images.start_train_steps=$EX_START_TRAIN "${EX_EXTRA[@]}"
cp "$EX/run/metrics.json" "$OUT/images_cuda_metrics.json" 2>/dev/null || echo "no images metrics.json"
cp "$EX/run/log.csv" "$OUT/images_cuda_log.csv" 2>/dev/null || true
python3 - "$EX/run/metrics.json" <<'EOF' || true
import json, sys
m = json.load(open(sys.argv[1]))
print("images fit: seconds", m.get("seconds"), "passed", m.get("passed"))
tr = m.get("training") or {}
print("training:", json.dumps({k: v for k, v in tr.items() if len(json.dumps(v)) < 300}))
EOF

# (b) training speed on $DEVICE (presets, then the batched many-materials run, merged into
# one file), and the same machine's CPU on gold for a baseline
step training-speed 130 python3 benchmarks/training_speed.py gold mlp/gold --device $DEVICE \
  --steps $TS_STEPS --repeats $TS_REP --phases 1 --many 0 --out "$OUT/training_speed_cuda.json"
step training-speed-many 70 python3 benchmarks/training_speed.py quickstart --device $DEVICE \
  --steps $TS_STEPS --repeats 1 --phases 1 --many $TS_MANY --out "$OUT/training_speed_cuda.json"
step training-speed-cpu 60 python3 benchmarks/training_speed.py gold --device cpu \
  --steps $TS_STEPS --repeats $TS_REP --phases 1 --many 0 --out "$OUT/training_speed_cpu.json"

fi

# (d) issue 30: the textured files (trained on a CPU: --models, benchmarks/gpu/textured_cost.py
#     --train) against the compact file and Mitsuba's textured principled, in $VARIANT
if want textured; then
  step textured-cost 200 python3 benchmarks/gpu/textured_cost.py --variant "$VARIANT" \
    --models "${TEXTURED_MODELS:-runs/gpu_models}" --repeats $REP --out "$OUT/textured_cost.json" \
    --size ${RES}x${SPP} --size ${RES_L}x${SPP_L}
fi

# (f) issue 29: one image-fit step in $VARIANT, the plugin's evaluators against roughconductor
if want image_step; then
  step image-step 150 python3 benchmarks/image_step.py --variant "$VARIANT" \
    --rounds $IS_ROUNDS --out "$OUT/image_step_cuda.json"
fi

# (e) issue 29: images of materials the project never saw (benchmarks/images_any.py), the
#     fits and renders in $VARIANT, the materials in $IMAGES_ONLY
if want images_any; then
  only=(); for m in $IMAGES_ONLY; do only+=(--only "$m"); done
  step images-any 300 python3 benchmarks/images_any.py --variant "$VARIANT" "${only[@]}" \
    --steps $IA_STEPS --work "$WORK/images_any" --out "$OUT/images_any_cuda.json"
fi

echo "=== done in $(( $(date +%s) - T0 ))s; files:"; ls -la "$OUT"
rm -rf "$WORK"
}

main 2>&1 | tee "$OUT/log.txt"
