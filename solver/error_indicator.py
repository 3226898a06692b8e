"""A-posteriori error indicator per element: the distance of the displacement gradient from its
recovered (smoothed) field, Zienkiewicz–Zhu style, and bulk (Dörfler) marking.

For a solved state with displacement u_h (P1 or P2, on the reference configuration X), the element
gradients ∇u_h are evaluated at each element's own dof points and averaged over the elements sharing
each dof, weighted by volume; interpolated with the same shape functions this is a continuous field
G*. The indicator of tet K is

    η_K = ‖G* − ∇u_h‖_{L²(K)} = ( ∫_K |G* − ∇u_h|² dX )^{1/2}       (mm^{3/2}),

integrated with the 14-point rule (exact for the quartic integrand of P2). Where the exact gradient
is smooth, G* is closer to it than ∇u_h, so η_K measures the local discretisation error of the
gradient (the strain), the quantity that drives the error in the unloaded geometry. How well it ranks
the true error is measured by `heartctl bench adaptive` (docs/solver.md)."""
from __future__ import annotations

import numpy as np

from .elements import CellQuadrature, TET_EDGES, build_dofmap, cell_quadrature, simplex_shape, tet_geometry

INDICATOR_QUAD_DEGREE = 5


def _dof_barycentric(order: int) -> np.ndarray:
    """Barycentric coordinates [4, nbf] of a tet's dof points: the vertices, then (P2) the edge midpoints."""
    lam = np.eye(4)
    if order == 1:
        return lam
    mids = np.stack([0.5 * (lam[:, i] + lam[:, j]) for i, j in TET_EDGES], axis=1)
    return np.hstack([lam, mids])


def gradient_indicator(nodes: np.ndarray, tets: np.ndarray, u_dofs: np.ndarray) -> np.ndarray:
    """η_K [m] (module docstring) for the displacement u_dofs [ndofs, 3] (mm) on the reference
    configuration `nodes` [n, 3] (mm) with tets [m, 4]: P1 when ndofs = n, P2 when ndofs = n + edges
    (in `elements.build_dofmap`'s order)."""
    n = nodes.shape[0]
    order = 1 if u_dofs.shape[0] == n else 2
    dofmap = build_dofmap(nodes, tets, order)
    if u_dofs.shape != (dofmap.n_dofs, 3):
        raise ValueError(f"displacement must be [{dofmap.n_dofs}, 3] for this mesh, got {u_dofs.shape}")
    ue = u_dofs[dofmap.cell_dofs]  # [m, nbf, 3]
    vol, g = tet_geometry(nodes, tets)
    _, dl = simplex_shape(order, _dof_barycentric(order))
    at_dofs = np.einsum("ebi,bld,elj->edij", ue, dl, g)  # ∇u at each element's dof points [m, nbf, 3, 3]
    weight = np.abs(vol)[:, None] * np.ones(dofmap.cell_dofs.shape[1])
    total = np.bincount(dofmap.cell_dofs.ravel(), weights=weight.ravel(), minlength=dofmap.n_dofs)
    recovered = np.stack([np.bincount(dofmap.cell_dofs.ravel(), weights=(weight * at_dofs[..., i, j]).ravel(),
                                      minlength=dofmap.n_dofs) for i in range(3) for j in range(3)], axis=1)
    recovered = (recovered / total[:, None]).reshape(-1, 3, 3)
    q: CellQuadrature = cell_quadrature(nodes, tets, order, INDICATOR_QUAD_DEGREE)
    grad_h = np.einsum("ebi,eqbj->eqij", ue, q.grads)
    smooth = np.einsum("bq,ebij->eqij", q.values, recovered[dofmap.cell_dofs])
    return np.sqrt(np.einsum("eqij,eqij,eq->e", smooth - grad_h, smooth - grad_h, q.dV))


def bulk_marking(indicator: np.ndarray, fraction: float, eligible: np.ndarray | None = None) -> np.ndarray:
    """Dörfler marking: the fewest `eligible` elements (bool [m]; default all) whose Σ η² reaches
    `fraction` of the eligible total, largest η first. Returns bool [m]."""
    if not 0 < fraction <= 1:
        raise ValueError(f"bulk fraction must be in (0, 1], got {fraction}")
    eligible = np.ones(len(indicator), dtype=bool) if eligible is None else np.asarray(eligible, dtype=bool)
    idx = np.flatnonzero(eligible)
    marked = np.zeros(len(indicator), dtype=bool)
    if idx.size == 0:
        return marked
    eta2 = indicator[idx] ** 2
    order = np.argsort(-eta2)
    cumulative = np.cumsum(eta2[order])
    count = int(np.searchsorted(cumulative, fraction * cumulative[-1] * (1 - 1e-12))) + 1
    marked[idx[order[:count]]] = True
    return marked
