#!/usr/bin/env bash
# One short GPU check (the device tool runs it from the repository root; carry .gpu, made by
# scripts/gpu_prepare.sh). In order of what matters most, each step time-boxed so that one slow step
# cannot eat the lease: `heartctl bench model` on the paper-size model (sparse GAT kernel, bf16) with
# torch.profiler's top kernels; the CUDA tests; PyG's GATConv kernel; then, where .gpu/store.zarr
# exists, `heartctl train --no-ray --device cuda` on it, eager, then the same through Ray Train on one
# GPU (`--gpus 1`: DDP over NCCL, from .gpu/ray) and with --compile (each epoch's line gives the loop's
# graphs/s); then fp32, a training batch of 512, and bench model through torch.compile (~9 min on an
# H200 in all).
# Output goes to stdout and, where $OUT is set, to $OUT/gpu_check.log.
# DEVICE=cpu runs the same steps on a CPU (to check the script itself).
set -uo pipefail
cd "$(dirname "$0")/.."
DEVICE=${DEVICE:-cuda}
PY=${PYTHON:-python3}
BATCHES=${BATCHES:-1,32,128,512}
TB=${TRAIN_BATCH:-128}
LOG=${OUT:+$OUT/gpu_check.log}
RUNS=$(mktemp -d)
export PYTHONPATH="$PWD:$PWD/.gpu/site${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1

step() {  # step SECONDS TITLE COMMAND...
  local limit=$1 title=$2; shift 2
  echo "== $title ($(date +%T))"
  timeout "$limit" "$@"; local rc=$?
  [ $rc -eq 124 ] && echo "!! $title: stopped after $limit s"
  return 0
}
HEARTCTL=($PY -c "from cli import main; main()")
BENCH=("${HEARTCTL[@]}" bench model --device "$DEVICE" --mesh .gpu/lv650.vtu)
TRAIN_ARGS=(--store .gpu/store.zarr --batch-size "$TB" --epochs "${EPOCHS:-8}" --patience 100)
TRAIN=("${HEARTCTL[@]}" train --no-ray --device "$DEVICE" "${TRAIN_ARGS[@]}")
RAY_SITE=${RAY_SITE:-/tmp/heartctl-ray}

RAY_GPUS=(--gpus 1 --bf16)  # one GPU worker, DDP over NCCL; with DEVICE=cpu one gloo worker
[ "$DEVICE" = cuda ] || RAY_GPUS=(--gpus 0 --workers 1)

ray_site() {  # unpack .gpu/ray's trimmed Ray and its wheels into $RAY_SITE once
  [ -f .gpu/ray/ray-trim.tar.xz ] && [ ! -d "$RAY_SITE/ray" ] || return 0
  mkdir -p "$RAY_SITE" && tar -xJf .gpu/ray/ray-trim.tar.xz -C "$RAY_SITE" &&
    $PY -m pip install -q --no-index --no-deps --target "$RAY_SITE" .gpu/ray/wheels/*.whl 2>&1 | tail -2
}

main() {
# meshio for the mesh; zarr and its codecs for the store (the GPU host has the rest)
$PY -m pip install -q --no-index --no-deps --target .gpu/site .gpu/wheels/meshio-*.whl 2>&1 | tail -2
$PY -m pip install -q --no-index --no-deps --target .gpu/site .gpu/train_wheels/*.whl 2>&1 | tail -2
[ "$DEVICE" = cuda ] && nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv,noheader
$PY -c "import torch, torch_geometric; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'pyg', torch_geometric.__version__)"
step 75 "sparse kernel, bf16, training batch $TB, profiled" \
  "${BENCH[@]}" --gat-kernel sparse --bf16 --batches "$BATCHES" --train-batch "$TB" --profile
step 75 "CUDA tests" env PYTEST_DISABLE_PLUGIN_AUTOLOAD=1 $PY -m pytest -q -p no:cacheprovider \
  tests/test_trainer_sparse_gat.py tests/test_trainer_batching.py
step 50 "pyg kernel, fp32" "${BENCH[@]}" --gat-kernel pyg --batches "1,${BATCHES##*,}" --train-batch "$TB"
if [ -d .gpu/store.zarr ]; then
  step 75 "heartctl train, bf16, eager" "${TRAIN[@]}" --bf16 --run-dir "$RUNS/eager"
  ray_site
  step 120 "heartctl train ${RAY_GPUS[*]} through Ray Train" env PYTHONPATH="$RAY_SITE:$PYTHONPATH" \
    "${HEARTCTL[@]}" train "${RAY_GPUS[@]}" "${TRAIN_ARGS[@]}" --run-dir "$RUNS/ray"
  step 180 "heartctl train, bf16, --compile" "${TRAIN[@]}" --bf16 --compile --run-dir "$RUNS/compiled"
fi
step 50 "sparse kernel, fp32" "${BENCH[@]}" --gat-kernel sparse --batches "$BATCHES" --train-batch "$TB"
step 50 "sparse kernel, bf16, training batch ${TRAIN_BATCH_BIG:-512}" \
  "${BENCH[@]}" --gat-kernel sparse --bf16 --batches "${BATCHES_BIG:-2048}" --train-batch "${TRAIN_BATCH_BIG:-512}"
step 180 "sparse kernel, bf16, torch.compile" \
  "${BENCH[@]}" --gat-kernel sparse --bf16 --compile --batches "$BATCHES" --train-batch "$TB"
echo "== done ($(date +%T))"
}
main 2>&1 | tee ${LOG:-/dev/null}
rm -rf "$RUNS"
