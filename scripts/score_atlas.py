"""Score a network on ED meshes you bring, against the `reference` preset on the same mesh, node for node.

    .venv/bin/python scripts/score_atlas.py MESH_DIR [--run RUN] [--units cm] [--cache DIR] [--threads N]

MESH_DIR holds ED meshes named ED{shape}_{P}_{C}_{endo}_{epi}.vtu (the seed paper's dataset: P mmHg, C Pa,
helix endo / |epi| degrees, epi negative). Without --run the network shipped with heartctl is scored. The
reference solves are kept in --cache (default build/network/atlas), so a rerun only predicts. Prints each
mesh's mean / max node error and the mean over the apical, mid and basal thirds (by height), then the means.
"""
from __future__ import annotations

import argparse
import hashlib
import re
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NAME = re.compile(r"ED(\d+)_([\d.]+)_([\d.]+)_([\d.]+)_([\d.]+)\.vtu$")


def region_means(ed_nodes: np.ndarray, error: np.ndarray) -> dict:
    """Mean error over thirds of the height, base plane (max z) to apex (min z)."""
    z = ed_nodes[:, 2]
    level = (z.max() - z) / (z.max() - z.min())  # 0 base … 1 apex
    return {name: float(error[(level >= lo) & (level <= hi)].mean())
            for name, lo, hi in (("base", 0.0, 1 / 3), ("mid", 1 / 3, 2 / 3), ("apex", 2 / 3, 1.0))}


def reference_unloaded(mesh, params, cache: Path, key: str) -> tuple[np.ndarray, float]:
    from solver.lv import inverse_solve

    path = cache / f"{key}.npz"
    if path.is_file():
        data = np.load(path)
        return data["unloaded"], float(data["wall_s"])
    t0 = time.perf_counter()
    unloaded = inverse_solve(mesh, params, "reference").unloaded_nodes
    wall = time.perf_counter() - t0
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, unloaded=unloaded, wall_s=wall)
    return unloaded, wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", type=Path)
    ap.add_argument("--run", type=Path, default=None)
    ap.add_argument("--units", default="cm")
    ap.add_argument("--cache", type=Path, default=Path("build/network/atlas"))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reference-only", action="store_true", help="only solve (and keep) the references")
    args = ap.parse_args()
    import os

    for var in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):  # before the solver loads
        os.environ[var] = str(args.threads)
    from solver.parameters import CaseParameters
    from storage.meshfiles import read_mesh
    from trainer.evaluation.predict import unload_with_network
    from trainer.shipped import shipped_run

    run = None if args.reference_only else args.run or shipped_run()
    rows = []
    for path in sorted(args.meshes.glob("ED*.vtu")):
        match = NAME.search(path.name)
        if not match:
            continue
        _, p, c, endo, epi = (float(g) for g in match.groups())
        params = CaseParameters(p, c, endo, -epi)
        mesh = read_mesh(path, args.units, check_units=False)
        key = hashlib.sha256(path.read_bytes() + f"{args.units}".encode()).hexdigest()[:16]
        reference, ref_s = reference_unloaded(mesh, params, args.cache, key)
        if run is None:
            print(f"{path.name}: {mesh.n_nodes} nodes, reference solve {ref_s:.0f} s", flush=True)
            continue
        net = unload_with_network(mesh, params, [run])
        error = np.linalg.norm(net.unloaded_nodes - reference, axis=1)
        regions = region_means(mesh.nodes, error)
        rows.append((error.mean(), error.max(), regions))
        print(f"{path.name}: {mesh.n_nodes} nodes, network {net.network_ms:.1f} ms: mean {error.mean():.3f} / max "
              f"{error.max():.3f} mm; base {regions['base']:.3f}, mid {regions['mid']:.3f}, apex {regions['apex']:.3f} "
              f"(reference solve {ref_s:.0f} s)" + "".join(f"\n  warning: {w}" for w in net.warnings), flush=True)
    if rows:
        print(f"mean over {len(rows)} meshes: {np.mean([r[0] for r in rows]):.3f} mm mean node error, "
              f"{np.mean([r[1] for r in rows]):.3f} mm mean of the largest; apex {np.mean([r[2]['apex'] for r in rows]):.3f}")


if __name__ == "__main__":
    main()
