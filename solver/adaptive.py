"""Adaptive unloading: `accurate` on the ED mesh, then on meshes refined locally where the error
indicator is largest, until the estimated nodal error of the unloaded geometry meets a tolerance.

1. Solve the inverse with `accurate` on the ED mesh M₀ (unloaded X₀); indicator η on M₀
   (`error_indicator.gradient_indicator`, on the unloaded configuration).
2. Mark the unrefined tets of M₀ that carry a bulk `fraction` of Σ η² (Dörfler; on a refined mesh a
   tet of M₀ carries the Σ η² of its children) and split them, with the closure
   (`local_refine.refine_marked`, always from M₀: a tet is split at most once, so the finest mesh is
   `reference`'s). Solve again, started from the last answer (each new midpoint at x_ED − u of the
   last P2 solution there), and compute η there.
3. Estimate the error of step k's answer at the ED mesh's vertices by its distance from the last
   answer, the difference from a locally refined solution:

       e_k(v) = |X_k(v) − X_{k−1}(v)|                                    (mm).

   Local refinement moves the error about more than it scales it (the error in X is spread over the
   wall: each tet's discretisation error acts on every node through the inverse), so the change is of
   the size of the new answer's error rather than a fraction of it: measured against `reference`, e_k's
   p95 is 0.5–1.7× the true p95 error of X_k (docs/solver.md, "Adaptive refinement").
4. Stop when the 95th percentile of e_k is ≤ the tolerance (met), or when no tet is left to split or
   after `max_steps` refinements (not met; the answer is the last one, with its estimate).

The answer is at the ED mesh's vertices (the first nodes of every refined mesh)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .elements import build_dofmap
from .error_indicator import bulk_marking, gradient_indicator
from .fidelity import get_fidelity
from .forward import SolveStats
from .lv import InverseResult, displacement_at_dofs, inverse_solve
from .local_refine import LocalRefinement, refine_marked
from .mesh import TetMesh
from .parameters import CaseParameters

ADAPTIVE_PRESET = "accurate"
BULK_FRACTION = 0.4
MAX_STEPS = 3
# each solve's mismatch tolerance: this share of the asked tolerance, between the preset's (1e-4 mm) and
# LOOSEST_SOLVE_TOL_MM. The estimate compares answers to a few hundredths of a mm, so tightening each
# solve to 1e-4 mm costs its last updates for nothing: at 0.05 mm, 1e-3 mm took 18.6 s against 20.6 s for
# the same answer to 1e-3 mm (the −2 SD shape, mid case, 318 nodes refined 3 times; 2-core box, one thread)
SOLVE_TOL_SHARE = 0.02
LOOSEST_SOLVE_TOL_MM = 1e-3


@dataclass(frozen=True)
class AdaptiveStep:
    """One solve of the adaptive loop: its mesh (nodes, tets, tets of the ED mesh split so far), the
    indicator's norm ‖η‖ (mm^{3/2}), the estimated nodal error (p95 and mean, mm; None on the ED mesh,
    which has nothing to compare with) and the solve's wall time (s)."""

    nodes: int
    tets: int
    split_tets: int
    indicator: float
    estimate_p95_mm: float | None
    estimate_mean_mm: float | None
    wall_s: float


@dataclass
class AdaptiveResult:
    """The unloaded geometry at the ED mesh's vertices (mm), the estimated error there (mm, [n]),
    whether the tolerance was met, the steps, the last solve at the ED vertices (its mismatch; its
    updates and stats are every solve's together, wall time included) and the indicator of the ED mesh's tets from the first solve (for ranking studies)."""

    unloaded_nodes: np.ndarray
    estimated_error_mm: np.ndarray
    met: bool
    steps: list[AdaptiveStep]
    inverse: InverseResult = field(repr=False)
    first_indicator: np.ndarray = field(repr=False, default=None)

    @property
    def mismatch_mm(self) -> float:
        return self.inverse.mismatch_mm

    @property
    def updates(self) -> int:
        return self.inverse.updates

    @property
    def stats(self) -> SolveStats:
        return self.inverse.stats


def adaptive_unload(ed_mesh: TetMesh, params: CaseParameters, tolerance_mm: float, base: str = "sliding",
                    fibres: str = "laplace", tol_mm: float | None = None, fraction: float = BULK_FRACTION,
                    max_steps: int = MAX_STEPS, report=None) -> AdaptiveResult:
    """The unloaded geometry of `ed_mesh` (module docstring) with its estimated p95 nodal error ≤
    `tolerance_mm` (mm) where local refinement can reach it. `tol_mm`: each inverse's mismatch
    tolerance (default SOLVE_TOL_SHARE × `tolerance_mm`, within [the preset's, LOOSEST_SOLVE_TOL_MM]).
    Raises SolveError when a solve fails."""
    if not (np.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise ValueError(f"`tolerance_mm` must be a finite number > 0, got {tolerance_mm}")
    if max_steps < 1:
        raise ValueError(f"`max_steps` must be ≥ 1, got {max_steps}")
    fid = get_fidelity(ADAPTIVE_PRESET)
    if tol_mm is None:
        tol_mm = float(np.clip(SOLVE_TOL_SHARE * tolerance_mm, fid.inverse_tol_mm, LOOSEST_SOLVE_TOL_MM))
    t0 = time.perf_counter()
    n = ed_mesh.n_nodes
    inv = inverse_solve(ed_mesh, params, fid, base, tol_mm=tol_mm, fibres=fibres)
    total, updates = SolveStats(), inv.updates  # every solve's work together
    total.add(inv.stats)
    refinement = refine_marked(ed_mesh, np.zeros(len(ed_mesh.tets), dtype=bool))
    eta = gradient_indicator(inv.unloaded_nodes, ed_mesh.tets, displacement_at_dofs(inv))
    first_eta = eta
    steps = [AdaptiveStep(n, len(ed_mesh.tets), 0, float(np.linalg.norm(eta)), None, None, time.perf_counter() - t0)]
    X_fine, u_fine = inv.unloaded_nodes, displacement_at_dofs(inv)
    estimate = np.full(n, np.inf)
    met = False
    for _ in range(max_steps):
        per_tet = np.sqrt(np.bincount(refinement.parent, weights=eta ** 2, minlength=len(ed_mesh.tets)))
        eligible = ~refinement.refined
        if not eligible.any():
            break
        marked = bulk_marking(per_tet, fraction, eligible) | refinement.refined
        following = refine_marked(ed_mesh, marked)
        start = _carried_unloaded(ed_mesh, refinement, X_fine, u_fine, following)
        t_step = time.perf_counter()
        inv = inverse_solve(following.mesh, params, fid, base, initial_unloaded=start, tol_mm=tol_mm, fibres=fibres)
        total.add(inv.stats)
        updates += inv.updates
        new_eta = gradient_indicator(inv.unloaded_nodes, following.mesh.tets, displacement_at_dofs(inv))
        estimate = np.linalg.norm(inv.unloaded_nodes[:n] - X_fine[:n], axis=1)
        refinement, eta, X_fine, u_fine = following, new_eta, inv.unloaded_nodes, displacement_at_dofs(inv)
        steps.append(AdaptiveStep(following.mesh.n_nodes, len(following.mesh.tets), int(following.refined.sum()),
                                  float(np.linalg.norm(eta)), float(np.percentile(estimate, 95)),
                                  float(estimate.mean()), time.perf_counter() - t_step))
        if report:
            report(f"adaptive step {len(steps) - 1}: {following.mesh.n_nodes} nodes, estimated error p95 "
                   f"{steps[-1].estimate_p95_mm:.3f} mm (tolerance {tolerance_mm:g} mm)")
        if steps[-1].estimate_p95_mm <= tolerance_mm:
            met = True
            break
    total.wall_s = time.perf_counter() - t0
    at_ed = InverseResult(X_fine[:n].copy(), inv.mismatch_mm, updates, total, inv.mismatch_history)
    return AdaptiveResult(X_fine[:n].copy(), estimate, met, steps, at_ed, first_eta)


def _carried_unloaded(ed_mesh: TetMesh, last: LocalRefinement, X_last: np.ndarray, u_last: np.ndarray,
                      following: LocalRefinement) -> np.ndarray:
    """A starting unloaded geometry on `following`'s mesh from the last solve (on `last`'s mesh: X_last
    at its nodes, its P2 displacement u_last at its dofs): the nodes both meshes have keep X_last; a new
    midpoint of an ED edge (a, b), an edge of the last mesh, takes x_ED − u_last at that edge's P2 dof."""
    last_ids, ids = last.fine_ids, following.fine_ids
    X = following.mesh.nodes.copy()
    order = np.argsort(last_ids)
    at = np.minimum(np.searchsorted(last_ids[order], ids), len(order) - 1)
    known = last_ids[order[at]] == ids
    X[known] = X_last[order[at[known]]]
    if (~known).any():
        n = ed_mesh.n_nodes
        ends = build_dofmap(ed_mesh.nodes, ed_mesh.tets, 2).edge_vertices[ids[~known] - n]  # ED vertices a, b
        last_map = build_dofmap(last.mesh.nodes, last.mesh.tets, 2)
        m = last.mesh.n_nodes
        keys = last_map.edge_vertices[:, 0].astype(np.int64) * m + last_map.edge_vertices[:, 1]
        wanted = np.sort(ends, axis=1).astype(np.int64)
        pos = np.searchsorted(keys, wanted[:, 0] * m + wanted[:, 1])
        if np.any(pos >= len(keys)) or np.any(keys[np.minimum(pos, len(keys) - 1)] != wanted[:, 0] * m + wanted[:, 1]):
            raise ValueError("a new midpoint's ED edge is not an edge of the last mesh")
        X[~known] = following.mesh.nodes[~known] - u_last[m + pos]
    return X
