"""`heartctl bench solver`: forward and pair wall time per preset, split into assembly, linear
solve and other, at a mid case and at the extreme corner of the paper's box."""
from __future__ import annotations

import time

from .linear import SparseSolver
from .lv import forward_solve, make_pair
from .meshing import mesh_lv
from .parameters import CaseParameters
from .shape_model import lv_shape

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
            from .lv import lv_problem

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


def corner_cases() -> list[CaseParameters]:
    """The corners of the paper's box: P 4/14 mmHg × C 50/300 Pa × helix ±60/±70°."""
    return [CaseParameters(p, c, th, -th) for p in (4.0, 14.0) for c in (50.0, 300.0) for th in (60.0, 70.0)]


def run_corner_benchmark(preset: str, nodes: int = 800, base: str = "sliding", fibres: str = "laplace") -> list[dict]:
    """Inverse round trip solve(unload(x_ED)) — the forward from zero load with load stepping —
    at every corner of the box on the three most extreme shapes (±2 SD and a mixed corner), with the
    given base condition and fibre rule."""
    from .forward import SolveError
    from .shape_model import extreme_shapes

    rows = []
    for shape in extreme_shapes():
        mesh = mesh_lv(shape, nodes)
        for params in corner_cases():
            t0 = time.perf_counter()
            row = {"fidelity": preset, "base": base, "fibres": fibres, "shape": shape.shape_id, "nodes": mesh.n_nodes,
                   "pressure_mmhg": params.pressure_mmhg, "stiffness_pa": params.stiffness_pa,
                   "helix_deg": params.helix_endo_deg}
            try:
                pair = make_pair(mesh, params, preset, base, forward_from_scratch=True, fibres=fibres)
                row.update(ok=True, roundtrip_mm=pair.stats["roundtrip_error_mm"],
                           newton=pair.stats["inverse_newton_iterations"] + pair.stats["forward_newton_iterations"],
                           min_jacobian=pair.stats["min_jacobian"])
            except SolveError as exc:
                row.update(ok=False, reason=str(exc))
            row["wall_s"] = time.perf_counter() - t0
            rows.append(row)
    return rows
