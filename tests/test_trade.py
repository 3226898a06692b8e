"""The speed–accuracy trade: inverse FE with an update budget, the re-inflation check, the trade table
(`bench trade`'s plumbing on a tiny run) and the choice it drives (`unload --method auto`, `--check`)."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from typer.testing import CliRunner

from cli import app
from solver.lv import inverse_solve
from solver.parameters import CaseParameters
from solver.reinflate import reinflation_error
from storage.meshfiles import write_mesh
from trainer.errors import TrainerError
from app.method_choice import Method, choose_method, parse_method
from bench.trade import TradeSpec, box_cases, held_out_cases, run_trade
from bench.trade_table import write_report
from trainer_fixtures import lv_mesh, make_tiny_store

runner = CliRunner()
MID = CaseParameters(8.0, 150.0, 60.0, -60.0)


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def error_line(result) -> str:
    lines = [ln for ln in result.output.strip().splitlines() if ln.startswith("heartctl: error:")]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    return lines[0]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("trade")
    store = make_tiny_store(root / "tiny.zarr", shapes=3)
    run_dir = root / "run"
    r = run("train", "--store", store, "--run-dir", run_dir, "--no-ray", "--epochs", 1, "--batch-size", 8,
            "--device", "cpu")
    assert r.exit_code == 0, r.output
    return run_dir


def test_update_budget_returns_the_reference_it_reached():
    """max_updates k: k fixed-point updates, then the answer and its mismatch (no error); more updates
    land closer, and to tolerance is the plain inverse."""
    ed = lv_mesh(0)
    full = inverse_solve(ed, MID, "fast")
    mismatches = []
    for k in (0, 1, 2):
        r = inverse_solve(ed, MID, "fast", max_updates=k)
        assert r.updates == k
        mismatches.append(r.mismatch_mm)
    assert mismatches[0] > mismatches[1] > mismatches[2] > full.mismatch_mm
    with pytest.raises(ValueError, match="max_updates"):
        inverse_solve(ed, MID, "fast", max_updates=-1)


def test_reinflation_estimates_the_error_and_names_failures():
    ed = lv_mesh(0)
    exact = inverse_solve(ed, MID, "fast").unloaded_nodes
    good = reinflation_error(ed, exact, MID, "fast")
    assert good.ok and good.max_mm < 1e-3
    off = exact + 0.2 * np.sin(ed.nodes / 7.0)  # a smooth error of ≤ 0.2 mm per component
    bad = reinflation_error(ed, off, MID, "fast")
    true_max = np.linalg.norm(off - exact, axis=1).max()
    assert bad.ok and 0.3 * true_max < bad.max_mm < 3.0 * true_max
    folded = exact.copy()
    folded[ed.tets[0, 0]] = folded[ed.tets[0, 1:]].mean(axis=0) + 50.0
    failed = reinflation_error(ed, folded, MID, "fast")
    assert not failed.ok and failed.failed and np.isnan(failed.max_mm)
    assert not reinflation_error(ed, exact[:-1], MID, "fast").ok


def test_box_cases_mid_then_hardest_corner():
    grid = {"shapes": 4, "pressure_mmhg": [4, 8, 14], "stiffness_pa": [50, 300], "helix_endo_deg": [60, 70],
            "helix_epi_deg": [-60, -70]}
    cases = box_cases(grid, 5)
    assert cases[0] == ("mid", CaseParameters(9.0, 175.0, 65.0, -65.0))
    assert cases[1][1] == CaseParameters(14.0, 50.0, 70.0, -70.0)  # highest load, softest wall, steepest fibres
    assert cases[2][1] == CaseParameters(4.0, 300.0, 60.0, -60.0)
    assert len(cases) == 5 and len(set(p for _, p in cases)) == 5
    held = held_out_cases({"grid": grid, "shape_nodes": {"0": 300, "3": 310}, "mesh_nodes": 350, "seed": 2},
                          TradeSpec(("r",), shapes=2, cases=2, user_nodes=800))
    assert {c.shape_id for c in held} == {4, 5} and {c.seed for c in held} == {2}  # unseen ids, same model
    assert {c.target_nodes for c in held} == {350, 800} and len(held) == 2 * 2 * 2
    later = held_out_cases({"grid": grid, "shape_nodes": {"0": 300, "3": 310}, "mesh_nodes": 350, "seed": 2},
                           TradeSpec(("r",), shapes=2, cases=1, user_nodes=0, first_shape=20))
    assert [c.shape_id for c in later] == [20, 21]  # the held-out shapes of a run on a larger store
    with pytest.raises(TrainerError, match="first_shape=3: the run's store holds shapes 0–3"):
        held_out_cases({"grid": grid, "shape_nodes": {"0": 300}, "mesh_nodes": 350}, TradeSpec(("r",), first_shape=3))
    other = held_out_cases({"grid": grid, "shape_nodes": {"0": 300}, "mesh_nodes": 350, "seed": 1},
                           TradeSpec(("r",), shapes=2, cases=1, user_nodes=0, seed=0))
    assert [(c.shape_id, c.seed) for c in other] == [(0, 0), (1, 0)]  # another seed: none of its shapes was trained on
    assert {c.version for c in other} == {1} and other[0].key.startswith("s0_seed0_v1_n350_")
    v3 = held_out_cases({"grid": grid, "shape_nodes": {"0": 300}, "mesh_nodes": 350, "seed": 1, "shape_model_version": 2},
                        TradeSpec(("r",), shapes=1, cases=1, user_nodes=0, shape_model=3))
    assert [(c.shape_id, c.seed, c.version) for c in v3] == [(0, 1, 3)]  # another model: its shapes are all unseen
    assert v3[0].key != replace(v3[0], version=2).key  # a cached reference of a v3 shape is not a v2 shape's
    with pytest.raises(ValueError, match="shape model version"):
        TradeSpec(("r",), shape_model=7).validate()


def _table(rows):
    return {"summary": [{"resolution": res, "nodes": n, "method": m, "cases": 2, "ok": ok, "p95_mm": p95,
                         "max_mm": p95 * 2, "time_mean_s": t} for res, n, m, ok, p95, t in rows]}


def test_choose_method_cheapest_that_met_the_tolerance():
    table = _table([("training", 300, "gnn", 2, 0.9, 0.01), ("training", 300, "fe fast", 2, 0.6, 0.3),
                    ("training", 300, "hybrid accurate +2", 2, 0.2, 1.0), ("training", 300, "fe accurate", 2, 0.15, 2.0),
                    ("training", 300, "hybrid fast +1", 1, 0.01, 0.1),  # failed a case: never chosen
                    ("user", 800, "gnn", 2, 0.1, 0.02), ("user", 800, "fe accurate", 2, 0.12, 5.0)])
    pick = choose_method(table, 0.25, 310, False)
    assert pick.run == Method("hybrid", "accurate", updates=2) and pick.label == "hybrid accurate +2"
    assert (pick.p95_mm, pick.max_mm, pick.time_mean_s, pick.nodes) == (0.2, 0.4, 1.0, 300)
    assert choose_method(table, 0.7, 310, False).run.method == "fe"
    assert choose_method(table, 0.15, 900, False).run.method == "gnn"  # the 800-node rows for a 900-node mesh
    with pytest.raises(TrainerError, match="closest, fe accurate, reached 0.150 mm"):
        choose_method(table, 0.05, 310, False)
    with pytest.raises(TrainerError, match="tolerance"):
        choose_method(table, float("nan"), 310, False)
    assert parse_method("hybrid fast to tol") == Method("hybrid", "fast")
    assert parse_method("gnn ensemble") == Method("gnn", ensemble=True)
    adaptive = choose_method(_table([("training", 300, "fe adaptive 0.05", 2, 0.04, 3.0)]), 0.05, 300, False)
    assert adaptive.run == Method("fe", "adaptive", tolerance_mm=0.05)


@pytest.mark.slow
def test_trade_table_on_a_tiny_run(trained, tmp_path, monkeypatch):
    """run_trade end to end on one held-out case (its reference made cheap here: `accurate` on the
    mesh itself), then the report and the choice it drives."""
    import bench.trade as trade

    real = trade.inverse_solve
    monkeypatch.setattr(trade, "inverse_solve", lambda ed, params, preset, *a, **k:
                        real(ed, params, "accurate" if preset == "reference" else preset, *a, **k))
    spec = TradeSpec((str(trained),), shapes=1, cases=1, user_nodes=0, hybrid_updates=(1,))
    result = run_trade(spec, tmp_path / "solves")
    methods = {r.method for r in result.rows}
    assert methods == {"gnn", "fe fast", "fe accurate", "fe adaptive 0.05", "hybrid fast +1", "hybrid accurate +1",
                       "hybrid fast to tol", "hybrid accurate to tol"}
    rows = {r.method: r for r in result.rows}
    assert rows["fe accurate"].max_mm < 1e-3  # the stand-in reference is accurate's own answer
    assert rows["hybrid accurate to tol"].vs_cold_max_mm < 1e-2
    assert rows["fe fast"].mean_mm > rows["fe accurate"].mean_mm
    assert rows["gnn"].check_max_mm is not None and rows["fe fast"].check_max_mm is None
    assert result.hybrid_goal.cases == 1 and result.check_network.answers == 1
    paths = write_report(result, trained / "trade")
    assert paths["plot"].stat().st_size > 0 and "| training" in paths["markdown"].read_text()
    written = json.loads(paths["json"].read_text())
    assert written["summary"] == [s.as_dict() for s in result.summary]
    assert "check_max_mm" not in next(r for r in written["rows"] if r["method"] == "fe fast")
    # the table --method auto reads: the cheapest method that met a tolerance
    assert choose_method(written, 10.0, result.summary[0].nodes, False).label == min(
        (s for s in result.summary if s.ok == s.cases), key=lambda s: s.time_mean_s).method
    # --network-only: the network scored against the same (cached) reference, no FE or hybrid method
    alone = run_trade(replace(spec, network_only=True), tmp_path / "solves")
    assert [r.method for r in alone.rows] == ["gnn"] and alone.hybrid_goal.cases == 0
    assert alone.rows[0].mean_mm == pytest.approx(rows["gnn"].mean_mm)


def test_unload_auto_and_check(trained, tmp_path):
    ed = tmp_path / "ed.vtu"
    write_mesh(ed, lv_mesh(1))
    base = ["unload", ed, "--pressure", 8, "--stiffness", 150, "--endo", 60, "--epi", -60, "--run", trained]
    (trained / "trade").mkdir(exist_ok=True)
    (trained / "trade" / "trade.json").write_text(json.dumps(_table([
        ("training", 120, "gnn", 2, 5.0, 0.01), ("training", 120, "fe fast", 2, 0.6, 0.2),
        ("training", 120, "hybrid fast +1", 2, 0.7, 0.1)])))
    out = tmp_path / "auto.vtu"
    r = run(*base, "--method", "auto", "--tolerance-mm", 0.8, "-o", out)
    assert r.exit_code == 0, r.output
    assert "auto: hybrid fast +1" in r.output and "at most 1 updates" in r.output and out.is_file()
    r = run(*base, "--method", "auto", "--tolerance-mm", 0.65, "-o", tmp_path / "fe.vtu")
    assert r.exit_code == 0 and "auto: fe fast" in r.output, r.output
    assert "no method met 0.1 mm" in error_line(run(*base, "--method", "auto", "--tolerance-mm", 0.1,
                                                    "-o", tmp_path / "none.vtu"))
    assert not (tmp_path / "none.vtu").exists()
    assert "--method auto needs --tolerance-mm" in error_line(run(*base, "--method", "auto", "-o", tmp_path / "x.vtu"))
    assert "--tolerance-mm applies to --method auto" in error_line(
        run(*base, "--method", "gnn", "--tolerance-mm", 1, "-o", tmp_path / "x.vtu"))
    assert "--check applies to" in error_line(run(*base[:-2], "--check", "-o", tmp_path / "x.vtu"))
    r = run(*base, "--method", "gnn", "--check", "--fidelity", "fast", "-o", tmp_path / "gnn.vtu")
    assert r.exit_code == 0, r.output
    assert "check: inflated again (fast" in r.output or "could not be inflated again" in r.output
    (trained / "trade" / "trade.json").unlink()
    assert "no trade table" in error_line(run(*base, "--method", "auto", "--tolerance-mm", 1, "-o", tmp_path / "y.vtu"))
