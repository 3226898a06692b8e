"""Rule-based myofibre field: transmural coordinate φ from a Laplace solve (0 endo, 1 epi) and an
orthonormal (f, s, n) frame per quadrature point with a helix angle linear in φ.

Sign convention: t = ∇φ/|∇φ| points endo → epi, e_l is the long axis (+z, apex → base) projected on
the wall, e_c = e_l × t is circumferential (counter-clockwise seen from the base, looking down −z).
f = cos θ e_c + sin θ e_l is e_c rotated by θ about t, so θ > 0 tilts fibres toward the base as they
run counter-clockwise; the paper's endo +60…+70° and epi −60…−70° form the usual opposed helices.
s = t (sheet-normal, transmural), n = f × s.

The field is discretised to the order of the displacement it drives. For P1 displacements φ is P1
and t constant per tet. For P2 displacements φ is P2 and t is evaluated at each quadrature point:
a per-tet t is only first-order accurate, and on the strongly curved apical wall (a coarse mesh has
one or two tets across it) its error dominated the P2 solution's discretisation error, so that it
did not shrink at P2's rate under refinement (`heartctl bench convergence`, docs/solver.md)."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .elements import build_dofmap, cell_quadrature, facet_dofs, simplex_shape, tet_geometry
from .linear import SparseSolver
from .mesh import TetMesh
from .parameters import FIBRE_RULES


def transmural_coordinate(mesh: TetMesh) -> np.ndarray:
    """φ at the mesh nodes: −Δφ = 0 in the wall, φ = 0 on the endocardium, φ = 1 on the epicardium
    (P1 elements)."""
    return np.clip(_laplace_dofs(mesh, 1)[1], 0.0, 1.0)


def _laplace_dofs(mesh: TetMesh, order: int):
    """(dof map, φ at its dofs) of the Laplace problem for φ with P`order` elements; the dofs of the
    endo- and epicardial triangles (vertices, and edge midpoints for P2) carry the boundary values."""
    dofmap = build_dofmap(mesh.nodes, mesh.tets, order)
    quad = cell_quadrature(mesh.nodes, mesh.tets, order, max(2 * order - 2, 1))
    ne, nq, nb, _ = quad.grads.shape
    by_dof = np.ascontiguousarray(quad.grads.transpose(0, 2, 1, 3)).reshape(ne, nb, nq * 3)  # [e, a, (q I)]
    weighted = by_dof * np.repeat(np.abs(quad.dV), 3, axis=1)[:, None, :]
    ke = weighted @ np.swapaxes(by_dof, 1, 2)  # Σ_q dV ∇φ_a · ∇φ_b
    phi = np.full(dofmap.n_dofs, np.nan)
    for value, facets in ((0.0, mesh.endo), (1.0, mesh.epi)):
        phi[np.unique(facet_dofs(dofmap, facets))] = value
    free = np.isnan(phi)
    unknown = np.cumsum(free) - 1  # a free dof's row in the reduced system
    rows = np.repeat(dofmap.cell_dofs, nb, axis=1).ravel()
    cols = np.tile(dofmap.cell_dofs, (1, nb)).ravel()
    values = ke.ravel()
    inner = free[rows] & free[cols]
    n_free = int(free.sum())
    K = sp.csr_matrix((values[inner], (unknown[rows[inner]], unknown[cols[inner]])), shape=(n_free, n_free))
    coupling = free[rows] & ~free[cols]  # a free row's entries on the surfaces' known values
    rhs = -np.bincount(unknown[rows[coupling]], weights=values[coupling] * phi[cols[coupling]], minlength=n_free)
    with SparseSolver() as linsolve:  # PARDISO where installed: SuperLU's fill grows fast on P2 in 3D
        phi[free] = linsolve.solve(K, rhs)
    return dofmap, phi


def wall_directions(mesh: TetMesh, phi: np.ndarray):
    """Per-tet transmural t, longitudinal e_l and circumferential e_c unit vectors, each [m, 3]."""
    vol, g = tet_geometry(mesh.nodes, mesh.tets)
    grad = _fill_flat_gradients(mesh.tets, np.einsum("ea,eaI->eI", phi[mesh.tets], g), np.abs(vol), mesh.n_nodes)
    t = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-300)
    el, ec = _longitudinal_circumferential(t)
    return t, el, ec


def _longitudinal_circumferential(t: np.ndarray):
    """e_l (the long axis +z projected normal to t) and e_c = e_l × t, unit, for unit t [k, 3]; where
    t lies along the axis (at the apex), x is projected instead."""
    ez = np.array([0.0, 0.0, 1.0])
    el = ez - np.outer(t @ ez, np.ones(3)) * t
    norm = np.linalg.norm(el, axis=1)
    degenerate = norm < 1e-6
    if degenerate.any():
        ex = np.array([1.0, 0.0, 0.0])
        el[degenerate] = ex - np.outer(t[degenerate] @ ex, np.ones(3)) * t[degenerate]
        norm = np.linalg.norm(el, axis=1)
    el /= norm[:, None]
    return el, np.cross(el, t)


def _fill_flat_gradients(tets: np.ndarray, grad: np.ndarray, vol: np.ndarray, n_nodes: int) -> np.ndarray:
    """∇φ per tet, where a tet with all four nodes on one surface (φ equal at its nodes: ∇φ = 0, so
    no transmural direction, e.g. one element across a thin wall) takes the volume-weighted mean
    gradient of the tets around its nodes."""
    size = np.linalg.norm(grad, axis=1)
    flat = size <= 1e-8 * max(float(np.median(size)), 1e-300)
    if not flat.any():
        return grad
    weights = np.where(flat, 0.0, vol)[:, None] * grad  # flat tets give nothing to their nodes
    at_node = np.zeros((n_nodes, 3))
    np.add.at(at_node, tets.ravel(), np.repeat(weights, 4, axis=0))
    grad = grad.copy()
    grad[flat] = at_node[tets[flat]].mean(axis=1)
    return grad


def fibre_frames(mesh: TetMesh, helix_endo_deg: float, helix_epi_deg: float, lam: np.ndarray,
                 phi: np.ndarray | None = None, order: int = 1) -> np.ndarray:
    """Frames [m, nq, 3, 3] whose columns are (f, s, n), at quadrature points with barycentric
    coordinates lam [4, nq]. Angles in degrees (CLI convention), converted to radians here.

    order 1: φ P1 (`phi` at the nodes may be given), t constant per tet. order 2: φ P2, t from ∇φ
    at each quadrature point (where ∇φ vanishes there, the tet's P1 direction)."""
    if order == 1:
        if phi is None:
            phi = transmural_coordinate(mesh)
        t, el, ec = wall_directions(mesh, phi)
        phi_q = np.einsum("ea,aq->eq", phi[mesh.tets], lam)
        t, el, ec = (np.broadcast_to(v[:, None, :], (len(mesh.tets), lam.shape[1], 3)) for v in (t, el, ec))
    elif order == 2:
        phi_q, t, el, ec = _quadratic_wall_directions(mesh, lam)
    else:
        raise ValueError(f"fibre field order must be 1 or 2, got {order}")
    theta = np.deg2rad(helix_endo_deg + np.clip(phi_q, 0.0, 1.0) * (helix_epi_deg - helix_endo_deg))
    c, s = np.cos(theta)[..., None], np.sin(theta)[..., None]
    f = c * ec + s * el
    sheet = np.broadcast_to(t, f.shape)
    n = np.cross(f, sheet)
    return np.stack([f, sheet, n], axis=-1)


def centroid_frames(mesh: TetMesh, helix_endo_deg: float, helix_epi_deg: float, order: int) -> np.ndarray:
    """One (f, s, n) frame per tet [m, 3, 3], the fibre field of the given order (1: `fast`'s P1 φ;
    2: `accurate`'s and `reference`'s P2 φ) at the tet's centroid: what a mesh file carries per cell."""
    return fibre_frames(mesh, helix_endo_deg, helix_epi_deg, np.full((4, 1), 0.25), order=order)[:, 0]


def _quadratic_wall_directions(mesh: TetMesh, lam: np.ndarray):
    """φ [m, nq] and unit t, e_l, e_c [m, nq, 3] at the points lam [4, nq] of every tet, from P2 φ."""
    dofmap, phi = _laplace_dofs(mesh, 2)
    vals, dl = simplex_shape(2, lam)
    _, g = tet_geometry(mesh.nodes, mesh.tets)
    local = phi[dofmap.cell_dofs]  # [m, 10]
    phi_q = local @ vals
    grad = np.swapaxes((local @ dl.reshape(dl.shape[0], -1)).reshape(len(g), *dl.shape[1:]), 1, 2) @ g  # [e, q, I]
    size = np.linalg.norm(grad, axis=2)
    flat = size <= 1e-8 * max(float(np.median(size)), 1e-300)
    if flat.any():  # a point where ∇φ vanishes (a tet hugging one surface): the tet's P1 direction
        p1 = transmural_coordinate(mesh)
        t1, _, _ = wall_directions(mesh, p1)
        grad[flat] = np.broadcast_to(t1[:, None, :], grad.shape)[flat]
    t = grad / np.linalg.norm(grad, axis=2, keepdims=True)
    el, ec = _longitudinal_circumferential(t.reshape(-1, 3))
    return phi_q, t, el.reshape(t.shape), ec.reshape(t.shape)


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


# --------------------------------------------------------------------------- heartFEM's rule
# The original dataset's pipeline (heartFEM's vtk_py: addLocalProlateSpheroidalDirections and
# addLocalFiberOrientation) builds the frame at each quadrature point from the closest points on
# the endo- and epicardial surfaces (both cut 0.05 cm below the base, as vtkClipPolyData cuts
# them) instead of a Laplace solve. Its transmural coordinate is d = d_endo² / (d_endo² + d_epi²): vtkCellLocator's
# FindClosestPoint returns the *squared* distance, which that code divides as if it were the
# distance. The transmural direction is t = unit(−(1 − d) N_endo + d N_epi) with the surface
# normals (out of the wall) at the closest points (heartFEM takes the closest face's normal; we
# interpolate vertex normals and blend nearly equidistant faces, see surface_distance, which keeps
# the frames continuous for the inverse problem), e_c = e_z × t, e_l = t × e_c, and the helix
# angle is linear in d. On a wall one element thick (the dataset's meshes) the squared ratio moves
# the quadrature points' angles from ±30° to ±48° for 60/−60 — it shows in the displacements.

BASE_CLIP_MM = 0.5  # heartFEM's clipheight, 0.05 cm
NORMAL_BLEND_FRACTION = 0.005  # soft-min width δ of the closest-point normal, × the surface's mean edge length
NORMAL_BLEND_CUTOFF = 20.0  # the blend's weights are zero beyond this many δ
FULL_WEIGHT_AREA = 1e-3  # a clipped piece counts fully in the blend from this fraction of the mean triangle area


def check_fibre_rule(rule: str) -> None:
    """ValueError (one line, naming --fibres) unless `rule` is one of FIBRE_RULES."""
    if rule not in FIBRE_RULES:
        raise ValueError(f"`fibres` must be {' or '.join(FIBRE_RULES)}, got {rule!r}")



def closest_points_on_triangles(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest point of triangle (a, b, c) to each point; all arrays [k, 3] (row-wise pairs).
    Region tests of Ericson, Real-Time Collision Detection §5.1.5, vectorised."""
    ab, ac, ap = b - a, c - a, points - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = points - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = points - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        out = a + ab * (vb * denom)[:, None] + ac * (vc * denom)[:, None]  # interior
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    cases = [  # later entries win: vertex regions, then edges, are tested in Ericson's order reversed
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[:, None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[:, None]),
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * t_bc[:, None]),
        ((d6 >= 0) & (d5 <= d6), c),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d1 <= 0) & (d2 <= 0), a),
    ]
    for mask, value in reversed(cases):
        out = np.where(mask[:, None], value, out)
    return out


def vertex_normals(nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals [n, 3] of a triangulated surface (zero where no triangle)."""
    tri = nodes[triangles]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # 2 × area × unit normal
    out = np.zeros_like(nodes, dtype=float)
    np.add.at(out, triangles.ravel(), np.repeat(face_n, 3, axis=0))
    return _unit(out)


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of v scaled to unit length (zero rows stay zero)."""
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def triangle_areas(nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    tri = nodes[triangles]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def mean_edge_length(nodes: np.ndarray, triangles: np.ndarray) -> float:
    tri = nodes[triangles]
    return float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).mean())


def surface_distance(points: np.ndarray, nodes: np.ndarray, triangles: np.ndarray, candidates: int = 32,
                     blend_mm: float | None = None, normals: np.ndarray | None = None,
                     face_weights: np.ndarray | None = None):
    """Distance from each point [k, 3] to a triangulated surface, and the unit surface normal at
    the closest point (orientation as the triangles are wound).

    The normal is interpolated from the vertex normals (`normals` at `nodes`; default: area-weighted
    ones of `triangles`) at each triangle's closest point, and the triangles are blended with weights
    exp(−Δ/δ)·(1 − Δ/(20δ))², Δ = d_i − d_min, zero for Δ ≥ 20δ; δ = blend_mm (default
    NORMAL_BLEND_FRACTION × the mean edge length; 0 takes the closest triangle alone). So the normal
    varies continuously with the points and the surface: inverse FE moves the reference and rebuilds
    the fibres, and a wall point inside a convex faceted surface (the epicardium) jumps from one
    face's closest point to another's where the two are equidistant (a 0.03 jump in the normal
    stalled the inverse at ~1e-3 mm). On a smooth stretch the neighbours of the closest face count
    too when the closest point is within ~√(2 d_min · 20δ) of their shared edge, where their normals
    agree with it. `face_weights` [t] (default 1) scale each triangle's weight: a clipped surface
    gives its tiny pieces little, so that pieces appearing as the plane passes a node change nothing.
    The triangles are searched by their centroids, nearest first, `candidates` at a time and more
    until every triangle left out is provably farther than d_min + 20δ."""
    from scipy.spatial import cKDTree

    tri = nodes[triangles]
    vertex_n = vertex_normals(nodes, triangles) if normals is None else normals
    delta = NORMAL_BLEND_FRACTION * mean_edge_length(nodes, triangles) if blend_mm is None else blend_mm
    cutoff = NORMAL_BLEND_CUTOFF * delta
    centroids = tri.mean(axis=1)
    reach = float(np.linalg.norm(tri - centroids[:, None, :], axis=2).max())  # a triangle's points lie this close to its centroid
    tree = cKDTree(centroids)
    n_tri = len(triangles)
    dist, normal = np.empty(len(points)), np.empty((len(points), 3))
    todo, m = np.arange(len(points)), min(candidates, n_tri)
    while todo.size:
        centroid_dist, near = tree.query(points[todo], k=m)
        centroid_dist, near = centroid_dist.reshape(len(todo), m), near.reshape(len(todo), m)
        d_min, n_blend = _blended_normal(points[todo], near, tri, vertex_n[triangles], delta, cutoff, face_weights)
        done = (m == n_tri) | (centroid_dist[:, -1] - reach > d_min + cutoff)
        dist[todo[done]], normal[todo[done]] = d_min[done], n_blend[done]
        todo, m = todo[~done], min(2 * m, n_tri)
    return dist, normal


def _blended_normal(points, near, tri, tri_normals, delta: float, cutoff: float, face_weights=None):
    """d_min [k] and the blended unit normal [k, 3] over the candidate triangles `near` [k, m]."""
    k, m = near.shape
    flat = near.ravel()
    rep = np.repeat(points, m, axis=0)
    q = closest_points_on_triangles(rep, tri[flat, 0], tri[flat, 1], tri[flat, 2])
    dist = np.linalg.norm(q - rep, axis=1).reshape(k, m)
    lam = _barycentric(q, *(tri[flat, i] for i in range(3)))
    normals = np.einsum("ka,kai->ki", lam, tri_normals[flat]).reshape(k, m, 3)
    d_min = dist.min(axis=1)
    gap = dist - d_min[:, None]
    closest = (np.arange(m)[None, :] == dist.argmin(axis=1)[:, None]).astype(float)
    if delta > 0:
        weights = np.exp(-gap / delta) * np.clip(1.0 - gap / cutoff, 0.0, None) ** 2
        if face_weights is not None:
            weights = weights * face_weights[near] + 1e-12 * closest  # never all zero
    else:
        weights = closest
    return d_min, _unit(np.einsum("km,kmi->ki", weights, normals))


def _barycentric(q: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentric coordinates [k, 3] of points q lying on triangles (a, b, c)."""
    v0, v1, v2 = b - a, c - a, q - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = np.maximum(d00 * d11 - d01 * d01, 1e-300)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, 1.0)


def clip_below(nodes: np.ndarray, triangles: np.ndarray, height: float):
    """The part of a triangulated surface below z = height, cut along the plane as VTK's
    vtkClipPolyData cuts it (heartFEM clips its surfaces so): triangles wholly below are kept, those
    wholly above dropped, and a triangle the plane crosses is cut at the plane (a triangle or a
    quadrilateral split in two, winding kept). A cut edge's point is shared by both of its triangles,
    a node on the plane is its own cut point, and zero-area pieces are dropped. The cut surface moves
    continuously with the nodes, where dropping whole triangles would jump.
    Returns (points [p, 3], triangles [t, 3], interpolation [p, n] sparse): points = interpolation @
    nodes (the first n points are the nodes; carry any nodal field to the points the same way)."""
    n = len(nodes)
    below = nodes[:, 2] < height
    inside = below[triangles]
    n_in = inside.sum(axis=1)
    crossed = (n_in == 1) | (n_in == 2)
    kept = [triangles[n_in == 3]]
    cut = triangles[crossed]
    # rotate each cut triangle (keeping its winding) so that it starts at its lone vertex: the one
    # below the plane when one is below, the one above when two are
    lone = np.where(n_in[crossed][:, None] == 1, inside[crossed], ~inside[crossed])
    idx = (lone.argmax(axis=1)[:, None] + np.arange(3)[None, :]) % 3
    a, b, c = (np.take_along_axis(cut, idx, axis=1)[:, i] for i in range(3))
    keys, inverse = np.unique(np.sort(np.concatenate([np.stack([a, b], 1), np.stack([a, c], 1)]), axis=1),
                              axis=0, return_inverse=True)
    inverse = inverse.ravel()
    z0, z1 = nodes[keys[:, 0], 2], nodes[keys[:, 1], 2]
    t = (height - z0) / (z1 - z0)  # one end below, one at or above: z1 ≠ z0
    fresh = (t != 0.0) & (t != 1.0)  # else an end lies on the plane and is the cut point itself
    point_of_edge = np.where(fresh, n + np.cumsum(fresh) - 1, np.where(t == 0.0, keys[:, 0], keys[:, 1]))
    rows = np.concatenate([np.arange(n), np.repeat(n + np.arange(fresh.sum()), 2)])
    cols = np.concatenate([np.arange(n), keys[fresh].ravel()])
    vals = np.concatenate([np.ones(n), np.stack([1.0 - t[fresh], t[fresh]], 1).ravel()])
    interpolation = sp.csr_matrix((vals, (rows, cols)), shape=(n + int(fresh.sum()), n))
    points = interpolation @ nodes
    p_ab, p_ac = point_of_edge[inverse[: len(a)]], point_of_edge[inverse[len(a):]]
    one_below = below[a]
    kept.append(np.stack([a, p_ab, p_ac], 1)[one_below])  # the lone vertex's corner
    two = ~one_below  # b and c below: the quadrilateral p_ab, b, c, p_ac
    kept.append(np.stack([p_ab, b, c], 1)[two])
    kept.append(np.stack([p_ab, c, p_ac], 1)[two])
    tris = np.concatenate(kept)
    return points, tris[triangle_areas(points, tris) > 0], interpolation


def _clipped_surface(mesh: TetMesh, triangles: np.ndarray, clip_mm: float):
    """A surface of the mesh cut clip_mm below its base (the highest node), as heartFEM clips it, with
    the whole surface's vertex normals carried to its points (so they do not jump as a node crosses
    the plane); the whole surface if nothing of it lies below. Returns (points, triangles, normals,
    face weights for the blend: a piece's area over FULL_WEIGHT_AREA × the mean area, at most 1)."""
    whole = vertex_normals(mesh.nodes, triangles)
    points, tris, interpolation = clip_below(mesh.nodes, triangles, mesh.nodes[:, 2].max() - clip_mm)
    if len(tris) == 0:
        return mesh.nodes, triangles, whole, np.ones(len(triangles))
    normals = _unit(interpolation @ whole)
    full = FULL_WEIGHT_AREA * triangle_areas(mesh.nodes, triangles).mean()
    return points, tris, normals, np.minimum(triangle_areas(points, tris) / full, 1.0)


def _clipped_distance(x: np.ndarray, mesh: TetMesh, surface: np.ndarray, clip_mm: float):
    """Distance and blended normal from points x to a clipped surface; δ from the whole surface's
    edges (the clipped one's mean edge changes as triangles are cut)."""
    points, tris, normals, weights = _clipped_surface(mesh, surface, clip_mm)
    blend_mm = NORMAL_BLEND_FRACTION * mean_edge_length(mesh.nodes, surface)
    return surface_distance(x, points, tris, blend_mm=blend_mm, normals=normals, face_weights=weights)


def heartfem_frames(mesh: TetMesh, helix_endo_deg: float, helix_epi_deg: float, lam: np.ndarray,
                    clip_mm: float = BASE_CLIP_MM) -> np.ndarray:
    """(f, s, n) frames [m, nq, 3, 3] at quadrature points by heartFEM's rule (see above); mm."""
    x = np.einsum("eai,aq->eqi", mesh.nodes[mesh.tets], lam).reshape(-1, 3)
    # TetMesh keeps its surface triangles wound out of the wall, so the normals need no fixing
    d_endo, n_endo = _clipped_distance(x, mesh, mesh.endo, clip_mm)
    d_epi, n_epi = _clipped_distance(x, mesh, mesh.epi, clip_mm)
    d = d_endo ** 2 / np.maximum(d_endo ** 2 + d_epi ** 2, 1e-300)  # squared, as heartFEM computes it
    t = -(1.0 - d)[:, None] * n_endo + d[:, None] * n_epi  # out of the wall: −N_endo and N_epi point endo → epi
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-300)
    ez = np.array([0.0, 0.0, 1.0])
    ec = np.cross(ez, t)
    small = np.linalg.norm(ec, axis=1) < 1e-6  # t along the axis at the apex
    ec[small] = np.cross(np.array([1.0, 0.0, 0.0]), t[small])
    ec /= np.linalg.norm(ec, axis=1, keepdims=True)
    el = np.cross(t, ec)
    theta = np.deg2rad(helix_endo_deg + d * (helix_epi_deg - helix_endo_deg))
    f = np.cos(theta)[:, None] * ec + np.sin(theta)[:, None] * el
    n = np.cross(f, t)
    frames = np.stack([f, t, n], axis=-1)
    return frames.reshape(len(mesh.tets), lam.shape[1], 3, 3)


def rule_frames(rule: str, mesh: TetMesh, helix_endo_deg: float, helix_epi_deg: float, lam: np.ndarray,
                order: int = 1) -> np.ndarray:
    """Frames by the named rule: "laplace" (ours, default; φ of element order `order`) or "heartfem"
    (the original dataset's, built at each point from surface distances: no element order)."""
    if rule == "laplace":
        return fibre_frames(mesh, helix_endo_deg, helix_epi_deg, lam, order=order)
    if rule == "heartfem":
        return heartfem_frames(mesh, helix_endo_deg, helix_epi_deg, lam)
    raise ValueError(f"unknown fibre rule {rule!r}; choose {' or '.join(FIBRE_RULES)}")
