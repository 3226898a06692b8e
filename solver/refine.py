"""Uniform refinement of a tagged LV mesh: every tet split in 8 (Bey's red refinement), every
surface triangle in 4, the new nodes at edge midpoints. The original vertices keep their numbers
(the first n nodes of the refined mesh), and the refined mesh fills the same polyhedral domain, so
a solution on it is compared with one on the original mesh node for node."""
from __future__ import annotations

import numpy as np

from .mesh import TetMesh, make_mesh, orient_positive

TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def _edge_numbers(tets: np.ndarray, n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Distinct edges [k, 2] (sorted ends) and each tet's six edge numbers [m, 6] (TET_EDGES order)."""
    ends = np.sort(tets[:, TET_EDGES].reshape(-1, 2), axis=1).astype(np.int64)
    keys = ends[:, 0] * n_nodes + ends[:, 1]
    distinct, inverse = np.unique(keys, return_inverse=True)
    edges = np.stack(np.divmod(distinct, n_nodes), axis=1)
    return edges, inverse.reshape(-1, 6)


def _midpoint_of(edges: np.ndarray, n_nodes: int):
    """A lookup (a, b) → the node number of the midpoint of edge ab (any order), vectorised."""
    keys = edges[:, 0] * n_nodes + edges[:, 1]

    def lookup(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        lo, hi = np.minimum(a, b).astype(np.int64), np.maximum(a, b).astype(np.int64)
        pos = np.searchsorted(keys, lo * n_nodes + hi)
        if np.any(pos >= keys.size) or np.any(keys[np.minimum(pos, keys.size - 1)] != lo * n_nodes + hi):
            raise ValueError("a surface triangle's edge is not an edge of the mesh's tets")
        return n_nodes + pos

    return lookup


def _split_triangles(tris: np.ndarray, midpoint) -> np.ndarray:
    """Each triangle (a, b, c) into four with the same winding."""
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
    return np.concatenate([np.stack(t, axis=1) for t in
                           ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])


def refine_uniform(mesh: TetMesh, levels: int = 1) -> TetMesh:
    """The mesh refined `levels` times: each level splits every tet into 4 corner tets and the inner
    octahedron into 4 along its shortest diagonal (keeps the elements' shape quality bounded under
    repeated refinement). Nodes 0 … n−1 are the original vertices; surface tags are carried."""
    if levels < 0:
        raise ValueError(f"refinement levels must be ≥ 0, got {levels}")
    for _ in range(levels):
        mesh = _refine_once(mesh)
    return mesh


def _refine_once(mesh: TetMesh) -> TetMesh:
    n = mesh.n_nodes
    tets = mesh.tets
    edges, tet_edges = _edge_numbers(tets, n)
    nodes = np.concatenate([mesh.nodes, 0.5 * (mesh.nodes[edges[:, 0]] + mesh.nodes[edges[:, 1]])])
    v = [tets[:, i] for i in range(4)]
    m = {tuple(e): n + tet_edges[:, k] for k, e in enumerate(TET_EDGES.tolist())}
    m01, m02, m03, m12, m13, m23 = (m[(0, 1)], m[(0, 2)], m[(0, 3)], m[(1, 2)], m[(1, 3)], m[(2, 3)])
    corners = [(v[0], m01, m02, m03), (m01, v[1], m12, m13), (m02, m12, v[2], m23), (m03, m13, m23, v[3])]
    # the octahedron's three diagonals join opposite edge midpoints: (m01, m23), (m02, m13), (m03, m12)
    diagonals = np.stack([np.linalg.norm(nodes[a] - nodes[b], axis=1)
                          for a, b in ((m01, m23), (m02, m13), (m03, m12))], axis=1)
    choice = diagonals.argmin(axis=1)
    # around each diagonal (p, q), the other four midpoints form a cycle; the four tets are (p, q, cycle[i], cycle[i+1])
    around = {0: (m01, m23, (m02, m03, m13, m12)),
              1: (m02, m13, (m01, m03, m23, m12)),
              2: (m03, m12, (m01, m02, m23, m13))}
    inner = []
    for k in range(4):
        rows = []
        for c in range(3):
            p, q, cycle = around[c]
            rows.append(np.stack([p, q, cycle[k], cycle[(k + 1) % 4]], axis=1))
        inner.append(np.select([(choice == c)[:, None] for c in range(3)], rows))
    new_tets = np.concatenate([np.stack(t, axis=1) for t in corners] + inner)
    new_tets = orient_positive(nodes, new_tets)
    midpoint = _midpoint_of(edges, n)
    endo, epi, base = (_split_triangles(f, midpoint) for f in (mesh.endo, mesh.epi, mesh.base))
    info = dict(mesh.info, refinement_levels=int(mesh.info.get("refinement_levels", 0)) + 1)
    return make_mesh(nodes, new_tets, endo, epi, base, info=info)


def prolongate(values: np.ndarray, coarse: TetMesh, levels: int = 1) -> np.ndarray:
    """Nodal values [n, ...] on `coarse` linearly interpolated onto the nodes of
    refine_uniform(coarse, levels) (a trial state for a refined solve)."""
    mesh = coarse
    for level in range(levels):
        edges, _ = _edge_numbers(mesh.tets, mesh.n_nodes)
        values = np.concatenate([values, 0.5 * (values[edges[:, 0]] + values[edges[:, 1]])])
        if level < levels - 1:
            mesh = _refine_once(mesh)
    return values
