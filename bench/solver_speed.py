"""`heartctl bench solver`: forward and pair wall time per preset, split into assembly, linear
solve and other, at a mid case and at the extreme corner of the paper's box."""
from __future__ import annotations

import time

from solver.linear import SparseSolver
from solver.lv import forward_solve, make_pair
from solver.meshing import mesh_lv
from solver.parameters import CaseParameters
from solver.shape_model import lv_shape

CASES = {"mid (8 mmHg, 150 Pa)": CaseParameters(8.0, 150.0, 60.0, -60.0),
         "extreme (14 mmHg, 50 Pa)": CaseParameters(14.0, 50.0, 60.0, -60.0)}


def run_solver_benchmark(presets: list[str], nodes: int = 1000, shape: int = 0) -> list[dict]:
    mesh = mesh_lv(lv_shape(shape), nodes)
    warm = SparseSolver()  # load MKL once so its start-up is not billed to the first case
    forward_solve(mesh, CaseParameters(1.0, 150.0, 60.0, -60.0), "fast", linsolve=warm)
    rows = []
    for preset in presets:
        for label, params in CASES.items():
            t0 = time.perf_counter()
            fwd = forward_solve(mesh, params, preset)
            t_fwd = time.perf_counter() - t0
            t0 = time.perf_counter()
            pair = make_pair(mesh, params, preset)
            t_pair = time.perf_counter() - t0
            s = pair.stats
            from solver.lv import lv_problem

            dofs = lv_problem(mesh, params, preset).free.size
            rows.append({
                "fidelity": preset, "case": label, "nodes": mesh.n_nodes, "dofs": int(dofs),
                "forward_s": t_fwd, "forward_assembly_s": fwd.stats.assembly_s, "forward_linear_s": fwd.stats.linear_s,
                "forward_other_s": t_fwd - fwd.stats.assembly_s - fwd.stats.linear_s,
                "forward_newton": fwd.stats.newton_iterations,
                "pair_s": t_pair, "pair_assembly_s": s["assembly_s"], "pair_linear_s": s["linear_s"],
                "pair_other_s": t_pair - s["assembly_s"] - s["linear_s"],
                "pair_newton": s["inverse_newton_iterations"] + s["forward_newton_iterations"],
                "inverse_updates": s["inverse_updates"], "roundtrip_mm": s["roundtrip_error_mm"],
            })
    return rows
