"""The LV tetrahedral mesh as a value: nodes (mm), tets, tagged boundary triangles (endocardium,
epicardium, base), validation of user meshes and surface tagging of untagged ones."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # outward for positive tets


class MeshError(ValueError):
    """A mesh the solver cannot use; the message says what is wrong in one line."""


class MeshUnitsWarning(UserWarning):
    """A mesh whose size no human LV has (long axis, wall, cavity): most likely read in the wrong
    length unit. The message names the sizes and the unit that would fit, in one line."""


@dataclass(frozen=True)
class TetMesh:
    """Linear tetrahedral mesh. nodes [n,3] in mm, tets [m,4] positively oriented;
    endo/epi/base [k,3] boundary triangles, each oriented with its normal pointing out of the wall."""

    nodes: np.ndarray
    tets: np.ndarray
    endo: np.ndarray
    epi: np.ndarray
    base: np.ndarray
    info: dict = field(default_factory=dict, compare=False)

    @property
    def n_nodes(self) -> int:
        return self.nodes.shape[0]

    def with_nodes(self, nodes: np.ndarray) -> "TetMesh":
        return replace(self, nodes=np.ascontiguousarray(nodes, dtype=float))

    def base_nodes(self) -> np.ndarray:
        return np.unique(self.base)

    def endo_nodes(self) -> np.ndarray:
        return np.unique(self.endo)

    def epi_nodes(self) -> np.ndarray:
        return np.unique(self.epi)


def _unique_faces(faces: np.ndarray, **kwargs):
    """np.unique over triangles as node sets (any order), returning only the `return_*` arrays.

    Each triangle becomes one int64 (its sorted node numbers in base n), which sorts about 4× faster
    than np.unique(axis=0) on rows; meshes with n³ ≥ 2⁶³ fall back to rows."""
    key = np.sort(faces, axis=1).astype(np.int64)
    n = int(key.max()) + 1 if key.size else 1
    if n < 2_000_000:  # n³ < 2⁶³
        key = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
        return np.unique(key, **kwargs)[1:]
    return np.unique(key, axis=0, **kwargs)[1:]


def boundary_facets(tets: np.ndarray) -> np.ndarray:
    """Triangles on the boundary, oriented outward (tets must be positively oriented)."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    idx, counts = _unique_faces(faces, return_index=True, return_counts=True)
    return faces[idx[counts == 1]]


def signed_tet_volumes(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tet, mm³ (positive when nodes 1, 2, 3 turn counter-clockwise seen
    from node 0's far side); no inversion, so it is safe on degenerate tets."""
    x = np.asarray(nodes, dtype=float)[tets]
    return np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6.0


def scaled_jacobian(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Mean-ratio-like quality in [−1, 1]: 6√2 V / l_rms^3 (1 for a regular tet, ≤ 0 inverted)."""
    vol = signed_tet_volumes(nodes, tets)
    x = nodes[tets]
    edges = np.stack([x[:, j] - x[:, i] for i, j in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]], axis=1)
    l_rms = np.sqrt((edges**2).sum(axis=2).mean(axis=1))
    return 6.0 * np.sqrt(2.0) * vol / l_rms**3


def orient_positive(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Reorder each tet's nodes so its volume is positive (for meshes we generate ourselves)."""
    vol = signed_tet_volumes(nodes, tets)
    tets = np.array(tets, dtype=np.int64)
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    return tets


MAX_COORDINATE_MM = 1e4  # 10 m: no LV mesh, in any unit it may have been written in, lies beyond


def check_coordinates(nodes: np.ndarray, scale_to_mm: float = 1.0, unit: str = "mm") -> None:
    """MeshError for NaN or infinite coordinates, or any beyond ±MAX_COORDINATE_MM once scaled to mm
    (checked before any arithmetic on them, which would overflow with numpy warnings)."""
    nodes = np.asarray(nodes, dtype=float)
    if not np.all(np.isfinite(nodes)):
        raise MeshError("mesh has NaN or infinite node coordinates")
    largest = float(np.abs(nodes).max()) if nodes.size else 0.0
    if largest > MAX_COORDINATE_MM / scale_to_mm:
        raise MeshError(f"mesh has coordinates up to {largest:.3g} {unit}, beyond ±{MAX_COORDINATE_MM:g} mm: no LV "
                        f"is that large; check the mesh's coordinates and length unit (`units`)")


def check_geometry(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Validate coordinates and connectivity; return tets positively oriented, or raise MeshError.

    Node order within a tet is only a convention (many writers mix both), so each tet is reordered
    to positive volume. An element is *inverted* when the mesh folds over it: across an interior
    face, the two neighbouring tets then lie on the same side."""
    nodes = np.asarray(nodes, dtype=float)
    tets = np.asarray(tets)
    if nodes.ndim != 2 or nodes.shape[1] != 3 or nodes.shape[0] < 4:
        raise MeshError("mesh needs at least 4 nodes with 3 coordinates")
    check_coordinates(nodes)
    if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] == 0:
        raise MeshError("mesh has no tetrahedra (only linear 4-node tets are supported)")
    if tets.min() < 0 or tets.max() >= nodes.shape[0]:
        raise MeshError("tet connectivity refers to nodes that do not exist")
    vol = signed_tet_volumes(nodes, tets)
    scale = np.ptp(nodes, axis=0).max() ** 3
    tiny = 1e-12 * scale
    if np.any(np.abs(vol) <= tiny):
        raise MeshError(f"mesh has {int(np.sum(np.abs(vol) <= tiny))} degenerate (zero-volume) tets")
    tets = orient_positive(nodes, tets)
    folded = folded_tets(nodes, tets)
    if folded.size:
        raise MeshError(f"mesh has {folded.size} inverted tets (the mesh folds over them; of {len(tets)})")
    return np.ascontiguousarray(tets, dtype=np.int64)


def _tet_components(tets: np.ndarray) -> np.ndarray:
    """Label tets by face-connected component."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    owner = np.repeat(np.arange(len(tets)), 4)
    (inverse,) = _unique_faces(tets[:, TET_FACES].reshape(-1, 3), return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    same = inverse[order][1:] == inverse[order][:-1]
    a, b = owner[order][:-1][same], owner[order][1:][same]
    graph = coo_matrix((np.ones(a.size), (a, b)), shape=(len(tets), len(tets)))
    return connected_components(graph, directed=False)[1]


def folded_tets(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Indices of positively oriented tets whose neighbour across a face lies on their own side."""
    faces = tets[:, TET_FACES].reshape(-1, 3)  # outward for positive tets
    owner = np.repeat(np.arange(len(tets)), 4)
    inverse, counts = _unique_faces(faces, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    if counts.max() > 2:
        raise MeshError(f"mesh is not manifold: {int((counts > 2).sum())} faces are shared by more than two tets")
    order = np.argsort(inverse, kind="stable")
    shared = counts[inverse[order]] == 2
    pair_idx = order[shared].reshape(-1, 2)
    a, b = pair_idx[:, 0], pair_idx[:, 1]
    # the face as seen from tet a is outward for a; the opposite vertex of b must lie outside it
    fa = faces[a]
    opposite_b = tets[owner[b], b % 4]  # face f of a tet leaves out its vertex f
    x = nodes[fa]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    side = np.einsum("ij,ij->i", nodes[opposite_b] - x[:, 0], normal)
    bad = side <= 0
    return np.unique(np.concatenate([owner[a][bad], owner[b][bad]]))


def _facet_components(facets: np.ndarray) -> np.ndarray:
    """Label triangles by edge-connected component."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nf = facets.shape[0]
    edges = np.sort(np.concatenate([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [0, 2]]]), axis=1)
    owner = np.tile(np.arange(nf), 3)
    key = edges[:, 0].astype(np.int64) * (facets.max() + 1) + edges[:, 1]
    order = np.argsort(key)
    same = key[order][1:] == key[order][:-1]
    a, b = owner[order][:-1][same], owner[order][1:][same]
    graph = coo_matrix((np.ones(a.size), (a, b)), shape=(nf, nf))
    return connected_components(graph, directed=False)[1]


def tag_surfaces(nodes: np.ndarray, tets: np.ndarray, base_tol_mm: float | None = None):
    """Find the base plane (the top boundary triangles, normal +z, at max z) and split the rest
    of the boundary into endocardium (inner component) and epicardium (outer) by connectivity."""
    facets = boundary_facets(tets)
    p = nodes[facets]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    z_top = nodes[:, 2].max()
    tol = base_tol_mm if base_tol_mm is not None else 1e-6 * max(np.ptp(nodes, axis=0).max(), 1.0)
    is_base = (normal[:, 2] > 0.99) & np.all(np.abs(p[:, :, 2] - z_top) <= tol, axis=1)
    if not is_base.any():
        raise MeshError("no base plane found: the base must be a flat cut at the top (max z) of the mesh")
    rest = facets[~is_base]
    labels = _facet_components(rest)
    counts = np.bincount(labels)
    if counts.size < 2:
        raise MeshError("could not separate endocardium from epicardium: the wall boundary is one surface")
    big = np.argsort(counts)[::-1][:2]
    if counts.size > 2 and counts[np.argsort(counts)[::-1][2]] > 0.05 * counts[big].min():
        raise MeshError(f"boundary has {counts.size} separate surfaces besides the base; expected endo and epi")
    extent = [np.ptp(nodes[np.unique(rest[labels == k])], axis=0).prod() for k in big]
    endo_label, epi_label = (big[0], big[1]) if extent[0] < extent[1] else (big[1], big[0])
    return rest[labels == endo_label], rest[labels == epi_label], facets[is_base]


TAGGED_BASE_MEAN_NORMAL_Z = 0.95  # the tagged base's area-weighted mean outward normal: within ~18° of +z
TAGGED_BASE_DROP = 0.10  # and every base node within 10 % of the mesh height of its top


def _check_surfaces(nodes: np.ndarray, endo: np.ndarray, epi: np.ndarray, base: np.ndarray) -> None:
    """MeshError unless the surfaces fit the solver's conventions (which fix z on the base and take
    +z as the long axis): the base a cut facing +z at the top of the mesh, the endocardium inside
    the epicardium. Surfaces found by tag_surfaces fit by construction; tags read from a file are
    checked, since a turned mesh or swapped tags would otherwise solve a different problem. A base
    need not be exactly flat (a network's unloaded output, a segmentation's cut): the bounds only
    catch a base that faces sideways or down, or sits away from the top."""
    p = nodes[base]
    area_normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]).sum(axis=0)
    height = np.ptp(nodes[:, 2])
    facing = area_normal[2] / max(np.linalg.norm(area_normal), 1e-300)
    if facing < TAGGED_BASE_MEAN_NORMAL_Z or p[:, :, 2].min() < nodes[:, 2].max() - TAGGED_BASE_DROP * height:
        raise MeshError("the tagged base is not a cut facing +z at the top of the mesh (long axis z, "
                        "base at max z, apex at negative z)")
    extent = [np.ptp(nodes[np.unique(f)], axis=0).prod() for f in (endo, epi)]
    if extent[0] >= extent[1]:
        raise MeshError("the tagged endocardium is not inside the epicardium (are the tags swapped?)")
    for name, faces in (("endocardium", endo), ("epicardium", epi)):
        pieces = np.unique(_facet_components(faces)).size
        if pieces > 1:
            raise MeshError(f"the tagged {name} is {pieces} separate pieces; it must be one surface (are part of "
                            f"its triangles tagged as another surface?)")


def lv_dimensions(mesh: TetMesh) -> dict:
    """Sizes of an LV mesh that tell its length unit: {"long_axis_mm": extent along z (base to
    apex), "wall_mm": mean distance from an endocardial node to the nearest epicardial node,
    "cavity_ml": volume enclosed by the endocardium and the plane of its top, or None when that is
    not positive (an open or odd endocardium)}."""
    from scipy.spatial import cKDTree

    nodes = mesh.nodes
    endo, epi = mesh.endo_nodes(), mesh.epi_nodes()
    wall = float(cKDTree(nodes[epi]).query(nodes[endo])[0].mean()) if endo.size and epi.size else None
    tri = nodes[mesh.endo]
    area_z = 0.5 * np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2]
    top = nodes[endo, 2].max() if endo.size else 0.0
    cavity = float(-((tri[:, :, 2].mean(axis=1) - top) * area_z).sum()) / 1e3  # endo normals point into the cavity
    return {"long_axis_mm": float(np.ptp(nodes[:, 2])), "wall_mm": wall, "cavity_ml": cavity if cavity > 0 else None}


def make_mesh(nodes: np.ndarray, tets: np.ndarray, endo=None, epi=None, base=None, info=None) -> TetMesh:
    """Validate and assemble a TetMesh; surfaces are found when not given."""
    tets = check_geometry(nodes, tets)
    sizes = np.bincount(_tet_components(tets))  # topology: once per mesh, not per trial geometry
    if sizes.size > 1:
        raise MeshError(f"mesh is in {sizes.size} separate pieces (tets sharing no face: the largest has "
                        f"{sizes.max()} of {len(tets)}); the LV wall must be one piece")
    nodes = np.ascontiguousarray(nodes, dtype=float)
    if endo is None or epi is None or base is None:
        endo, epi, base = tag_surfaces(nodes, tets)
    else:
        outward = {tuple(sorted(f)): f for f in boundary_facets(tets)}

        def orient(faces):
            faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
            try:
                return np.array([outward[tuple(sorted(f))] for f in faces], dtype=np.int64).reshape(-1, 3)
            except KeyError as exc:
                raise MeshError("a tagged surface triangle is not on the mesh boundary") from exc

        endo, epi, base = orient(endo), orient(epi), orient(base)
        tagged = np.sort(np.concatenate([endo, epi, base]), axis=1)
        distinct, counts = np.unique(tagged, axis=0, return_counts=True)
        if (counts > 1).any():
            raise MeshError(f"{int((counts > 1).sum())} boundary triangles carry more than one surface tag; each must be "
                            f"endocardium, epicardium or base, once")
        if len(distinct) < len(outward):  # untagged triangles may only close small voids, as tag_surfaces allows
            tagged_keys = set(map(tuple, distinct))
            is_tagged = np.array([key in tagged_keys for key in outward])
            labels = _facet_components(np.array(list(outward.values())))
            gaps = np.isin(labels[~is_tagged], labels[is_tagged])
            if gaps.any():
                raise MeshError(f"{int(gaps.sum())} of the {len(outward)} boundary triangles carry no surface tag; "
                                f"endocardium, epicardium and base must cover the wall's boundary")
    for name, faces in (("endocardium", endo), ("epicardium", epi), ("base", base)):
        if len(faces) == 0:
            raise MeshError(f"mesh has no {name} surface")
    _check_surfaces(nodes, endo, epi, base)
    return TetMesh(nodes, tets, np.asarray(endo), np.asarray(epi), np.asarray(base), dict(info or {}))
