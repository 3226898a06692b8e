"""Rule-based myofibre field: transmural coordinate φ from a Laplace solve (0 endo, 1 epi) and an
orthonormal (f, s, n) frame per quadrature point with a helix angle linear in φ.

Sign convention: t = ∇φ/|∇φ| points endo → epi, e_l is the long axis (+z, apex → base) projected on
the wall, e_c = e_l × t is circumferential (counter-clockwise seen from the base, looking down −z).
f = cos θ e_c + sin θ e_l is e_c rotated by θ about t, so θ > 0 tilts fibres toward the base as they
run counter-clockwise; the paper's endo +60…+70° and epi −60…−70° form the usual opposed helices.
s = t (sheet-normal, transmural), n = f × s."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from .elements import tet_geometry
from .mesh import TetMesh


def transmural_coordinate(mesh: TetMesh) -> np.ndarray:
    """φ at the mesh nodes: −Δφ = 0 in the wall, φ = 0 on the endocardium, φ = 1 on the epicardium."""
    vol, g = tet_geometry(mesh.nodes, mesh.tets)
    ke = vol[:, None, None] * np.einsum("eaI,ebI->eab", g, g)
    rows = np.repeat(mesh.tets, 4, axis=1).ravel()
    cols = np.tile(mesh.tets, (1, 4)).ravel()
    K = sp.csr_matrix((ke.ravel(), (rows, cols)), shape=(mesh.n_nodes,) * 2)
    phi = np.full(mesh.n_nodes, np.nan)
    phi[mesh.endo_nodes()] = 0.0
    phi[mesh.epi_nodes()] = 1.0
    fixed = ~np.isnan(phi)
    free = ~fixed
    rhs = -K[free][:, fixed] @ phi[fixed]
    phi[free] = spsolve(K[free][:, free].tocsc(), rhs)
    return np.clip(phi, 0.0, 1.0)


def wall_directions(mesh: TetMesh, phi: np.ndarray):
    """Per-tet transmural t, longitudinal e_l and circumferential e_c unit vectors, each [m, 3]."""
    _, g = tet_geometry(mesh.nodes, mesh.tets)
    grad = np.einsum("ea,eaI->eI", phi[mesh.tets], g)
    t = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-300)
    ez = np.array([0.0, 0.0, 1.0])
    el = ez - np.outer(t @ ez, np.ones(3)) * t
    norm = np.linalg.norm(el, axis=1)
    degenerate = norm < 1e-6  # t along the long axis (at the apex): fall back to x
    if degenerate.any():
        ex = np.array([1.0, 0.0, 0.0])
        el[degenerate] = ex - np.outer(t[degenerate] @ ex, np.ones(3)) * t[degenerate]
        norm = np.linalg.norm(el, axis=1)
    el /= norm[:, None]
    ec = np.cross(el, t)
    return t, el, ec


def fibre_frames(mesh: TetMesh, helix_endo_deg: float, helix_epi_deg: float, lam: np.ndarray,
                 phi: np.ndarray | None = None) -> np.ndarray:
    """Frames [m, nq, 3, 3] whose columns are (f, s, n), at quadrature points with barycentric
    coordinates lam [4, nq]. Angles in degrees (CLI convention), converted to radians here."""
    if phi is None:
        phi = transmural_coordinate(mesh)
    t, el, ec = wall_directions(mesh, phi)
    phi_q = np.einsum("ea,aq->eq", phi[mesh.tets], lam)
    theta = np.deg2rad(helix_endo_deg + phi_q * (helix_epi_deg - helix_endo_deg))
    c, s = np.cos(theta)[..., None], np.sin(theta)[..., None]
    f = c * ec[:, None, :] + s * el[:, None, :]
    sheet = np.broadcast_to(t[:, None, :], f.shape)
    n = np.cross(f, sheet)
    return np.stack([f, sheet, n], axis=-1)


def uniform_frames(n_cells: int, n_quad: int, fibre=(1.0, 0.0, 0.0), sheet=(0.0, 1.0, 0.0)) -> np.ndarray:
    """A constant (f, s, n) frame everywhere (benchmarks with straight fibres)."""
    f = np.asarray(fibre, float) / np.linalg.norm(fibre)
    s = np.asarray(sheet, float) - np.dot(sheet, f) * f
    s /= np.linalg.norm(s)
    frame = np.stack([f, s, np.cross(f, s)], axis=1)
    return np.broadcast_to(frame, (n_cells, n_quad, 3, 3)).copy()


def helix_angle_at_nodes(mesh: TetMesh, helix_endo_deg: float, helix_epi_deg: float, phi=None) -> np.ndarray:
    """Helix angle (degrees) at each node, for visualisation."""
    if phi is None:
        phi = transmural_coordinate(mesh)
    return helix_endo_deg + phi * (helix_epi_deg - helix_endo_deg)
