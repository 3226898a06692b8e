#!/usr/bin/env bash
# `make run`: the whole pipeline as far as it exists, small and local (2 cores, a few minutes).
set -euo pipefail
cd "$(dirname "$0")/.."
HEARTCTL=.venv/bin/heartctl
OUT=out
mkdir -p "$OUT"

echo "== 1. Solver verification: Land et al. 2015 problem 1 (beam), fast preset"
$HEARTCTL verify --problem land1 --fidelity fast

echo
echo "== 2. An ED mesh from the shape model (shape 0), with surface tags and fibres"
$HEARTCTL mesh --shape 0 --nodes 800 -o "$OUT/shape0_ed.vtu"

echo
echo "== 3. Distributed data generation, local two-core mode (Ray), into a Zarr store"
rm -rf "$OUT/local.zarr"
$HEARTCTL generate --local --store "$OUT/local.zarr"
$HEARTCTL status --store "$OUT/local.zarr"

echo
echo "== 4. Train HeartUnloadNet on that store (Ray Train, two CPU workers, a few epochs)"
echo "   (--config recommended: the paper's network without the cycle term, with weight averaging, no dropout and"
echo "   the mesh's linear FE response as node input, the lowest measured error; --config paper is the paper's model)"
rm -rf "$OUT/run_local"
$HEARTCTL train --local --store "$OUT/local.zarr" --run-dir "$OUT/run_local" --config recommended

echo
echo "== 5. Reference pairs of the same ED meshes (the accurate preset on each mesh refined once: near the"
echo "   converged solution), at one parameter set, to score the network and its fast labels against"
rm -rf "$OUT/local_reference.zarr"
$HEARTCTL generate --local --fidelity reference --pressures 8 --stiffness 100 --store "$OUT/local_reference.zarr"
$HEARTCTL evaluate --run "$OUT/run_local" --store "$OUT/local.zarr" --reference "$OUT/local_reference.zarr"

echo
echo "== 6. Unload one ED mesh: by the network just trained (--check: inflated again, how far it lands from the"
echo "   ED mesh), by the network shipped with heartctl (docs/model-card.md), then by inverse FE"
echo "   (8 mmHg, C = 150 Pa, helix +60/−60°)"
$HEARTCTL unload "$OUT/shape0_ed.vtu" --pressure 8 --stiffness 150 --endo 60 --epi -60 \
    --method gnn --run "$OUT/run_local" --check -o "$OUT/shape0_unloaded_gnn.vtu"
$HEARTCTL unload "$OUT/shape0_ed.vtu" --pressure 8 --stiffness 150 --endo 60 --epi -60 \
    --method gnn -o "$OUT/shape0_unloaded_shipped.vtu"
$HEARTCTL unload "$OUT/shape0_ed.vtu" --pressure 8 --stiffness 150 --endo 60 --epi -60 \
    --method fe --fidelity fast -o "$OUT/shape0_unloaded.vtu"

echo
echo "== 7. Check: inflate the FE-unloaded mesh again; it must land on the ED mesh"
$HEARTCTL solve "$OUT/shape0_unloaded.vtu" --pressure 8 --stiffness 150 --endo 60 --epi -60 \
    --fidelity fast -o "$OUT/shape0_reloaded.vtu"
.venv/bin/python - "$OUT/shape0_ed.vtu" "$OUT/shape0_reloaded.vtu" <<'PY'
import sys, meshio, numpy as np
ed, back = (meshio.read(p).points for p in sys.argv[1:3])
err = np.linalg.norm(ed - back, axis=1)
print(f"round trip ED → unloaded → ED: max nodal error {err.max():.2e} mm, mean {err.mean():.2e} mm")
PY
echo
echo "Outputs in $OUT/ (open the .vtu files in ParaView)."
