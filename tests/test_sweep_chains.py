"""Pressure chains: the sweep's tasks group the cases of a shape that differ only in pressure, and
each inverse starts from the unloaded geometry extrapolated from the chain's lower pressures. The
warm start must change the cost, never the answer (beyond the inverse tolerance). No Ray here."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from orchestrator.grid import SweepSpec, pressure_chains
from orchestrator.tasks import mesh_shape, run_case, run_chain
from solver.fidelity import get_fidelity
from solver.lv import unloaded_guess

CHAIN = [(6.0, 100.0, 60.0, -60.0), (10.0, 100.0, 60.0, -60.0), (14.0, 100.0, 60.0, -60.0)]


@pytest.fixture(scope="module")
def mesh():
    return mesh_shape(0, 0, 200)["mesh"]


@pytest.fixture(scope="module")
def warm_and_cold(mesh):
    warm = run_chain(mesh, CHAIN, "fast")
    cold = [run_case(mesh, p, "fast") for p in CHAIN]
    return warm, cold


def test_guess_is_the_last_geometry_then_the_line_through_the_last_two():
    x4, x8 = np.full((5, 3), 1.0), np.full((5, 3), 3.0)
    assert unloaded_guess([], 8.0) is None
    np.testing.assert_array_equal(unloaded_guess([(4.0, x4)], 8.0), x4)
    np.testing.assert_allclose(unloaded_guess([(4.0, x4), (8.0, x8)], 12.0), 5.0)  # 3 + (3 − 1)·4/4
    np.testing.assert_allclose(unloaded_guess([(4.0, x4), (8.0, x8)], 6.0), 2.0)
    np.testing.assert_array_equal(unloaded_guess([(8.0, x4), (8.0, x8)], 12.0), x8)  # no slope from one P


def test_chains_share_stiffness_and_angles_rise_in_pressure_and_cover_every_case_once():
    spec = SweepSpec(shapes=1, pressure_mmhg=(14.0, 4.0, 8.0), stiffness_pa=(50.0, 300.0), helix_endo_deg=(60.0, 70.0),
                     helix_epi_deg=(-60.0,), fidelity="fast", nodes=200)
    params = spec.case_params()
    ks = [k for k in range(spec.cases_per_shape) if k != 5]  # one case already done
    chains = pressure_chains(params, ks)
    assert sorted(k for c in chains for k in c) == ks
    assert len(chains) == 4  # 2 C × 2 θendo
    for chain in chains:
        assert len({tuple(params[k, 1:]) for k in chain}) == 1
        assert np.all(np.diff(params[chain, 0]) > 0)
    short = pressure_chains(params, ks, max_len=2)
    assert max(len(c) for c in short) == 2 and sorted(k for c in short for k in c) == ks
    assert pressure_chains(params, []) == []


def test_warm_started_chain_gives_the_cold_pairs_in_fewer_iterations(warm_and_cold):
    warm, cold = warm_and_cold
    tol = get_fidelity("fast").inverse_tol_mm
    assert [r["ok"] for r in warm] == [True] * 3 and [r["ok"] for r in cold] == [True] * 3
    assert [r["warm_start"] for r in warm] == [False, True, True]
    assert [r["attempts"] for r in warm] == [1, 1, 1]
    np.testing.assert_array_equal(warm[0]["unloaded"], cold[0]["unloaded"])  # the first case starts cold
    for w, c in zip(warm[1:], cold[1:]):
        # both inverses stop within tol of x_ED, so their unloaded geometries differ by about tol
        assert np.linalg.norm(w["unloaded"] - c["unloaded"], axis=1).max() < 5 * tol
        assert np.linalg.norm(w["loaded"] - c["loaded"], axis=1).max() < 5 * tol
        assert w["stats"]["roundtrip_error_mm"] < 10 * tol
    it = lambda rs: sum(r["stats"]["inverse_newton_iterations"] for r in rs[1:])  # noqa: E731
    assert it(warm) < 0.6 * it(cold), (it(warm), it(cold))


def test_chain_without_warm_start_is_the_cold_solve(mesh, warm_and_cold):
    _, cold = warm_and_cold
    plain = run_chain(mesh, CHAIN[:2], "fast", warm_start=False)
    assert [r["warm_start"] for r in plain] == [False, False]
    for p, c in zip(plain, cold):
        np.testing.assert_array_equal(p["unloaded"], c["unloaded"])


def test_a_failed_case_does_not_feed_the_next_guess_and_a_folded_guess_is_dropped(mesh, monkeypatch):
    import solver.lv

    chain = [(8.0, 100.0, 60.0, -60.0), (1e5, 100.0, 60.0, -60.0), (12.0, 100.0, 60.0, -60.0)]
    seen = []
    real = solver.lv.unloaded_guess

    def spy(solved, pressure):
        seen.append([p for p, _ in solved])
        return real(solved, pressure)

    monkeypatch.setattr(solver.lv, "unloaded_guess", spy)
    res = run_chain(mesh, chain, "fast")
    assert [r["ok"] for r in res] == [True, False, True]
    assert seen == [[], [8.0], [8.0]]  # the failed 1e5 mmHg case is not extrapolated from

    def folding(solved, pressure):
        x = mesh.nodes.copy()
        x[mesh.tets[0, 0]] = x[mesh.tets[0, 1:]].mean(axis=0) * 3 - 2 * x[mesh.tets[0, 0]]  # flip a corner through
        return x if solved else None

    monkeypatch.setattr(solver.lv, "unloaded_guess", folding)
    res = run_chain(mesh, chain[::2], "fast")
    assert [r["ok"] for r in res] == [True, True] and [r["warm_start"] for r in res] == [False, False]
    assert res[1]["attempts"] == 1


def test_an_unexpected_error_fails_its_case_only(mesh, monkeypatch):
    """A linear solver's own exception (SciPy's "Factor is exactly singular", a PyPardisoError) is
    that case's failure, with its type and reason, after the robust retry; the chain's other cases
    keep their results (before, the whole task raised and every case of the chain was lost)."""
    import solver.lv

    real = solver.lv.make_pair
    calls = []

    def singular_at_10(mesh_, params, *args, **kwargs):
        calls.append(params.pressure_mmhg)
        if params.pressure_mmhg == 10.0:
            raise RuntimeError("Factor is exactly singular")
        return real(mesh_, params, *args, **kwargs)

    monkeypatch.setattr(solver.lv, "make_pair", singular_at_10)
    res = run_chain(mesh, CHAIN, "fast")
    assert [r["ok"] for r in res] == [True, False, True]
    assert res[1]["reason"] == "RuntimeError: Factor is exactly singular" and res[1]["attempts"] == 2
    assert calls == [6.0, 10.0, 10.0, 14.0]
    with pytest.raises(MemoryError):  # the worker's trouble: raised, and the driver leaves the chain pending
        monkeypatch.setattr(solver.lv, "make_pair", lambda *a, **k: (_ for _ in ()).throw(MemoryError()))
        run_case(mesh, CHAIN[0], "fast")


def test_an_inverse_that_gives_out_is_not_retried_and_ends_its_chain(mesh, monkeypatch):
    """A stalled or folding inverse from the ED mesh is not retried (smaller load steps repeat its updates),
    and the chain's higher pressures are recorded as failed with the reason, unsolved; a forward solve's
    failure is still retried and the chain goes on."""
    import solver.lv
    from solver.forward import SolveError
    from solver.inverse_failure import InverseError

    real, calls = solver.lv.make_pair, []

    def failing_at(pressure, error):
        def make_pair(mesh_, params, *args, **kwargs):
            calls.append(params.pressure_mmhg)
            if params.pressure_mmhg == pressure:
                raise error
            return real(mesh_, params, *args, **kwargs)
        return make_pair

    monkeypatch.setattr(solver.lv, "make_pair", failing_at(6.0, InverseError("inverse FE stalled: … largest at 3 %")))
    res = run_chain(mesh, CHAIN, "fast")
    assert [r["ok"] for r in res] == [False, False, False] and calls == [6.0]
    assert res[0]["attempts"] == 1 and res[0]["reason"].startswith("inverse FE stalled")
    assert [r["attempts"] for r in res[1:]] == [0, 0]
    assert res[2]["reason"].startswith("not solved: the inverse failed at 6 mmHg") and "stalled" in res[2]["reason"]

    calls.clear()
    monkeypatch.setattr(solver.lv, "make_pair", failing_at(10.0, SolveError("step size collapsed at 40 % of load")))
    res = run_chain(mesh, CHAIN, "fast")
    assert [r["ok"] for r in res] == [True, False, True] and calls == [6.0, 10.0, 10.0, 14.0]
    assert res[1]["attempts"] == 2 and not res[1]["inverse_failed"]


def test_in_flight_limit_follows_the_cluster_as_nodes_join():
    from orchestrator.pacing import InFlightLimit

    now, cpus = [0.0], [0.0]  # an autoscaling cluster: a head with no CPUs
    limit = InFlightLimit(None, lambda: cpus[0], every_s=5.0, clock=lambda: now[0])
    assert limit.current() == 2  # enough waiting tasks for the autoscaler to start a node
    cpus[0] = 32.0
    assert limit.current() == 2  # read again only every 5 s
    now[0] = 5.0
    assert limit.current() == 64 and limit.cpus_seen == 32.0
    cpus[0], now[0] = 8.0, 11.0  # nodes leave: the limit follows down
    assert limit.current() == 16 and limit.cpus_seen == 32.0
    fixed = InFlightLimit(3, lambda: 1 / 0)  # --max-in-flight: the cluster is never asked
    assert fixed.current() == 3


def test_a_case_lost_with_its_worker_is_pending_then_failed_after_three_runs(tmp_path):
    import ray

    from orchestrator.sweep import MAX_LOSSES, _failed_task_results
    from storage.writer import PairStore

    spec = SweepSpec(shapes=1, pressure_mmhg=(8.0, 12.0), stiffness_pa=(100.0,), helix_endo_deg=(60.0,),
                     helix_epi_deg=(-60.0,), fidelity="fast", nodes=200)
    store = PairStore.create(str(tmp_path / "s.zarr"), spec.store_attrs())
    shape = mesh_shape(0, 0, 200)
    m = shape["mesh"]
    store.write_shape(0, m.nodes, m.tets, m.endo, m.epi, m.base, shape["coefficients"], shape["info"])
    crash = ray.exceptions.WorkerCrashedError()
    for run in range(1, MAX_LOSSES):
        assert _failed_task_results(store, 0, [0, 1], crash) == [None, None]  # pending: a rerun solves them
    results = _failed_task_results(store, 0, [0, 1], crash)
    assert all(not r["ok"] and f"lost with its worker in {MAX_LOSSES} runs" in r["reason"] for r in results)
    store.flush()
    assert PairStore.open(store.location).table(0).losses == {"0": MAX_LOSSES, "1": MAX_LOSSES}  # kept over runs
    own = ray.exceptions.RayTaskError("run_chain", "Traceback …", KeyError("params"))
    assert _failed_task_results(store, 0, [1], own)[0]["reason"] == "task error: KeyError: 'params'"


def test_which_task_failures_leave_their_cases_pending():
    """A worker or node lost after Ray's retries, or a task out of memory: the cases stay pending
    for the next run. An error of the task's own code fails them, with its reason."""
    import ray

    from orchestrator.sweep import _error_line, _lost_to_infrastructure

    assert _lost_to_infrastructure(ray.exceptions.WorkerCrashedError())
    assert _lost_to_infrastructure(ray.exceptions.RayTaskError("run_chain", "Traceback …", MemoryError()))
    own = ray.exceptions.RayTaskError("run_chain", "Traceback …", KeyError("params"))
    assert not _lost_to_infrastructure(own)
    assert _error_line(own) == "KeyError: 'params'"


def test_a_workspace_builds_one_problem_and_one_analysis_and_changes_no_answer(mesh):
    """Pairs solved through one PairWorkspace (as a chain's are) reuse its FE problem and PARDISO's
    analysis, and land on the same unloaded geometry as pairs that build their own."""
    from solver.lv import PairWorkspace, make_pair
    from solver.parameters import CaseParameters

    cases = [CaseParameters(*c) for c in CHAIN[:2]] + [CaseParameters(8.0, 100.0, 70.0, -70.0)]
    with PairWorkspace(mesh) as workspace:
        shared = [make_pair(mesh, p, "fast", workspace=workspace) for p in cases]
        analysis = workspace.linsolve._pattern_key
        assert len(workspace._problems) == 1  # same preset, base, fibres and C: one problem
        other = workspace.problem(mesh, CaseParameters(8.0, 300.0, 60.0, -60.0), get_fidelity("fast"),
                                  "sliding", "laplace")
        assert len(workspace._problems) == 2 and other is not shared[0].inverse.problem
        with pytest.raises(ValueError, match="topology"):
            workspace.problem(replace(mesh, tets=mesh.tets[::-1].copy()), cases[0], get_fidelity("fast"),
                              "sliding", "laplace")
    assert all(pair.inverse.problem is shared[0].inverse.problem for pair in shared)
    assert workspace.linsolve.backend != "pardiso" or analysis is not None  # one analysis, kept
    assert workspace.linsolve._pardiso is None and not workspace.linsolve.has_factor  # freed on leaving
    for pair, params in zip(shared, cases):
        alone = make_pair(mesh, params, "fast")
        assert np.abs(pair.unloaded_nodes - alone.unloaded_nodes).max() < 1e-9
        assert np.abs(pair.loaded_nodes - alone.loaded_nodes).max() < 1e-9


@pytest.mark.slow
def test_an_accurate_chain_starts_from_its_neighbours_loaded_states(mesh, monkeypatch):
    """Each `accurate` inverse of a chain starts from the loaded states of the pairs before it,
    extrapolated to its pressure (edge midpoints and pressure field included), on the factorisation
    the workspace holds: the same unloaded geometries to the inverse tolerance with fewer
    factorisations than a start from straight edges and a zero pressure field. A remembered pair's
    own pressure gives back its state."""
    from solver.lv import PairWorkspace, make_pair, unloaded_guess
    from solver.parameters import CaseParameters

    def chain(use_states: bool):
        pairs, solved = [], []
        with PairWorkspace(mesh) as workspace:
            if not use_states:
                monkeypatch.setattr(workspace, "loaded_guess", lambda *args: None)
            for c in CHAIN:
                params = CaseParameters(*c)
                pair = make_pair(mesh, params, "accurate", initial_unloaded=unloaded_guess(solved, c[0]),
                                 workspace=workspace)
                pairs.append(pair)
                solved.append((c[0], pair.unloaded_nodes))
            if use_states:
                last = pairs[-1]
                z = workspace.loaded_guess(last.inverse.problem, CHAIN[-1][0], mesh.nodes)
                np.testing.assert_allclose(z, last.forward.state, rtol=0, atol=2 * tol)
            return pairs, workspace.linsolve.factorizations

    tol = get_fidelity("accurate").inverse_tol_mm
    warm, warm_factorizations = chain(True)
    plain, plain_factorizations = chain(False)
    for w, p in zip(warm, plain):
        assert np.linalg.norm(w.unloaded_nodes - p.unloaded_nodes, axis=1).max() < 5 * tol
        assert w.stats["roundtrip_error_mm"] < 10 * tol
    assert warm_factorizations < 0.7 * plain_factorizations, (warm_factorizations, plain_factorizations)


def test_one_workspace_serves_pairs_of_other_supports_in_turn():
    """A workspace holds one sparse solver for problems of several supports (sliding and clamped
    bases: tangents of other sizes and patterns, the gauge rows without a stored diagonal): pairs in
    turn, each started from the last of its own kind, give what pairs solved alone give, with the
    symmetric-part factorisation kept."""
    from dataclasses import replace as dc_replace

    from bench.convergence import CASES, convergence_shape
    from solver.lv import PairWorkspace, make_pair
    from solver.meshing import mesh_lv

    small = mesh_lv(convergence_shape("mean"), 50)
    mid, high = CASES["mid"], dc_replace(CASES["mid"], pressure_mmhg=12.0)
    tol = get_fidelity("fast").inverse_tol_mm
    with PairWorkspace(small) as workspace:
        first = {base: make_pair(small, mid, "fast", base, workspace=workspace) for base in ("sliding", "clamped")}
        for base in ("sliding", "clamped"):
            pair = make_pair(small, high, "fast", base, initial_unloaded=first[base].unloaded_nodes,
                             workspace=workspace)
            alone = make_pair(small, high, "fast", base)
            assert np.linalg.norm(pair.unloaded_nodes - alone.unloaded_nodes, axis=1).max() < 5 * tol
        assert workspace.linsolve.symmetric_part and workspace.linsolve.skew_residual < 1e-2
