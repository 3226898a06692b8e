"""Lagrange tetrahedra (P1, P2) on straight-sided meshes: dof numbering, shape functions and
their reference-configuration gradients at quadrature points, and the matching boundary triangles."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skfem.mesh import MeshTet, MeshTri  # noqa: F401  (reference cells for quadrature)
from skfem.quadrature import get_quadrature
from skfem.refdom import RefTet, RefTri

# local vertex pairs of the six tet edges, in the P2 dof order used below
TET_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
TRI_EDGES = np.array([[0, 1], [1, 2], [0, 2]])


@dataclass(frozen=True)
class DofMap:
    """Scalar Lagrange dofs of order 1 or 2 on a tet mesh.

    `points` [ndofs, 3] are dof locations in mm (vertices first, then edge midpoints);
    `cell_dofs` [ntets, 4|10]; `facet_dofs` [nfacets, 3|6] for the given boundary facets.
    """

    order: int
    points: np.ndarray
    cell_dofs: np.ndarray
    n_vertices: int
    edge_vertices: np.ndarray | None = None  # [n_edges, 2] vertex pair of each edge dof (P2)

    @property
    def n_dofs(self) -> int:
        return self.points.shape[0]


def build_dofmap(nodes: np.ndarray, tets: np.ndarray, order: int) -> DofMap:
    if order == 1:
        return DofMap(1, nodes.copy(), tets.copy(), nodes.shape[0])
    if order != 2:
        raise ValueError(f"element order must be 1 or 2, got {order}")
    n = nodes.shape[0]
    pairs = np.sort(tets[:, TET_EDGES], axis=2).reshape(-1, 2)
    keys = pairs[:, 0].astype(np.int64) * n + pairs[:, 1]
    uniq, inverse = np.unique(keys, return_inverse=True)
    edge_nodes = np.stack([uniq // n, uniq % n], axis=1)
    mid = 0.5 * (nodes[edge_nodes[:, 0]] + nodes[edge_nodes[:, 1]])
    cell_dofs = np.hstack([tets, n + inverse.reshape(-1, 6)])
    return DofMap(2, np.vstack([nodes, mid]), cell_dofs, n, edge_nodes)


def facet_dofs(dofmap: DofMap, facets: np.ndarray) -> np.ndarray:
    """Dofs of boundary triangles [nf, 3] (vertex indices): vertices, then edges 01, 12, 02."""
    if dofmap.order == 1:
        return facets.copy()
    n = dofmap.n_vertices
    tets = dofmap.cell_dofs[:, :4]
    pairs = np.sort(tets[:, TET_EDGES], axis=2).reshape(-1, 2)
    keys = pairs[:, 0].astype(np.int64) * n + pairs[:, 1]
    edge_dof = dofmap.cell_dofs[:, 4:].reshape(-1)
    order = np.argsort(keys)
    fpairs = np.sort(facets[:, TRI_EDGES], axis=2).reshape(-1, 2)
    fkeys = fpairs[:, 0].astype(np.int64) * n + fpairs[:, 1]
    pos = np.searchsorted(keys[order], fkeys)
    return np.hstack([facets, edge_dof[order[pos]].reshape(-1, 3)])


def simplex_shape(order: int, lam: np.ndarray):
    """Lagrange basis of order 1 or 2 on a triangle (lam [3, nq]) or tet (lam [4, nq]) at points given
    by barycentric coordinates: values [nbf, nq] and derivatives by the barycentric coordinates
    [nbf, nv, nq]. Vertices first, then the edges in TRI_EDGES / TET_EDGES order."""
    nv, nq = lam.shape
    if order == 1:
        return lam.copy(), np.broadcast_to(np.eye(nv)[:, :, None], (nv, nv, nq)).copy()
    if order != 2:
        raise ValueError(f"element order must be 1 or 2, got {order}")
    edges = TET_EDGES if nv == 4 else TRI_EDGES
    vals = np.zeros((nv + len(edges), nq))
    dl = np.zeros((nv + len(edges), nv, nq))
    for a in range(nv):
        vals[a] = lam[a] * (2 * lam[a] - 1)
        dl[a, a] = 4 * lam[a] - 1
    for k, (i, j) in enumerate(edges):
        vals[nv + k] = 4 * lam[i] * lam[j]
        dl[nv + k, i] = 4 * lam[j]
        dl[nv + k, j] = 4 * lam[i]
    return vals, dl


@dataclass(frozen=True)
class CellQuadrature:
    """Shape data on the reference (unloaded) configuration at quadrature points.

    values [nbf, nq]; grads [ntets, nq, nbf, 3] (1/mm); dV [ntets, nq] (mm^3, weight × volume);
    lam [4, nq] barycentric coordinates of the points; p1_grads [ntets, 4, 3] vertex basis gradients.
    """

    values: np.ndarray
    grads: np.ndarray
    dV: np.ndarray
    lam: np.ndarray
    p1_grads: np.ndarray
    volumes: np.ndarray


def tet_geometry(nodes: np.ndarray, tets: np.ndarray):
    """Signed volumes [ntets] (mm^3) and gradients of barycentric coordinates [ntets, 4, 3].

    With edges e_k = x_k − x_0, the rows of [e_1 e_2 e_3]⁻¹ (the gradients of λ_1..3) are
    e_2 × e_3, e_3 × e_1, e_1 × e_2 over det = e_1 · (e_2 × e_3): 0.6 ms against 1.8 ms with
    np.linalg.det + inv on 2,786 tets. A flat tet gives non-finite gradients instead of raising
    (np.linalg.inv raised only for some float-coplanar tets anyway): meshes are checked for
    zero-volume tets where they enter (`mesh.check_geometry`: files, the network's guesses, each
    inverse update's trial reference)."""
    x = nodes[tets]
    e1, e2, e3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    g = np.empty((tets.shape[0], 4, 3))
    g[:, 1], g[:, 2], g[:, 3] = np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)
    det = np.einsum("ei,ei->e", e1, g[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        g[:, 1:] /= det[:, None, None]
        g[:, 0] = -g[:, 1:].sum(axis=1)
    return det / 6.0, g


def quadrature_barycentric(quad_degree: int) -> np.ndarray:
    """Barycentric coordinates [4, nq] of the tet rule of the given exact degree."""
    X, _ = get_quadrature(RefTet, quad_degree)
    return np.vstack([1 - X.sum(axis=0), X])


def cell_quadrature(nodes: np.ndarray, tets: np.ndarray, order: int, quad_degree: int) -> CellQuadrature:
    X, W = get_quadrature(RefTet, quad_degree)
    lam = np.vstack([1 - X.sum(axis=0), X])
    vals, dl = simplex_shape(order, lam)
    vol, g = tet_geometry(nodes, tets)
    grads = _basis_gradients(dl, g)
    dV = 6.0 * vol[:, None] * W[None, :]
    return CellQuadrature(vals, grads, dV, lam, g, vol)


def _basis_gradients(dl: np.ndarray, g: np.ndarray) -> np.ndarray:
    """∇φ_a at the points [e, q, a, I] = Σ_l ∂φ_a/∂λ_l (q) ∇λ_l (e), from dl [a, l, q] and g [e, l, I]: one
    matmul [e, I, l] @ [l, (q a)] (the three-operand einsum's loop took 3.6× as long at degree 2 and 1.4× at
    degree 5, on 1,000 tets)."""
    na, nl, nq = dl.shape
    by_point = np.ascontiguousarray(dl.transpose(1, 2, 0)).reshape(nl, nq * na)
    grads = (np.swapaxes(g, 1, 2) @ by_point).reshape(len(g), 3, nq, na)
    return np.ascontiguousarray(grads.transpose(0, 2, 3, 1))


@dataclass(frozen=True)
class FacetQuadrature:
    """Triangle basis values [nbf, nq], parametric derivatives [nbf, 2, nq] and weights [nq]."""

    values: np.ndarray
    dxi: np.ndarray
    weights: np.ndarray


def facet_quadrature(order: int, quad_degree: int) -> FacetQuadrature:
    X, W = get_quadrature(RefTri, quad_degree)
    lam = np.vstack([1 - X.sum(axis=0), X])
    vals, dl = simplex_shape(order, lam)
    dxi = np.stack([dl[:, 1] - dl[:, 0], dl[:, 2] - dl[:, 0]], axis=1)
    return FacetQuadrature(vals, dxi, W)
