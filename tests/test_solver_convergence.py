"""Uniform refinement, the fibre field's order, convergence under refinement, the reference preset
and the Richardson arithmetic of `heartctl bench convergence`."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from orchestrator.tasks import run_chain
from bench.convergence_report import markdown_report
from bench.convergence import (CASES, ConvergenceSpec, Hierarchy, convergence_shape, nodal_error,
                                observed_order, parse_hierarchies, richardson_error, run_convergence, unload_at_level)
from solver.elements import quadrature_barycentric
from solver.fidelity import get_fidelity
from solver.fibres import fibre_frames
from solver.lv import forward_solve, inverse_solve
from solver.mesh import boundary_facets, scaled_jacobian, signed_tet_volumes
from solver.meshing import mesh_lv, mesh_truncated_ellipsoid
from solver.refine import prolongate, refine_uniform


@pytest.fixture(scope="module")
def tiny():
    return mesh_lv(convergence_shape("mean"), 50)


@pytest.fixture(scope="module")
def one_level():
    """bench convergence on the tiny mesh (86 nodes) refined once, both presets (accurate's refined answer is
    the reference)."""
    return run_convergence(ConvergenceSpec(("mean",), ("mid",), (Hierarchy(50, 1),), quad_degrees=()))


def _area(nodes, tris):
    p = nodes[tris]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()


def test_refinement_keeps_the_vertices_the_domain_and_the_surfaces(tiny):
    fine = refine_uniform(tiny, 2)
    assert np.array_equal(fine.nodes[: tiny.n_nodes], tiny.nodes)
    assert len(fine.tets) == 64 * len(tiny.tets)
    vol = signed_tet_volumes(fine.nodes, fine.tets)
    assert vol.min() > 0
    assert vol.sum() == pytest.approx(signed_tet_volumes(tiny.nodes, tiny.tets).sum(), rel=1e-12)
    # red refinement along the shortest diagonal keeps the elements' quality bounded
    assert scaled_jacobian(fine.nodes, fine.tets).min() > 0.5 * scaled_jacobian(tiny.nodes, tiny.tets).min()
    for name in ("endo", "epi", "base"):
        coarse_tris, fine_tris = getattr(tiny, name), getattr(fine, name)
        assert len(fine_tris) == 16 * len(coarse_tris)
        assert _area(fine.nodes, fine_tris) == pytest.approx(_area(tiny.nodes, coarse_tris), rel=1e-12)
    assert len(boundary_facets(fine.tets)) == len(fine.endo) + len(fine.epi) + len(fine.base)
    with pytest.raises(ValueError, match="levels"):
        refine_uniform(tiny, -1)


def test_prolongation_reproduces_linear_fields(tiny):
    fine = refine_uniform(tiny, 2)
    assert np.allclose(prolongate(tiny.nodes, tiny, 2), fine.nodes, atol=1e-12)
    field = tiny.nodes @ np.array([0.3, -1.2, 2.0]) + 5.0
    assert np.allclose(prolongate(field, tiny, 2), fine.nodes @ np.array([0.3, -1.2, 2.0]) + 5.0)


def test_p2_fibres_follow_the_wall_an_order_better_than_p1():
    """On a hemispherical shell (base through the centre) the transmural direction is radial. The
    P2 field's t at the quadrature points is much closer to it than the P1 field's per-tet t, and its
    error shrinks faster under refinement (what the accurate preset's apex needed)."""
    shell = mesh_truncated_ellipsoid((20.0, 20.0, 20.0), (30.0, 30.0, 30.0), 0.0, 0.0, 300)
    lam = quadrature_barycentric(2)
    errors = {}
    for level in (0, 1):
        m = refine_uniform(shell, level)
        x = np.einsum("eai,aq->eqi", m.nodes[m.tets], lam)
        radial = x / np.linalg.norm(x, axis=2, keepdims=True)
        for order in (1, 2):
            t = fibre_frames(m, 60.0, -60.0, lam, order=order)[..., 1]
            errors[order, level] = np.degrees(np.arccos(np.clip((t * radial).sum(axis=2), -1, 1))).mean()
    assert errors[2, 0] < 0.7 * errors[1, 0]  # 2.9° against 5.1° on 276 nodes
    assert errors[2, 1] < 0.6 * errors[1, 1]  # 1.3° against 3.8° on 1,635
    assert errors[2, 0] / errors[2, 1] > errors[1, 0] / errors[1, 1]


@pytest.mark.slow
def test_the_quadrature_study_scores_each_degree_against_the_highest():
    """bench convergence's quadrature study (accurate on the 86-node LV and its refinement): the
    highest cell degree is the quadrature reference, degree 2's error shrinks under refinement
    (0.079 → 0.016 mm mean) and is over 10× the preset's degree 5's, the facet degree barely moves
    the answer, and the refined answer at the preset's degrees is the convergence reference."""
    result = run_convergence(ConvergenceSpec(("mean",), ("mid",), (Hierarchy(50, 1),), presets=("accurate",),
                                             quad_degrees=(2, 7)))
    rows = {(r.quad_degree, r.facet_quad_degree, r.level): r for r in result.quadrature}
    own = get_fidelity("accurate")
    assert set(rows) == {(q, f, level) for level in (0, 1)
                         for q, f in ((2, own.facet_quad_degree), (own.quad_degree, own.facet_quad_degree),
                                      (7, own.facet_quad_degree), (own.quad_degree, 7))}
    assert not any(r.failed for r in rows.values())
    err = {k: r.quadrature["mean_mm"] for k, r in rows.items()}
    f = own.facet_quad_degree
    assert err[7, f, 0] == err[7, f, 1] == 0.0
    assert err[2, f, 1] < 0.5 * err[2, f, 0]
    assert err[own.quad_degree, f, 0] < 0.1 * err[2, f, 0]
    assert abs(err[own.quad_degree, 7, 0] - err[own.quad_degree, f, 0]) < 0.01
    assert rows[own.quad_degree, f, 1].converged is None and rows[own.quad_degree, f, 1].is_preset
    assert rows[2, f, 1].converged["mean_mm"] == pytest.approx(err[2, f, 1], rel=0.2)
    assert "## Convergence in quadrature" in markdown_report(result)


@pytest.mark.slow
def test_unloading_converges_under_refinement_at_the_expected_rate(tiny, one_level):
    """fast (P1/P1) on a tiny LV and its two refinements: the nodal differences of consecutive levels
    shrink at an observed order of 1–2.5 (P1: 2 for a smooth solution; the apical fibre vortex and
    the faceted wall lower it), and accurate (P2/P1) moves less than fast under refinement of the
    same mesh (0.12 mm against 0.21 mm on 86 nodes)."""
    fast, accurate = (next(o for o in one_level.orders if o.preset == p) for p in ("fast", "accurate"))
    assert accurate.level_diffs_mean_mm[0] < 0.75 * fast.level_diffs_mean_mm[0]
    levels = [unload_at_level(tiny, CASES["mid"], "fast", level) for level in (0, 1, 2)]
    diffs = [nodal_error(a.unloaded, b.unloaded, tiny.nodes)["mean_mm"] for a, b in zip(levels[:-1], levels[1:])]
    order = observed_order(*diffs)
    assert 1.0 <= order <= 2.5, diffs


def test_observed_order_and_richardson_on_a_known_sequence():
    # u_h = u* + c h²: differences 0.75 c h0², 0.1875 c h0² → p = 2, finest error c (h0/4)² = d_top / 3
    d01, d12 = 0.75, 0.1875
    assert observed_order(d01, d12) == pytest.approx(2.0)
    assert richardson_error(d12, 2.0) == pytest.approx(0.0625)
    assert np.isnan(observed_order(0.0, 0.1)) and np.isnan(richardson_error(0.1, -0.5))


def test_nodal_error_regions():
    nodes = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -5.0], [0.0, 0.0, -10.0]])
    err = nodal_error(nodes + [[0.1, 0, 0], [0.2, 0, 0], [0.4, 0, 0]], nodes, nodes)
    assert err["max_mm"] == pytest.approx(0.4) and err["mean_mm"] == pytest.approx(0.7 / 3)
    assert err["apex_mean_mm"] == pytest.approx(0.4) and err["base_mean_mm"] == pytest.approx(0.1)


def test_mesh_hierarchies_parse_and_bad_ones_are_refused():
    assert parse_hierarchies("150:2,800:1") == (Hierarchy(150, 2), Hierarchy(800, 1))
    for text in ("150", "a:1", "150:2:1"):
        with pytest.raises(ValueError, match="NODES:LEVELS"):
            parse_hierarchies(text)
    with pytest.raises(ValueError, match="refinement level"):
        ConvergenceSpec(hierarchies=(Hierarchy(150, 0),)).validate()
    with pytest.raises(ValueError, match="unknown case"):
        ConvergenceSpec(cases=("easy",)).validate()
    with pytest.raises(ValueError, match="unknown convergence shape"):
        ConvergenceSpec(shapes=("round",)).validate()


@pytest.fixture(scope="module")
def reference_chain(tiny):
    """Two `reference` pairs in a pressure chain, as `generate` solves them: the mid case, then 12 mmHg."""
    mid = CASES["mid"]
    return run_chain(tiny, [mid, replace(mid, pressure_mmhg=12.0)], "reference")


@pytest.mark.slow
def test_the_reference_preset_answers_the_refined_solve_at_the_ed_nodes(tiny, one_level, reference_chain):
    params = CASES["mid"]
    pair = reference_chain[0]  # the chain's first pair, solved cold
    assert pair["ok"] and pair["unloaded"].shape == tiny.nodes.shape
    assert np.linalg.norm(pair["loaded"] - tiny.nodes, axis=1).max() < 1e-3
    # accurate on the mesh as given is as far from it as from the inverse on the refined mesh that
    # bench convergence solved (one_level: accurate's level-1 answer is its reference): the pair is
    # that refined solve, at the ED nodes
    coarse = inverse_solve(tiny, params, "accurate")
    gap = nodal_error(coarse.unloaded_nodes, pair["unloaded"], tiny.nodes)
    level0 = next(r for r in one_level.rows if r.preset == "accurate" and r.level == 0)
    assert gap["mean_mm"] > 0.01  # the mesh's own discretisation error
    assert abs(gap["mean_mm"] - level0.error["mean_mm"]) < 2e-3 and abs(gap["max_mm"] - level0.error["max_mm"]) < 5e-3
    fwd = forward_solve(tiny.with_nodes(pair["unloaded"]), params, "reference")
    assert fwd.loaded_nodes.shape == tiny.nodes.shape
    inv = inverse_solve(tiny, params, "reference", initial_unloaded=coarse.unloaded_nodes)
    assert np.abs(inv.unloaded_nodes - pair["unloaded"]).max() < 1e-3
    with pytest.raises(ValueError, match="one point per ED node"):
        inverse_solve(tiny, params, "reference", initial_unloaded=coarse.unloaded_nodes[:-1])


@pytest.mark.slow
def test_a_reference_chain_solves_on_one_refined_mesh_from_its_own_refined_pairs(reference_chain):
    """A refined preset's chain keeps one workspace on the refined mesh: the second pair's inverse
    starts from the refined pair before it (no coarse solve) and meets the preset's tolerance (the
    inverse's answer is the one geometry that inflates onto x_ED)."""
    first, second = reference_chain
    tol = get_fidelity("reference").inverse_tol_mm
    assert second["ok"] and [r["attempts"] for r in reference_chain] == [1, 1]
    assert second["warm_start"] and second["stats"]["guess_wall_s"] < 0.1 * first["stats"]["guess_wall_s"]
    assert second["stats"]["inverse_mismatch_mm"] <= tol and second["stats"]["roundtrip_error_mm"] < 10 * tol


@pytest.mark.slow
def test_the_report_names_its_reference(one_level):
    text = markdown_report(one_level, "# title")
    written = one_level.as_dict()
    assert written["rows"][0]["mean_mm"] == one_level.rows[0].error["mean_mm"] and written["quadrature"] == []
    assert "error" not in written["rows"][0]  # the figures are flattened beside the row's fields, not nested
    assert "Reference: `accurate` on the hierarchy's finest mesh" in text
    assert "| mean | mid | 50-node | accurate | 1 |" in text and "† | reference |" in text
