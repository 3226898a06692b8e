#!/usr/bin/env bash
# Rebuild the network shipped with heartctl from nothing: labels, pretraining, fine-tuning, scoring,
# packaging. Every step resumes: rerun the script after an interruption and it goes on where it stopped.
#
#   scripts/build_network.sh                 # all steps, in build/network/
#   WORK=/scratch/net CPUS=8 scripts/build_network.sh
#   STEPS="fast reference" scripts/build_network.sh   # only the label stores
#
# Cost on the 2-core box: docs/model-card.md ("Training data and what it cost").
set -euo pipefail
cd "$(dirname "$0")/.."
HEARTCTL=${HEARTCTL:-.venv/bin/heartctl}
WORK=${WORK:-build/network}
CPUS=${CPUS:-2}
STEPS=${STEPS:-"fast reference pretrain finetune score package"}
SHIP=${SHIP:-finetuned}   # the run scored and packaged (pretrained: the fast-label network alone)
mkdir -p "$WORK"

# The training box: the paper's (P 4–14 mmHg, C 50–300 Pa, helix 60–70 / −60…−70°), ~350-node meshes of the
# shape model (version 2). Pretraining: 60 shapes of seed 1, `fast` labels, helix at the box's four corners.
# Fine-tuning: REF_SHAPES shapes of seed 0, `reference` labels (27 s a pair on one core), the same pressures and
# stiffnesses at the helix box's centre: the labels' budget goes to more shapes. Held out: seed 0 from shape 20 on.
REF_SHAPES=${REF_SHAPES:-12}
GRID=(--pressures 4,9,14 --stiffness 50,120,300 --endo 60,70 --epi=-60,-70 --nodes 350 --num-cpus "$CPUS")
REF_GRID=(--pressures 4,9,14 --stiffness 50,120,300 --endo 65 --epi=-65 --nodes 350 --num-cpus "$CPUS")

want() { [[ " $STEPS " == *" $1 "* ]]; }

if want fast; then
    echo "== fast labels for pretraining: 60 shapes (seed 1) × 3 P × 3 C × 2 × 2 helix"
    $HEARTCTL generate --shapes 60 --seed 1 "${GRID[@]}" --fidelity fast --store "$WORK/fast.zarr"
fi
if want reference; then
    echo "== reference labels for fine-tuning: $REF_SHAPES shapes (seed 0) × 3 P × 3 C, helix 65 / −65°"
    $HEARTCTL generate --shapes "$REF_SHAPES" --seed 0 "${REF_GRID[@]}" --fidelity reference --store "$WORK/reference.zarr"
fi
if want pretrain; then
    echo "== pretraining on the fast labels"
    $HEARTCTL train --no-ray --device cpu --config recommended --store "$WORK/fast.zarr" \
        --run-dir "$WORK/pretrained" --epochs 20
fi
if want finetune; then
    echo "== fine-tuning on the reference labels"
    $HEARTCTL train --no-ray --device cpu --config recommended --store "$WORK/reference.zarr" \
        --run-dir "$WORK/finetuned" --epochs 100 --lr 3e-4 --init-from "$WORK/pretrained"
fi
if want score; then
    echo "== scoring against the reference preset: its test split, held-out shapes 20–22 (seed 0), the atlas LV"
    if [ "$SHIP" = finetuned ]; then  # its test split: shapes of the reference store it never trained on
        $HEARTCTL evaluate --run "$WORK/$SHIP" --store "$WORK/reference.zarr" --reference "$WORK/reference.zarr"
    fi
    $HEARTCTL bench trade --run "$WORK/$SHIP" --seed 0 --first-shape 20 --shapes 3 --cases 3 --user-nodes 750 \
        --threads "$CPUS" --out "$WORK/trade"
    .venv/bin/python scripts/bundle_reference_pairs.py "$WORK/$SHIP" "$WORK/trade/solves"
    if [ -d "${ATLAS:-../shared/fixtures/l2u}" ]; then
        .venv/bin/python scripts/score_atlas.py "${ATLAS:-../shared/fixtures/l2u}" --run "$WORK/$SHIP" \
            --units cm --cache "$WORK/atlas"
    fi
fi
if want package; then
    echo "== packaging the network as heartctl's shipped one (trainer/shipped/)"
    .venv/bin/python scripts/ship_network.py "$WORK/$SHIP" "$WORK/trade"
fi
