"""Shape model reproducibility and ranges; gmsh meshes: tags, quality, node counts; surface tagging
of untagged meshes; fibre frames."""
import numpy as np
import scipy.sparse as sp
import pytest

from solver.elements import cell_quadrature
from solver.fibres import fibre_frames, transmural_coordinate
from solver.mesh import MeshError, boundary_facets, make_mesh, scaled_jacobian
from solver.meshing import mesh_lv
from solver.shape_model import MODES, extreme_shapes, lv_shape, shape_coefficients


def test_shape_ids_are_reproducible_and_distinct():
    a, b = shape_coefficients(7, seed=3), shape_coefficients(7, seed=3)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(shape_coefficients(8, seed=3), a)
    assert not np.allclose(shape_coefficients(7, seed=4), a)


def test_coefficients_truncated_and_shapes_in_healthy_ranges():
    coeffs = np.array([shape_coefficients(i) for i in range(400)])
    assert np.all(np.abs(coeffs) <= 2.0)
    assert abs(coeffs.mean()) < 0.15 and 0.75 < coeffs.std() < 1.0  # truncated N(0,1): SD ≈ 0.88
    for shape in [lv_shape(i) for i in range(200)] + extreme_shapes():
        assert 80.0 <= shape.cavity_volume_ml() <= 220.0
        assert 6.0 <= shape.wall_thickness_mm <= 14.0
        assert shape.apex_thickness_mm < shape.wall_thickness_mm
    assert len(MODES) >= 6


@pytest.fixture(scope="module")
def default_mesh():
    return mesh_lv(lv_shape(0))


def test_gmsh_mesh_tags_quality_and_size(default_mesh):
    m = default_mesh
    assert 600 <= m.n_nodes <= 1000
    assert m.info["min_scaled_jacobian"] > 0.1
    assert scaled_jacobian(m.nodes, m.tets).min() > 0.1
    np.testing.assert_allclose(m.nodes[m.base_nodes(), 2], 0.0, atol=1e-9)
    assert m.nodes[:, 2].max() == pytest.approx(0.0, abs=1e-9) and m.nodes[:, 2].min() < -40
    # every boundary triangle carries exactly one tag
    tagged = np.sort(np.vstack([m.endo, m.epi, m.base]), axis=1)
    assert len(np.unique(tagged, axis=0)) == len(tagged) == len(boundary_facets(m.tets))
    # endo lies inside epi
    r = lambda f: np.linalg.norm(m.nodes[np.unique(f)][:, :2], axis=1).mean()  # noqa: E731
    assert r(m.endo) < r(m.epi)


def test_node_count_follows_target():
    shape = lv_shape(1)
    coarse, fine = mesh_lv(shape, 300), mesh_lv(shape, 1500)
    assert 0.8 * 300 <= coarse.n_nodes <= 1.2 * 300
    assert 0.8 * 1500 <= fine.n_nodes <= 1.2 * 1500


def test_untagged_mesh_is_tagged_like_gmsh(default_mesh):
    m = default_mesh
    auto = make_mesh(m.nodes, m.tets)
    for a, b in ((auto.endo, m.endo), (auto.epi, m.epi), (auto.base, m.base)):
        assert set(map(tuple, np.sort(a, axis=1))) == set(map(tuple, np.sort(b, axis=1)))


def test_solid_without_cavity_has_no_endocardium():
    from skfem import MeshTet

    box = MeshTet.init_tensor(np.linspace(0, 1, 3), np.linspace(0, 1, 3), np.linspace(-1, 0, 3))
    from solver.mesh import orient_positive

    nodes = box.p.T
    with pytest.raises(MeshError, match="endocardium"):
        make_mesh(nodes, orient_positive(nodes, box.t.T))


def test_fibre_frames_orthonormal_with_linear_helix(default_mesh):
    m = default_mesh
    phi = transmural_coordinate(m)
    assert np.all(phi[m.endo_nodes()] == 0) and np.all(phi[m.epi_nodes()] == 1)
    lam = cell_quadrature(m.nodes, m.tets, 2, 2).lam
    frames = fibre_frames(m, 60.0, -60.0, lam, phi)
    gram = np.einsum("eqia,eqib->eqab", frames, frames)
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-12)
    # helix angle: f · e_l = sin θ with θ linear in φ from +60° (endo) to −60° (epi)
    from solver.fibres import wall_directions

    t, el, ec = wall_directions(m, phi)
    phi_q = np.einsum("ea,aq->eq", phi[m.tets], lam)
    theta = np.deg2rad(60.0 - 120.0 * phi_q)
    np.testing.assert_allclose(np.einsum("eqi,ei->eq", frames[..., 0], el), np.sin(theta), atol=1e-12)
    np.testing.assert_allclose(np.einsum("eqi,ei->eq", frames[..., 1], t), 1.0, atol=1e-12)


def test_a_tet_with_no_transmural_gradient_takes_its_neighbours_direction(default_mesh):
    """All four nodes of a tet on one surface (φ equal at them: ∇φ = 0, e.g. one element across a
    thin wall) gave t = 0 and a fibre frame of zero vectors; now its neighbours' direction."""
    from solver.fibres import wall_directions

    m = default_mesh
    phi = transmural_coordinate(m)
    t_ref, _, _ = wall_directions(m, phi)
    flat = int(np.argmax(np.ptp(phi[m.tets], axis=1) < 1.0))  # any tet; make its φ constant
    phi[m.tets[flat]] = phi[m.tets[flat]].mean()
    t, el, ec = wall_directions(m, phi)
    for v in (t, el, ec):
        assert np.all(np.isfinite(v)) and np.allclose(np.linalg.norm(v, axis=1), 1.0)
    assert t[flat] @ t_ref[flat] > 0.9  # close to the direction it had with its own gradient


def test_closest_points_on_triangles_match_dense_sampling():
    """Every region of the triangle (interior, three edges, three vertices) against a dense
    barycentric sampling of the triangle."""
    from solver.fibres import closest_points_on_triangles

    rng = np.random.default_rng(3)
    a, b, c = np.array([0.0, 0, 0]), np.array([2.0, 0, 0]), np.array([0.5, 1.5, 0.3])
    pts = rng.normal(scale=2.0, size=(300, 3)) + np.array([0.8, 0.5, 0.0])
    got = closest_points_on_triangles(pts, *(np.broadcast_to(v, pts.shape) for v in (a, b, c)))
    s = np.linspace(0, 1, 241)
    u, v = np.meshgrid(s, s)
    keep = u + v <= 1
    samples = a + np.outer(u[keep], b - a) + np.outer(v[keep], c - a)
    brute = np.sqrt(((pts[:, None, :] - samples[None]) ** 2).sum(-1)).min(axis=1)
    np.testing.assert_allclose(np.linalg.norm(got - pts, axis=1), brute, atol=2e-2)
    assert np.all(np.linalg.norm(got - pts, axis=1) <= brute + 1e-12)


def test_surface_normal_is_continuous_where_two_faces_are_equidistant():
    """Inside a convex faceted surface (a wall point under the epicardium) the closest point jumps
    from one face to the other where the two are equidistant. The blended normal does not jump
    there (it did: 0.03 on a generated LV, and inverse FE with heartFEM's fibres stalled at ~1e-3 mm),
    and away from the tie it is the closest face's interpolated normal."""
    from solver.fibres import surface_distance

    # a roof over the point: two faces meeting at the ridge x = 0, wound so that their normals point up
    nodes = np.array([[0.0, -1, 0], [0.0, 1, 0], [-1.0, 0, -0.5], [1.0, 0, -0.5]])
    tris = np.array([[0, 1, 2], [1, 0, 3]])
    a, b, c = (nodes[tris][:, i] for i in range(3))
    assert np.all(np.cross(b - a, c - a)[:, 2] > 0)
    eps = 1e-7
    pts = np.array([[-eps, 0.0, -1.0], [eps, 0.0, -1.0], [-0.3, 0.0, -1.0]])
    d, n = surface_distance(pts, nodes, tris)
    assert abs(d[0] - d[1]) < 1e-6
    assert np.linalg.norm(n[0] - n[1]) < 1e-4  # continuous across the tie
    _, n_sharp = surface_distance(pts, nodes, tris, blend_mm=0.0)
    assert np.linalg.norm(n_sharp[0] - n_sharp[1]) > 1e-2  # the closest face alone jumps
    np.testing.assert_allclose(n[2], n_sharp[2], atol=1e-12)  # far from the tie: unchanged


def test_surface_clipped_at_the_base_is_cut_along_the_plane(default_mesh):
    """heartFEM's surfaces are cut 0.05 cm below the base as vtkClipPolyData cuts them: everything kept
    lies below the plane, each piece faces the way its triangle faced, the cut rim is one loop, a
    node on the plane is not duplicated, and the kept area and the fibre frames change continuously
    as the plane passes a node (dropping whole triangles by their centroids jumped)."""
    from scipy.sparse.csgraph import connected_components

    from solver.fibres import clip_below, heartfem_frames

    m = default_mesh

    def area(points, tris, *_):
        return 0.5 * np.linalg.norm(np.cross(points[tris[:, 1]] - points[tris[:, 0]],
                                             points[tris[:, 2]] - points[tris[:, 0]]), axis=1).sum()

    def face_normals(points, tris):
        return np.cross(points[tris[:, 1]] - points[tris[:, 0]], points[tris[:, 2]] - points[tris[:, 0]])

    total = area(m.nodes, m.epi)
    height = m.nodes[:, 2].max() - 0.5
    points, tris, interpolation = clip_below(m.nodes, m.epi, height)
    np.testing.assert_allclose(interpolation @ m.nodes, points)
    assert points[np.unique(tris), 2].max() <= height + 1e-12
    assert 0.95 * total < area(points, tris) < total
    # each piece lies in its parent triangle's plane and faces the same way (parent: nearest centroid)
    parents = np.linalg.norm(points[tris].mean(1)[:, None] - m.nodes[m.epi].mean(1)[None], axis=2).argmin(1)
    assert np.all((face_normals(points, tris) * face_normals(m.nodes, m.epi)[parents]).sum(1) > 0)
    edges, counts = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1),
                              axis=0, return_counts=True)
    rim = edges[counts == 1]
    assert counts.max() == 2 and np.all(np.bincount(rim.ravel())[np.unique(rim)] == 2)
    rim_nodes, local = np.unique(rim, return_inverse=True)
    graph = sp.coo_matrix((np.ones(len(rim)), (local.reshape(-1, 2)[:, 0], local.reshape(-1, 2)[:, 1])),
                          shape=(len(rim_nodes),) * 2)
    assert connected_components(graph, directed=False)[0] == 1  # one loop
    # a plane through an epicardial node: no duplicate point, and nothing jumps as it passes the node
    z = np.sort(m.nodes[np.unique(m.epi), 2])
    z_node = z[len(z) // 2]
    on, _, _ = clip_below(m.nodes, m.epi, z_node)
    assert len(np.unique(np.round(on, 9), axis=0)) == len(on)
    below, above = (area(*clip_below(m.nodes, m.epi, z_node + dz)) for dz in (-1e-9, 1e-9))
    assert 0 <= above - below < 1e-5 * total
    assert area(*clip_below(m.nodes, m.epi, m.nodes[:, 2].max() + 1.0)) == pytest.approx(total)
    lam = cell_quadrature(m.nodes, m.tets, 1, 2).lam
    top = m.nodes[:, 2].max()
    frames = [heartfem_frames(m, 60.0, -60.0, lam, clip_mm=top - z_node + dz) for dz in (-1e-9, 1e-9)]
    assert np.abs(frames[1] - frames[0]).max() < 1e-4


def test_heartfem_frames_orthonormal_and_transmural(default_mesh):
    """heartFEM's rule: orthonormal (f, s, n); s points endo → epi (away from the long axis on the
    free wall); helix angles stay within the endo/epi range and reach both signs; at points next
    to the endocardium the angle is near the endo value (squared-distance coordinate ≈ 0)."""
    from solver.fibres import heartfem_frames, surface_distance

    m = default_mesh
    lam = cell_quadrature(m.nodes, m.tets, 2, 4).lam
    frames = heartfem_frames(m, 60.0, -60.0, lam)
    gram = np.einsum("eqia,eqib->eqab", frames, frames)
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-10)
    x = np.einsum("eai,aq->eqi", m.nodes[m.tets], lam)
    radial = x[..., :2] / np.linalg.norm(x[..., :2], axis=-1, keepdims=True)
    mid = x[..., 2] > 0.5 * m.nodes[:, 2].min()  # upper half: the wall faces outwards
    assert np.mean((frames[..., :2, 1] * radial).sum(-1)[mid] > 0.5) > 0.95
    f, t = frames[..., 0], frames[..., 1]
    ec = np.cross(np.array([0.0, 0.0, 1.0]), t)
    ec /= np.linalg.norm(ec, axis=-1, keepdims=True)
    theta = np.degrees(np.arctan2((f * np.cross(t, ec)).sum(-1), (f * ec).sum(-1)))
    assert theta.min() >= -60.0 - 1e-6 and theta.max() <= 60.0 + 1e-6
    assert theta.min() < -30 and theta.max() > 30
    d_endo, _ = surface_distance(x.reshape(-1, 3), m.nodes, m.endo)
    d_epi, _ = surface_distance(x.reshape(-1, 3), m.nodes, m.epi)
    near_endo = (d_endo < 0.2 * d_epi).reshape(theta.shape)
    assert near_endo.any() and np.all(theta[near_endo] > 55.0)


@pytest.mark.parametrize("offset", [0, 5_000_000])
def test_face_keys_match_row_unique_for_small_and_huge_node_numbers(offset):
    """Triangles as node sets: the int64 key (and the row fallback past 2e6 nodes) group the same
    faces as np.unique over sorted rows."""
    from solver.mesh import _unique_faces

    rng = np.random.default_rng(0)
    faces = rng.integers(0, 40, size=(500, 3)) + offset
    faces = np.concatenate([faces, faces[:200, ::-1]])  # the same triangles in another order
    _, want_idx, want_inv, want_cnt = np.unique(np.sort(faces, axis=1), axis=0, return_index=True,
                                                return_inverse=True, return_counts=True)
    idx, inv, cnt = _unique_faces(faces, return_index=True, return_inverse=True, return_counts=True)
    np.testing.assert_array_equal(idx, want_idx)
    np.testing.assert_array_equal(inv.ravel(), want_inv.ravel())
    np.testing.assert_array_equal(cnt, want_cnt)
