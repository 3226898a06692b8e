#!/usr/bin/env bash
# Fill .gpu/ (git-ignored, a few MB) with what scripts/gpu_check.sh needs on a GPU host that has
# Python 3.12, torch and torch-geometric but nothing else of ours: pure-Python wheels (meshio for the
# mesh, typer/rich for the CLI, pytest for the CUDA tests) and one paper-size LV mesh (VTU, mm).
# Run here (internet, .venv): bash scripts/gpu_prepare.sh ; then on the device: bash scripts/gpu_check.sh
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p .gpu/wheels
.venv/bin/pip download -q --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64 --no-deps \
    -d .gpu/wheels meshio typer rich click shellingham markdown-it-py mdurl pygments pytest pluggy iniconfig packaging
.venv/bin/heartctl mesh --shape 0 --nodes 680 -o .gpu/lv650.vtu  # 643 nodes: the goal's ~650-node mesh
du -sh .gpu
