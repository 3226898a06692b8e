"""`heartctl bench solver`: forward and pair wall time per preset, split into assembly, linear
solve and other, at a mid case and at the extreme corner of the paper's box."""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

from solver.linear import SparseSolver
from solver.lv import forward_solve, lv_problem, make_pair
from solver.meshing import mesh_lv
from solver.parameters import CaseParameters
from solver.shape_model import lv_shape

CASES = {"mid (8 mmHg, 150 Pa)": CaseParameters(8.0, 150.0, 60.0, -60.0),
         "extreme (14 mmHg, 50 Pa)": CaseParameters(14.0, 50.0, 60.0, -60.0)}


@dataclass(frozen=True, kw_only=True)
class SolverTiming:
    """One preset at one case on one mesh: its size (nodes, free dofs); the forward solve's wall time (s)
    split into assembly, linear solves and other, and its Newton iterations; the same for the pair
    (inverse then forward), its inverse updates and its round-trip error (mm)."""

    fidelity: str
    case: str
    nodes: int
    dofs: int
    forward_s: float
    forward_assembly_s: float
    forward_linear_s: float
    forward_other_s: float
    forward_newton: int
    pair_s: float
    pair_assembly_s: float
    pair_linear_s: float
    pair_other_s: float
    pair_newton: int
    inverse_updates: int
    roundtrip_mm: float

    def as_dict(self) -> dict:
        return asdict(self)


def run_solver_benchmark(presets: list[str], nodes: int = 1000, shape: int = 0) -> list[SolverTiming]:
    """Each preset at each of CASES on shape `shape`'s mesh of ~`nodes` nodes, MKL loaded beforehand."""
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
            rows.append(SolverTiming(
                fidelity=preset, case=label, nodes=mesh.n_nodes, dofs=int(lv_problem(mesh, params, preset).free.size),
                forward_s=t_fwd, forward_assembly_s=fwd.stats.assembly_s, forward_linear_s=fwd.stats.linear_s,
                forward_other_s=t_fwd - fwd.stats.assembly_s - fwd.stats.linear_s,
                forward_newton=fwd.stats.newton_iterations,
                pair_s=t_pair, pair_assembly_s=s["assembly_s"], pair_linear_s=s["linear_s"],
                pair_other_s=t_pair - s["assembly_s"] - s["linear_s"],
                pair_newton=s["inverse_newton_iterations"] + s["forward_newton_iterations"],
                inverse_updates=s["inverse_updates"], roundtrip_mm=s["roundtrip_error_mm"]))
    return rows
