"""Uniform refinement of a tagged LV mesh: every tet split in 8 (Bey's red refinement), every
surface triangle in 4, the new nodes at edge midpoints. The original vertices keep their numbers
(the first n nodes of the refined mesh), and the refined mesh fills the same polyhedral domain, so
a solution on it is compared with one on the original mesh node for node.

The new nodes are the P2 dof map's edge nodes (`elements.build_dofmap`), in its order: a P2 field
on the mesh (vertices, then edges) is therefore a nodal field on the refined mesh as it stands."""
from __future__ import annotations

import numpy as np

from .elements import TET_EDGES, build_dofmap, facet_dofs
from .mesh import TetMesh, make_mesh, orient_positive


def refine_uniform(mesh: TetMesh, levels: int = 1) -> TetMesh:
    """The mesh refined `levels` times: each level splits every tet into 4 corner tets and the inner
    octahedron into 4 along its shortest diagonal (keeps the elements' shape quality bounded under
    repeated refinement). Nodes 0 … n−1 are the original vertices; surface tags are carried."""
    if levels < 0:
        raise ValueError(f"refinement levels must be ≥ 0, got {levels}")
    for _ in range(levels):
        mesh = _refine_once(mesh)
    return mesh


def _split_triangles(dofmap, tris: np.ndarray) -> np.ndarray:
    """Each triangle (a, b, c) into four with the same winding (facet dofs: a, b, c, ab, bc, ac)."""
    a, b, c, ab, bc, ca = facet_dofs(dofmap, tris).T
    return np.concatenate([np.stack(t, axis=1) for t in
                           ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])


def red_children(nodes: np.ndarray, v: list, m: dict) -> list[np.ndarray]:
    """The 8 children [k, 4] each of tets with vertices v[0..3] (arrays [k]) and edge midpoints
    m[(i, j)] (arrays [k], for the six local edges i < j): 4 corner tets and the inner octahedron in 4
    along its shortest diagonal (keeps the elements' shape quality bounded under repeated refinement)."""
    m01, m02, m03, m12, m13, m23 = (m[(0, 1)], m[(0, 2)], m[(0, 3)], m[(1, 2)], m[(1, 3)], m[(2, 3)])
    corners = [(v[0], m01, m02, m03), (m01, v[1], m12, m13), (m02, m12, v[2], m23), (m03, m13, m23, v[3])]
    # the octahedron's three diagonals join opposite edge midpoints: (m01, m23), (m02, m13), (m03, m12)
    diagonals = np.stack([np.linalg.norm(nodes[a] - nodes[b], axis=1)
                          for a, b in ((m01, m23), (m02, m13), (m03, m12))], axis=1)
    choice = diagonals.argmin(axis=1)
    # around each diagonal (p, q), the other four midpoints form a cycle; the four tets are (p, q, cycle[i], cycle[i+1])
    around = ((m01, m23, (m02, m03, m13, m12)),
              (m02, m13, (m01, m03, m23, m12)),
              (m03, m12, (m01, m02, m23, m13)))
    inner = []
    for k in range(4):
        rows = [np.stack([p, q, cycle[k], cycle[(k + 1) % 4]], axis=1) for p, q, cycle in around]
        inner.append(np.select([(choice == c)[:, None] for c in range(3)], rows))
    return [np.stack(t, axis=1) for t in corners] + inner


def _refine_once(mesh: TetMesh) -> TetMesh:
    dofmap = build_dofmap(mesh.nodes, mesh.tets, 2)
    nodes = dofmap.points  # vertices, then edge midpoints
    v = [mesh.tets[:, i] for i in range(4)]
    m = {tuple(e): dofmap.cell_dofs[:, 4 + k] for k, e in enumerate(TET_EDGES.tolist())}
    new_tets = orient_positive(nodes, np.concatenate(red_children(nodes, v, m)))
    endo, epi, base = (_split_triangles(dofmap, f) for f in (mesh.endo, mesh.epi, mesh.base))
    info = dict(mesh.info, refinement_levels=int(mesh.info.get("refinement_levels", 0)) + 1)
    return make_mesh(nodes, new_tets, endo, epi, base, info=info)


def prolongate(values: np.ndarray, coarse: TetMesh, levels: int = 1) -> np.ndarray:
    """Nodal values [n, ...] on `coarse` linearly interpolated onto the nodes of
    refine_uniform(coarse, levels) (a trial state for a refined solve)."""
    mesh = coarse
    for level in range(levels):
        ends = build_dofmap(mesh.nodes, mesh.tets, 2).edge_vertices
        values = np.concatenate([values, 0.5 * (values[ends[:, 0]] + values[ends[:, 1]])])
        if level < levels - 1:
            mesh = _refine_once(mesh)
    return values


def refined_unloaded(ed_mesh: TetMesh, unloaded: np.ndarray, displacement: np.ndarray | None = None,
                     levels: int = 1) -> np.ndarray:
    """An unloaded geometry on refine_uniform(ed_mesh, levels) from one on `ed_mesh`. With the P2
    displacement of its solve (`displacement_at_dofs`), each new midpoint takes X = x_ED − u there:
    one fixed-point step from where the P2 solution puts it, where interpolating X ignores the
    solution's curvature along the edge (an inverse on the refined mesh starts closer to its answer,
    docs/solver.md). Otherwise, and for further levels, X is interpolated linearly."""
    unloaded = np.asarray(unloaded, dtype=float)
    if unloaded.shape != ed_mesh.nodes.shape or not np.all(np.isfinite(unloaded)):
        raise ValueError("initial unloaded guess must be finite and have one point per ED node")
    if displacement is None or levels < 1:
        return prolongate(unloaded, ed_mesh, levels)
    fine = refine_uniform(ed_mesh, 1)
    if displacement.shape != fine.nodes.shape:  # a P1 solve: no midpoint values
        return prolongate(unloaded, ed_mesh, levels)
    X = fine.nodes - displacement
    X[: ed_mesh.n_nodes] = unloaded
    return prolongate(X, fine, levels - 1)
