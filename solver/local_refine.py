"""Local refinement of a tagged LV mesh: the marked tets split in 8 as `refine.refine_uniform` splits
every tet, and a conforming closure around them, one level deep.

The edges to split are the marked tets' edges, closed until every tet has a pattern with a template:
a face with two split edges gets its third, and a tet whose split edges are not one edge, two
opposite edges or the three edges of one face gets all six. Templates:

* six edges: red (4 corner tets and the octahedron in 4 along its shortest diagonal, `refine`);
* three edges of one face: that face in 4, each joined to the opposite vertex (4 tets);
* two opposite edges: bisected at one, each half at the other (4 tets);
* one edge: bisected, both halves joined to the other two vertices (2 tets).

Every face is then split in 0, 2 or 4 triangles the same way from both sides, so the mesh conforms.
Nodes 0 … n−1 are the original vertices and the new ones are the split edges' midpoints, so the
refined mesh fills the same polyhedral domain and its nodes are a subset of the uniformly refined
mesh's (`LocalRefinement.fine_ids`): a solution on it is compared with both node for node."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .elements import TET_EDGES, build_dofmap, facet_dofs
from .mesh import TetMesh, make_mesh, orient_positive
from .refine import red_children

# the four faces of a tet as local edge numbers (TET_EDGES: 01, 12, 02, 03, 13, 23), and the vertex
# opposite each face; face k's vertices are FACE_VERTICES[k]
FACE_EDGES = np.array([[0, 1, 2], [0, 3, 4], [2, 3, 5], [1, 4, 5]])
FACE_VERTICES = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
FACE_OPPOSITE = np.array([3, 2, 1, 0])
OPPOSITE_EDGES = np.array([[0, 5], [1, 3], [2, 4]])  # 01–23, 12–03, 02–13


@dataclass(frozen=True)
class LocalRefinement:
    """A locally refined mesh and where it came from.

    mesh: the refined TetMesh (nodes: the coarse vertices, then the split edges' midpoints);
    parent [n_fine_tets]: the coarse tet each fine tet lies in;
    split_edges [n_split]: the coarse mesh's P2 edge numbers (`elements.build_dofmap`) of the new nodes, in order;
    refined [n_coarse_tets]: True where a coarse tet was split in 8 (marked, or closed to six edges)."""

    mesh: TetMesh
    parent: np.ndarray
    split_edges: np.ndarray
    refined: np.ndarray

    @property
    def fine_ids(self) -> np.ndarray:
        """Each node's number in `refine_uniform(coarse, 1)` (vertices keep theirs; a midpoint is n + its edge)."""
        n = self.mesh.n_nodes - len(self.split_edges)
        return np.concatenate([np.arange(n), n + self.split_edges])


def close_split_edges(tet_edges: np.ndarray, split: np.ndarray) -> np.ndarray:
    """The smallest superset of `split` (bool per edge) that the templates cover: no face with exactly
    two split edges, and each tet with 0, 1, 2 (opposite), 3 (one face's) or 6 split edges. tet_edges [m, 6] holds
    each tet's edge numbers in TET_EDGES order."""
    split = split.copy()
    while True:
        before = int(split.sum())
        s = split[tet_edges]
        for face in FACE_EDGES:
            two = s[:, face].sum(axis=1) == 2
            split[tet_edges[two][:, face]] = True
        s = split[tet_edges]
        count = s.sum(axis=1)
        one_face = (count == 3) & np.any(s[:, FACE_EDGES].all(axis=2), axis=1)
        opposite = (count == 2) & np.any(s[:, OPPOSITE_EDGES].all(axis=2), axis=1)
        irregular = ~((count <= 1) | (count == 6) | one_face | opposite)
        split[tet_edges[irregular]] = True
        if int(split.sum()) == before:
            return split


def refine_marked(mesh: TetMesh, marked: np.ndarray) -> LocalRefinement:
    """`mesh` with the tets `marked` (bool [m] or indices) split in 8, and the closure templates
    around them (module docstring). No tet marked: the mesh as given; all marked: `refine_uniform(mesh, 1)`'s
    elements (numbered differently)."""
    m = len(mesh.tets)
    marked = np.asarray(marked)
    if marked.dtype != bool:
        idx = marked.astype(np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= m):
            raise ValueError(f"marked tets must be numbers 0–{m - 1}")
        marked = np.zeros(m, dtype=bool)
        marked[idx] = True
    elif marked.shape != (m,):
        raise ValueError(f"marked must be one flag per tet ({m}), got shape {marked.shape}")
    dofmap = build_dofmap(mesh.nodes, mesh.tets, 2)
    n = mesh.n_nodes
    tet_edges = dofmap.cell_dofs[:, 4:] - n
    split = np.zeros(len(dofmap.edge_vertices), dtype=bool)
    split[tet_edges[marked].ravel()] = True
    split = close_split_edges(tet_edges, split)
    split_edges = np.flatnonzero(split)
    node_of_edge = np.full(len(split), -1, dtype=np.int64)
    node_of_edge[split_edges] = n + np.arange(len(split_edges))
    nodes = np.vstack([mesh.nodes, dofmap.points[n + split_edges]])

    s = split[tet_edges]
    count = s.sum(axis=1)
    mid = node_of_edge[tet_edges]  # [m, 6], −1 where not split
    children, parents = [], []

    def add(rows: list[np.ndarray], which: np.ndarray) -> None:
        for r in rows:
            children.append(r)
            parents.append(which)

    keep = np.flatnonzero(count == 0)
    add([mesh.tets[keep]], keep)
    red = np.flatnonzero(count == 6)
    v = [mesh.tets[red, i] for i in range(4)]
    mids = {tuple(e): mid[red, k] for k, e in enumerate(TET_EDGES.tolist())}
    add(red_children(nodes, v, mids), red)
    for k, (a, b) in enumerate(TET_EDGES.tolist()):  # one edge: two halves
        which = np.flatnonzero((count == 1) & s[:, k])
        c, d = [i for i in range(4) if i not in (a, b)]
        t, mk = mesh.tets[which], mid[which, k]
        add([np.stack([t[:, a], mk, t[:, c], t[:, d]], axis=1), np.stack([mk, t[:, b], t[:, c], t[:, d]], axis=1)],
            which)
    for e1, e2 in OPPOSITE_EDGES:  # two opposite edges ab, cd: four tets
        which = np.flatnonzero((count == 2) & s[:, e1] & s[:, e2])
        t, m1, m2 = mesh.tets[which], mid[which, e1], mid[which, e2]
        (a, b), (c, d) = (t[:, TET_EDGES[e1][0]], t[:, TET_EDGES[e1][1]]), (t[:, TET_EDGES[e2][0]], t[:, TET_EDGES[e2][1]])
        add([np.stack(r, axis=1) for r in ((a, m1, c, m2), (a, m1, m2, d), (m1, b, c, m2), (m1, b, m2, d))], which)
    for f, (edges, verts) in enumerate(zip(FACE_EDGES, FACE_VERTICES)):  # one face: four tets
        which = np.flatnonzero((count == 3) & s[:, edges].all(axis=1))
        t = mesh.tets[which]
        a, b, c, d = t[:, verts[0]], t[:, verts[1]], t[:, verts[2]], t[:, FACE_OPPOSITE[f]]
        mab, mbc, mac = (mid[which, _edge_number(verts[i], verts[j])] for i, j in ((0, 1), (1, 2), (0, 2)))
        add([np.stack(r, axis=1) for r in ((a, mab, mac, d), (mab, b, mbc, d), (mac, mbc, c, d), (mab, mbc, mac, d))],
            which)
    tets = orient_positive(nodes, np.concatenate(children))
    endo, epi, base = (_split_facets(f, dofmap, node_of_edge) for f in (mesh.endo, mesh.epi, mesh.base))
    info = dict(mesh.info, locally_refined_tets=int((count == 6).sum()))
    fine = make_mesh(nodes, tets, endo, epi, base, info=info)
    return LocalRefinement(fine, np.concatenate(parents), split_edges, count == 6)


def _edge_number(i: int, j: int) -> int:
    """The local number (TET_EDGES order) of the edge joining local vertices i and j."""
    pair = sorted((i, j))
    return int(np.flatnonzero((TET_EDGES == pair).all(axis=1))[0])


def _split_facets(facets: np.ndarray, dofmap, node_of_edge: np.ndarray) -> np.ndarray:
    """Boundary triangles (a, b, c) split as their tets' faces are: none, one edge (2 triangles) or all
    three (4), each child with the parent's winding."""
    if len(facets) == 0:
        return facets.copy()
    n = dofmap.n_vertices
    edges = facet_dofs(dofmap, facets)[:, 3:] - n  # edges ab, bc, ac
    mid = node_of_edge[edges]
    s = mid >= 0
    count = s.sum(axis=1)
    a, b, c = facets.T
    out = [facets[count == 0]]
    full = count == 3
    mab, mbc, mac = mid[full].T
    out += [np.stack(t, axis=1) for t in ((a[full], mab, mac), (mab, b[full], mbc), (mac, mbc, c[full]),
                                          (mab, mbc, mac))]
    # one split edge: (x, y) split at m, z the third vertex, in the triangle's cyclic order x → y → z
    for k, (x, y, z) in enumerate(((a, b, c), (b, c, a), (a, c, b))):
        one = (count == 1) & s[:, k]
        mk = mid[one, k]
        if k == 2:  # edge ac runs against the winding a → b → c: (c, a) is the cyclic pair
            out += [np.stack([c[one], mk, b[one]], axis=1), np.stack([mk, a[one], b[one]], axis=1)]
        else:
            out += [np.stack([x[one], mk, z[one]], axis=1), np.stack([mk, y[one], z[one]], axis=1)]
    if (count == 2).any():
        raise ValueError("a boundary triangle has two split edges: the closure is broken")
    return np.concatenate(out)
