"""Write tests/data/shipped_reference_pairs.npz: three held-out ED meshes of the shipped network's shape
family with their `reference` unloaded geometry, which `make test` scores the shipped network on.

    .venv/bin/python scripts/bundle_reference_pairs.py RUN_DIR [CACHE_DIR]

The cases are `bench trade --seed 0 --shape-model 2 --first-shape 20`'s: shapes 20, 21 and 22 of seed 0 of
shape model version 2 at the run's mesh size, at the mid of its parameter box and its two hardest corners.
The reference solves are kept in CACHE_DIR
(default build/network/trade/solves, where `bench trade --out build/network/trade` keeps them too).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT = Path(__file__).resolve().parents[1] / "tests" / "data" / "shipped_reference_pairs.npz"


def main(run_dir: Path, cache_dir: Path) -> None:
    from bench.convergence import SolveCache
    from solver.meshing import mesh_lv
    from solver.shape_model import lv_shape
    from trainer.training.checkpoint import load_run
    from trainer.data.store_cases import fingerprint_value
    from bench.trade import TradeSpec, held_out_cases, reference_answer

    fingerprint = load_run(run_dir)["fingerprint"]
    base = fingerprint_value(fingerprint, "base") or "sliding"
    fibres = fingerprint_value(fingerprint, "fibres") or "laplace"
    spec = TradeSpec(runs=[run_dir], shapes=3, cases=3, user_nodes=0, first_shape=20, seed=0, shape_model=2)
    cases = held_out_cases(fingerprint, spec)
    chosen = [cases[0], cases[4], cases[8]]  # shape 20 mid, shape 21 first corner, shape 22 second corner
    cache = SolveCache(cache_dir)
    arrays = {}
    for i, case in enumerate(chosen):
        ed = mesh_lv(lv_shape(case.shape_id, case.seed, case.version), case.target_nodes)
        ref = reference_answer(case, ed, base, fibres, cache, print)
        if ref.failed:
            raise SystemExit(f"reference of shape {case.shape_id} {case.name} failed: {ref.failed}")
        p = case.params
        arrays.update({f"{i}_nodes": ed.nodes, f"{i}_tets": ed.tets.astype(np.int32),
                       f"{i}_endo": ed.endo.astype(np.int32), f"{i}_epi": ed.epi.astype(np.int32),
                       f"{i}_base": ed.base.astype(np.int32), f"{i}_reference": ref.unloaded,
                       f"{i}_params": np.array([p.pressure_mmhg, p.stiffness_pa, p.helix_endo_deg, p.helix_epi_deg]),
                       f"{i}_shape": np.array([case.shape_id, case.seed, case.version])})
        print(f"shape {case.shape_id} ({ed.n_nodes} nodes) {case.name}: reference in {ref.wall_s:.0f} s")
    np.savez_compressed(OUT, count=np.array(len(chosen)), **arrays)
    print(f"wrote {OUT} ({OUT.stat().st_size / 1024:.0f} kB)")


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]) if len(sys.argv) > 2 else Path("build/network/trade/solves"))
