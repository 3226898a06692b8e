"""Local refinement, the error indicator, the surface gauge and the adaptive unload: a conforming
closure, the indicator exact where the element is, the sliding base's rigid motion fixed the same way on
any mesh of the base, and an adaptive answer nearer the converged one than the mesh it started from."""
import numpy as np
import pytest

from solver.adaptive import LOOSEST_SOLVE_TOL_MM, adaptive_unload
from solver.assembly import _surface_moments
from solver.elements import build_dofmap
from solver.error_indicator import bulk_marking, gradient_indicator
from solver.local_refine import FACE_EDGES, close_split_edges, refine_marked
from solver.lv import displacement_at_dofs, forward_solve, inverse_solve
from solver.mesh import boundary_facets, signed_tet_volumes
from solver.meshing import mesh_lv
from solver.parameters import CaseParameters
from solver.refine import refine_uniform
from solver.shape_model import lv_shape

MID = CaseParameters(8.0, 150.0, 60.0, -60.0)


@pytest.fixture(scope="module")
def lv():
    return mesh_lv(lv_shape(0, 0, 2), 150)


@pytest.mark.parametrize("fraction", [0.02, 0.1, 0.3])
def test_local_refinement_conforms_and_fills_the_same_domain(lv, fraction):
    marked = np.random.default_rng(3).random(len(lv.tets)) < fraction
    r = refine_marked(lv, marked)
    fine = r.mesh
    assert r.refined[marked].all()
    # conforming: every boundary triangle of the refined mesh is a tagged surface triangle (a hanging
    # face would show as an untagged inner boundary)
    assert len(boundary_facets(fine.tets)) == len(fine.endo) + len(fine.epi) + len(fine.base)
    # each ED tet is filled exactly by its children; the original vertices keep their numbers
    np.testing.assert_allclose(np.bincount(r.parent, weights=signed_tet_volumes(fine.nodes, fine.tets)),
                               signed_tet_volumes(lv.nodes, lv.tets), rtol=1e-12)
    np.testing.assert_array_equal(fine.nodes[: lv.n_nodes], lv.nodes)
    # its nodes are the uniformly refined mesh's
    np.testing.assert_array_equal(refine_uniform(lv, 1).nodes[r.fine_ids], fine.nodes)


def test_marking_every_tet_is_the_uniform_refinement(lv):
    r = refine_marked(lv, np.arange(len(lv.tets)))
    uniform = refine_uniform(lv, 1)
    ids = r.fine_ids
    assert {tuple(sorted(ids[t])) for t in r.mesh.tets} == {tuple(sorted(t)) for t in uniform.tets}
    none = refine_marked(lv, np.zeros(len(lv.tets), dtype=bool))
    np.testing.assert_array_equal(none.mesh.tets, lv.tets)


def test_closure_leaves_only_patterns_with_a_template(lv):
    dofmap = build_dofmap(lv.nodes, lv.tets, 2)
    tet_edges = dofmap.cell_dofs[:, 4:] - lv.n_nodes
    split = np.random.default_rng(0).random(len(dofmap.edge_vertices)) < 0.05
    closed = close_split_edges(tet_edges, split)
    assert closed[split].all()
    s = closed[tet_edges]
    assert not np.any(s[:, FACE_EDGES].sum(axis=2) == 2)
    assert set(np.unique(s.sum(axis=1))) <= {0, 1, 2, 3, 6}


def test_bad_marks_are_refused(lv):
    with pytest.raises(ValueError, match="marked"):
        refine_marked(lv, [len(lv.tets)])
    with pytest.raises(ValueError, match="one flag per tet"):
        refine_marked(lv, np.ones(3, dtype=bool))


def test_indicator_vanishes_where_the_element_is_exact(lv):
    """η_K = ‖G* − ∇u_h‖ is zero for a field the element reproduces (linear for P1, quadratic for P2)
    and not for a quadratic field on P1."""
    X = lv.nodes
    p2 = build_dofmap(X, lv.tets, 2).points
    A = np.array([[0.01, 0.02, -0.01], [0.0, 0.03, 0.01], [0.02, -0.01, 0.0]])

    def quadratic(x):
        return x @ A.T + 1e-3 * np.stack([x[:, 0] * x[:, 1], x[:, 2] ** 2, x[:, 0] ** 2], axis=1)

    assert gradient_indicator(X, lv.tets, X @ A.T).max() < 1e-12
    assert gradient_indicator(X, lv.tets, p2 @ A.T).max() < 1e-12
    assert gradient_indicator(X, lv.tets, quadratic(p2)).max() < 1e-9
    assert gradient_indicator(X, lv.tets, quadratic(X)).max() > 1e-2
    with pytest.raises(ValueError, match="displacement"):
        gradient_indicator(X, lv.tets, np.zeros((5, 3)))


def test_bulk_marking_takes_the_fewest_largest():
    eta = np.array([1.0, 3.0, 2.0, 0.5])
    np.testing.assert_array_equal(bulk_marking(eta, 0.6), [False, True, False, False])  # 9 of 14.25
    np.testing.assert_array_equal(bulk_marking(eta, 0.7), [False, True, True, False])
    np.testing.assert_array_equal(bulk_marking(eta, 0.9, eligible=[True, False, True, True]),
                                  [True, False, True, False])
    with pytest.raises(ValueError):
        bulk_marking(eta, 0.0)


def test_sliding_gauge_is_the_base_surfaces_on_any_mesh(lv):
    """The sliding base's in-plane rigid motion is fixed by ∫u_x dA = ∫u_y dA = ∫(X − X̄) × u · e_z dA = 0
    over the base: true of the solution on a mesh refined only near the base, whose base dofs are spread
    unevenly (a mean over dofs would place it differently)."""
    near_base = np.isin(lv.tets, lv.base_nodes()).any(axis=1)
    fine = refine_marked(lv, near_base).mesh
    result = forward_solve(fine, MID, "accurate")
    dofmap = build_dofmap(fine.nodes, fine.tets, 2)
    w, m = _surface_moments(dofmap, fine.base)
    u = result.state[: 3 * dofmap.n_dofs].reshape(-1, 3)
    area, centroid = w.sum(), m.sum(axis=0) / w.sum()
    # the weights themselves, against the triangles' areas and area-weighted centroid
    corners = fine.nodes[fine.base]
    tri = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    assert area == pytest.approx(tri.sum(), rel=1e-12)
    np.testing.assert_allclose(centroid, (tri[:, None] * corners.mean(axis=1)).sum(axis=0) / tri.sum(), atol=1e-9)
    scale = np.abs(u).max() * area
    assert abs(w @ u[:, 0]) < 1e-8 * scale and abs(w @ u[:, 1]) < 1e-8 * scale
    moment = (m[:, 0] - w * centroid[0]) @ u[:, 1] - (m[:, 1] - w * centroid[1]) @ u[:, 0]
    assert abs(moment) < 1e-8 * scale * 30.0


@pytest.mark.slow
def test_adaptive_unload_is_nearer_the_converged_answer(lv):
    """From `accurate` on the mesh, each refinement where η is largest; the answer at the ED mesh's
    vertices is nearer `reference` (the converged solution on this mesh) than `accurate`'s, and its
    estimate says whether the tolerance was met."""
    reference = inverse_solve(lv, MID, "reference").unloaded_nodes
    accurate = inverse_solve(lv, MID, "accurate")
    err = lambda X: np.linalg.norm(X - reference, axis=1).mean()  # noqa: E731
    result = adaptive_unload(lv, MID, tolerance_mm=1e-6, max_steps=2)
    assert not result.met and len(result.steps) == 3
    assert result.unloaded_nodes.shape == lv.nodes.shape
    assert result.steps[2].split_tets > result.steps[1].split_tets > 0
    assert err(result.unloaded_nodes) < 0.8 * err(accurate.unloaded_nodes)
    assert np.all(np.isfinite(result.estimated_error_mm))
    assert result.mismatch_mm <= 1e-4
    eta = gradient_indicator(accurate.unloaded_nodes, lv.tets, displacement_at_dofs(accurate))
    np.testing.assert_allclose(result.first_indicator, eta, rtol=1e-6)
    loose = adaptive_unload(lv, MID, tolerance_mm=10.0)
    assert loose.met and len(loose.steps) == 2
    assert loose.mismatch_mm <= LOOSEST_SOLVE_TOL_MM  # each solve to 2 % of the tolerance, at most 1e-3 mm
    with pytest.raises(ValueError, match="tolerance_mm"):
        adaptive_unload(lv, MID, tolerance_mm=float("nan"))


@pytest.mark.slow
def test_bench_adaptive_scores_the_indicator_and_each_tolerance_against_the_refined_solve(tmp_path):
    """`bench adaptive` on one small case: the indicator ranks the true local error better than chance,
    a loose tolerance is met after the first estimate's refinement, a tighter one refines at least as far
    and lands nearer the reference than `accurate`,
    and the report's JSON holds every figure."""
    import json

    from bench.adaptive import AdaptiveSpec, run_adaptive, write_report

    result = run_adaptive(AdaptiveSpec(cases=("mid",), nodes=150, tolerances=(5.0, 0.02)))
    (case,) = result.rows
    assert case.reference_nodes > case.nodes and case.reference_s > 0
    assert 0.0 < case.ranking.spearman <= 1.0 and case.ranking.top_share <= case.ranking.best_share + 1e-12
    loose, tight = case.adaptive
    assert loose.met and len(loose.steps) <= 2 and len(tight.steps) >= len(loose.steps)
    assert tight.error["mean_mm"] < case.accurate_error["mean_mm"]
    paths = write_report(result, tmp_path, "# adaptive")
    written = json.loads(paths["json"].read_text())
    assert written["rows"][0]["adaptive"][1]["mean_mm"] == tight.error["mean_mm"]
    assert "| mean | mid |" in paths["markdown"].read_text()
