#!/usr/bin/env bash
# One short GPU check (the device tool runs it from the repository root; carry .gpu, made by
# scripts/gpu_prepare.sh). In order of what matters most, each step time-boxed so that one slow step
# cannot eat the lease: `heartctl bench model` on the paper-size model (sparse GAT kernel, bf16 then
# fp32; training at batch 128 and 512), with torch.profiler's top kernels; the sparse GAT kernel's
# and the graph table's CUDA tests; PyG's GATConv kernel for comparison; torch.compile.
# Output goes to stdout and, where $OUT is set, to $OUT/gpu_check.log.
# DEVICE=cpu runs the same steps on a CPU (to check the script itself).
set -uo pipefail
cd "$(dirname "$0")/.."
DEVICE=${DEVICE:-cuda}
PY=${PYTHON:-python3}
BATCHES=${BATCHES:-1,32,128,512}
LOG=${OUT:+$OUT/gpu_check.log}
export PYTHONPATH="$PWD:$PWD/.gpu/site${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1

step() {  # step SECONDS TITLE COMMAND...
  local limit=$1 title=$2; shift 2
  echo "== $title ($(date +%T))"
  timeout "$limit" "$@"; local rc=$?
  [ $rc -eq 124 ] && echo "!! $title: stopped after $limit s"
  return 0
}
BENCH=($PY -c "from cli import main; main()" bench model --device "$DEVICE" --mesh .gpu/lv650.vtu)

main() {
$PY -m pip install -q --no-index --no-deps --target .gpu/site .gpu/wheels/*.whl 2>&1 | tail -2
[ "$DEVICE" = cuda ] && nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv,noheader
$PY -c "import torch, torch_geometric; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'pyg', torch_geometric.__version__)"
step 120 "sparse kernel, bf16, training batch ${TRAIN_BATCH:-128}, profiled" \
  "${BENCH[@]}" --gat-kernel sparse --bf16 --batches "$BATCHES" ${TRAIN_BATCH:+--train-batch $TRAIN_BATCH} --profile
step 90 "sparse kernel, fp32" "${BENCH[@]}" --gat-kernel sparse --batches "$BATCHES" ${TRAIN_BATCH:+--train-batch $TRAIN_BATCH}
step 90 "sparse kernel, bf16, training batch ${TRAIN_BATCH_BIG:-512}" \
  "${BENCH[@]}" --gat-kernel sparse --bf16 --batches "${BATCHES_BIG:-2048}" --train-batch "${TRAIN_BATCH_BIG:-512}"
step 150 "CUDA tests" env PYTEST_DISABLE_PLUGIN_AUTOLOAD=1 $PY -m pytest -q -p no:cacheprovider \
  tests/test_trainer_sparse_gat.py tests/test_trainer_batching.py
for prec in "" "--bf16"; do
  step 90 "pyg kernel ${prec:-fp32}" "${BENCH[@]}" --gat-kernel pyg $prec --batches "$BATCHES" ${TRAIN_BATCH:+--train-batch $TRAIN_BATCH}
done
step 180 "sparse kernel, bf16, torch.compile" \
  "${BENCH[@]}" --gat-kernel sparse --bf16 --compile --batches "$BATCHES" ${TRAIN_BATCH:+--train-batch $TRAIN_BATCH}
echo "== done ($(date +%T))"
}
main 2>&1 | tee ${LOG:-/dev/null}
