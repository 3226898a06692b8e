"""A-posteriori check of an unloaded geometry without ground truth: inflate it again to the ED pressure
and measure how far it lands from the ED mesh it was meant to unload.

For the exact unloaded geometry X* of the model, x(X*) = x_ED. For an approximation X (the network's,
or a few inverse updates'), r = x(X) − x_ED is the residual of the backward-displacement fixed point
X ← X − r, whose first-order solution is X − X* ≈ (∂x/∂X)⁻¹ r; since x = X + u(X) and the wall
stretches by tens of percent, |r| tracks |X − X*| up to a factor near one. `bench trade` measures how
well it ranks true errors (Spearman) and the factor between them."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .fidelity import Fidelity
from .forward import SolveError
from .lv import forward_solve
from .mesh import MeshError, TetMesh, check_geometry
from .parameters import CaseParameters


@dataclass(frozen=True)
class ReinflationCheck:
    """Nodal distance (mm) between the re-inflated unloaded mesh and the ED mesh; `failed` names why
    there is none (the unloaded mesh folds an element, or its forward solve did not converge)."""

    mean_mm: float
    max_mm: float
    p95_mm: float
    wall_s: float
    failed: str = ""

    @property
    def ok(self) -> bool:
        return not self.failed


def reinflation_error(ed_mesh: TetMesh, unloaded_nodes: np.ndarray, params: CaseParameters,
                      fidelity: Fidelity | str = "accurate", base: str = "sliding",
                      fibres: str = "laplace") -> ReinflationCheck:
    """One forward solve of `unloaded_nodes` (on ed_mesh's connectivity, mm) at `params`; the distance
    of the result from ed_mesh's nodes. Never raises for a bad answer: the reason goes in `failed`."""
    t0 = time.perf_counter()
    unloaded = np.asarray(unloaded_nodes, dtype=float)
    nan = float("nan")
    if unloaded.shape != ed_mesh.nodes.shape or not np.all(np.isfinite(unloaded)):
        return ReinflationCheck(nan, nan, nan, 0.0, "the unloaded nodes are not finite or do not match the ED mesh")
    try:
        check_geometry(unloaded, ed_mesh.tets)
        loaded = forward_solve(ed_mesh.with_nodes(unloaded), params, fidelity, base, fibres=fibres).loaded_nodes
    except (MeshError, SolveError) as exc:
        reason = str(exc).splitlines()[0][:160]
        return ReinflationCheck(nan, nan, nan, time.perf_counter() - t0, reason)
    d = np.linalg.norm(loaded - ed_mesh.nodes, axis=1)
    return ReinflationCheck(float(d.mean()), float(d.max()), float(np.percentile(d, 95)), time.perf_counter() - t0)
