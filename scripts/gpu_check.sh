#!/usr/bin/env bash
# One short GPU check (the device tool runs it from the repository root; carry .gpu, made by
# scripts/gpu_prepare.sh): the sparse GAT kernel's CUDA tests against PyG's GATConv, then
# `heartctl bench model` on the paper-size model for both GAT kernels, fp32 and bf16, then the
# sparse kernel in bf16 through torch.compile.
# DEVICE=cpu runs the same steps on a CPU (to check the script itself).
set -uo pipefail
cd "$(dirname "$0")/.."
DEVICE=${DEVICE:-cuda}
PY=${PYTHON:-python3}
export PYTHONPATH="$PWD:$PWD/.gpu/site${PYTHONPATH:+:$PYTHONPATH}"
$PY -m pip install -q --no-index --no-deps --target .gpu/site .gpu/wheels/*.whl 2>&1 | tail -2
[ "$DEVICE" = cuda ] && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
$PY -c "import torch, torch_geometric; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'pyg', torch_geometric.__version__)"
PYTEST_DISABLE_PLUGIN_AUTOLOAD=1 $PY -m pytest -q -p no:cacheprovider tests/test_trainer_sparse_gat.py tests/test_trainer_batching.py 2>&1 | tail -3
for kernel in sparse pyg; do
  for prec in "" "--bf16"; do
    echo "== bench model --gat-kernel $kernel $prec"
    $PY -c "from cli import main; main()" bench model --device "$DEVICE" --mesh .gpu/lv650.vtu \
        --gat-kernel "$kernel" $prec --batches "${BATCHES:-1,32,128,512}" ${TRAIN_BATCH:+--train-batch $TRAIN_BATCH} 2>&1 | tail -12
  done
done
echo "== bench model --gat-kernel sparse --bf16 --compile"
$PY -c "from cli import main; main()" bench model --device "$DEVICE" --mesh .gpu/lv650.vtu \
    --gat-kernel sparse --bf16 --compile --batches "${BATCHES:-1,32,128,512}" ${TRAIN_BATCH:+--train-batch $TRAIN_BATCH} 2>&1 | tail -12
