#!/usr/bin/env bash
# Fill .gpu/ (git-ignored, ~50 MB: the device tool carries at most 64 MiB) with what
# scripts/gpu_check.sh needs on a GPU host that has Python 3.12, torch, torch-geometric, typer and
# pytest but nothing else of ours: wheels of meshio (meshes) and zarr with its codecs (the store), one
# paper-size LV mesh (VTU, mm), a store of 432 fast FE pairs (12 shapes of ~650 nodes; a few minutes
# here) for `heartctl train` there, and Ray for `heartctl train --gpus 1`: this venv's Ray version as
# the cp312 wheel's files without its Java jars and RLlib (~31 MB as .tar.xz) and the wheels of Ray
# Train's imports that the host lacks.
# Run here (internet, .venv): bash scripts/gpu_prepare.sh ; then on the device: bash scripts/gpu_check.sh
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p .gpu/wheels .gpu/train_wheels
.venv/bin/pip download -q --only-binary=:all: --python-version 3.12 --platform manylinux2014_x86_64 --no-deps \
    -d .gpu/wheels meshio
.venv/bin/pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --no-deps \
    -d .gpu/train_wheels "zarr==$(.venv/bin/python -c 'import zarr; print(zarr.__version__)')" \
    "numcodecs==$(.venv/bin/python -c 'import numcodecs; print(numcodecs.__version__)')" donfig google-crc32c
.venv/bin/heartctl mesh --shape 0 --nodes 680 -o .gpu/lv650.vtu  # 643 nodes: the goal's ~650-node mesh
[ -d .gpu/store.zarr ] || .venv/bin/heartctl generate --store .gpu/store.zarr --shapes "${SHAPES:-12}" \
    --pressures 8,12,16 --stiffness 100,200,300 --endo 50,60 --epi=-50,-60 --fidelity fast --nodes 680
if [ ! -f .gpu/ray/ray-trim.tar.xz ]; then
  mkdir -p .gpu/ray/wheels
  tmp=$(mktemp -d)
  .venv/bin/pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
      --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --no-deps \
      -d "$tmp" "ray==$(.venv/bin/python -c 'import ray; print(ray.__version__)')"
  unzip -q "$tmp"/ray-*.whl -d "$tmp/files"
  rm -rf "$tmp/files/ray/jars" "$tmp/files/ray/rllib"
  tar -cJf .gpu/ray/ray-trim.tar.xz -C "$tmp/files" .
  rm -rf "$tmp"
  .venv/bin/pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
      --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --no-deps \
      -d .gpu/ray/wheels pydantic pydantic-core typing-inspection annotated-types jsonschema \
      jsonschema-specifications referencing rpds-py tensorboardX
fi
du -sh .gpu
