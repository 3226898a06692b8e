"""heartctl train / evaluate / unload --method gnn|hybrid / bench model through the CLI, and every
bad input (bad checkpoint, mismatched store, bad split or config) → one line, exit code 2."""
from __future__ import annotations

import json
import shutil

import meshio
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from cli import app
from storage.meshfiles import write_mesh
from trainer.training.checkpoint import load_run
from trainer_fixtures import flip_byte, lv_mesh, make_tiny_store

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def assert_bad_input(result, *words):
    assert result.exit_code == 2, result.output
    lines = [ln for ln in result.output.strip().splitlines() if ln.startswith("heartctl: error:")]
    assert len(lines) == 1, result.output
    for w in words:
        assert w in lines[0], lines[0]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("trainer_cli")
    store = make_tiny_store(root / "tiny.zarr", shapes=4)
    run_dir = root / "run"
    r = run("train", "--store", store, "--run-dir", run_dir, "--no-ray", "--epochs", 1, "--batch-size", 8,
            "--device", "cpu")
    assert r.exit_code == 0, r.output
    return {"root": root, "store": store, "run": run_dir}


def test_train_evaluate_json(trained):
    assert (trained["run"] / "checkpoint.pt").is_file() and (trained["run"] / "metrics.csv").is_file()
    r = run("evaluate", "--run", trained["run"], "--store", trained["store"], "--json", "--no-plots")
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    for key in ("dsc_1mm", "dsc_01mm", "hd_mm", "md_mm", "sd_mm", "ms_per_case", "cases"):
        assert key in out
    assert out["cases"] > 0 and 0 <= out["dsc_1mm"] <= 1 and out["hd_mm"] >= out["md_mm"] > 0
    assert out["response_ms_per_mesh"] is None  # this network takes no linear response
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", trained["store"], "--no-plots",
                         "--out", trained["run"] / "metrics.csv"), "is a file")
    r = run("evaluate", "--run", trained["run"], "--store", trained["store"], "--split", "all", "--no-plots")
    assert r.exit_code == 0, r.output
    assert "DSC @ 1 mm" in r.output


def test_unload_gnn_and_hybrid(trained, tmp_path):
    ed = tmp_path / "ed.vtu"
    m = lv_mesh(0)
    write_mesh(ed, m, units="cm")
    out = tmp_path / "unloaded.vtu"
    r = run("unload", ed, "--pressure", 8, "--stiffness", 100, "--endo", 60, "--epi", -60, "--method", "gnn",
            "--run", trained["run"], "--units", "cm", "-o", out)
    assert r.exit_code == 0, r.output
    u = meshio.read(out)
    assert u.points.shape == (m.n_nodes, 3)
    np.testing.assert_allclose(u.points + u.point_data["displacement"], m.nodes / 10.0, atol=1e-9)  # cm
    assert np.abs(u.point_data["displacement"]).max() > 0
    assert "trained on a store" not in r.output  # --base / --fibres left at their defaults: no warning
    r = run("unload", ed, "--pressure", 8, "--stiffness", 100, "--endo", 60, "--epi", -60, "--method", "gnn",
            "--base", "clamped", "--run", trained["run"], "--units", "cm", "-o", out)
    assert r.exit_code == 0, r.output
    assert "--base clamped: the network was trained on a store with base sliding" in r.output
    out_avg = tmp_path / "averaged.vtu"
    r = run("unload", ed, "--pressure", 8, "--stiffness", 100, "--endo", 60, "--epi", -60, "--method", "gnn",
            "--rotations", 4, "--run", trained["run"], "--units", "cm", "-o", out_avg)
    assert r.exit_code == 0, r.output
    assert np.abs(meshio.read(out_avg).points - u.points).max() > 0  # averaged over turns: another answer
    assert_bad_input(run("unload", ed, "--pressure", 8, "--stiffness", 100, "--endo", 60, "--epi", -60, "--method",
                         "gnn", "--rotations", 0, "--run", trained["run"], "-o", tmp_path / "bad.vtu"), "--rotations")
    assert not (tmp_path / "bad.vtu").exists()
    out2 = tmp_path / "hybrid.vtu"
    r = run("unload", ed, "--pressure", 8, "--stiffness", 100, "--endo", 60, "--epi", -60, "--method", "hybrid",
            "--fidelity", "fast", "--run", trained["run"], "--units", "cm", "-o", out2)
    assert r.exit_code in (0, 1), r.output  # 1 only if the inverse solve itself fails
    if r.exit_code == 0:
        assert "hybrid" in r.output and out2.is_file()


def test_hybrid_refines_with_the_asked_fibres_and_base(trained, monkeypatch):
    """--method hybrid hands fidelity, base and fibres on to the inverse FE solve."""
    import solver.lv
    from solver.parameters import CaseParameters
    from trainer.evaluation.predict import HYBRID_TOL_MM, unload_with_network

    seen = {}

    def fake_inverse(mesh, params, fidelity, base, initial_unloaded=None, tol_mm=None, fibres="laplace",
                     max_updates=None, rough_first_state=False):
        seen.update(fidelity=fidelity, base=base, fibres=fibres, guess=initial_unloaded, tol_mm=tol_mm,
                    rough=rough_first_state)
        return type("R", (), {"unloaded_nodes": mesh.nodes.copy()})()

    monkeypatch.setattr(solver.lv, "inverse_solve", fake_inverse)
    m = lv_mesh(0)
    out = unload_with_network(m, CaseParameters(8.0, 100.0, 60.0, -60.0), trained["run"], "hybrid", "fast",
                              "clamped", fibres="heartfem")
    assert seen["fidelity"] == "fast" and seen["base"] == "clamped" and seen["fibres"] == "heartfem"
    assert (seen["guess"] is None) == out.fallback
    assert seen["tol_mm"] == HYBRID_TOL_MM and seen["rough"]  # hybrid's own tolerance, a rough first state


def test_hybrid_starts_again_from_the_ed_mesh_when_the_guess_does_not_converge(trained, monkeypatch):
    """A valid guess from which inverse FE fails: hybrid solves again from the ED mesh (never worse
    than --method fe), says so in a warning, and reports the fallback."""
    import solver.lv
    from solver.forward import SolveError
    from solver.parameters import CaseParameters
    from trainer.evaluation.predict import unload_with_network

    calls = []

    def inverse_failing_from_a_guess(mesh, params, fidelity, base, initial_unloaded=None, tol_mm=None,
                                     fibres="laplace", max_updates=None, rough_first_state=False):
        calls.append(initial_unloaded is not None)
        if initial_unloaded is not None:
            raise SolveError("step size collapsed at 0.0% of load")
        return type("R", (), {"unloaded_nodes": mesh.nodes.copy()})()

    monkeypatch.setattr(solver.lv, "inverse_solve", inverse_failing_from_a_guess)
    out = unload_with_network(lv_mesh(0), CaseParameters(8.0, 100.0, 60.0, -60.0), trained["run"], "hybrid", "fast")
    assert calls == [True, False] and out.fallback and out.guess_attempt_s >= 0
    assert any("did not converge" in w and "started again from the ED mesh" in w for w in out.warnings)


def test_train_makes_the_run_dirs_folders(trained, tmp_path):
    """`--run-dir runs/cpu` in a fresh clone (no runs/ yet) trains (the README's examples); a run
    directory under a file is refused in one line, with nothing made."""
    r = run("train", "--store", trained["store"], "--run-dir", tmp_path / "runs" / "new" / "cpu", "--no-ray",
            "--epochs", 1, "--batch-size", 8, "--device", "cpu")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "runs" / "new" / "cpu" / "checkpoint.pt").is_file()
    (tmp_path / "a_file").write_text("x")
    assert_bad_input(run("train", "--store", trained["store"], "--run-dir", tmp_path / "a_file" / "r", "--no-ray"),
                     "is a file")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "runs"]  # nothing made
    assert (tmp_path / "a_file").read_text() == "x"


def test_bad_checkpoint_and_run_dirs(trained, tmp_path):
    bad = tmp_path / "bad_run"
    bad.mkdir()
    (bad / "checkpoint.pt").write_bytes(b"\x00garbage")
    assert_bad_input(run("evaluate", "--run", bad, "--store", trained["store"]), "cannot read checkpoint")
    assert_bad_input(run("evaluate", "--run", tmp_path / "nope", "--store", trained["store"]), "does not exist")
    empty = tmp_path / "empty_run"
    empty.mkdir()
    assert_bad_input(run("evaluate", "--run", empty, "--store", trained["store"]), "no checkpoint.pt")
    ed = tmp_path / "ed.vtu"
    write_mesh(ed, lv_mesh(0))
    o = tmp_path / "o.vtu"
    assert_bad_input(run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "gnn", "--run", bad, "-o", o),
                     "cannot read checkpoint")
    assert_bad_input(run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "fe", "--run", bad, "-o", o),
                     "--run applies to --method gnn|hybrid|auto")
    assert_bad_input(run("unload", ed, "--pressure", 8, "--stiffness", 100, "--run", trained["run"], "-o", o), "--run")
    assert not o.exists()
    assert_bad_input(run("train", "--store", trained["store"], "--run-dir", bad, "--no-ray"), "cannot read checkpoint")


def test_mismatched_store(trained):
    other = make_tiny_store(trained["root"] / "other_seed.zarr", shapes=4, seed=1)
    out = trained["root"] / "ev_other"
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", other, "--out", out), "does not match", "seed")
    assert not out.exists()  # refused before any output folder is made
    grid = make_tiny_store(trained["root"] / "other_grid.zarr", shapes=4, pressures=(6.0, 10.0))
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", grid), "does not match", "grid")
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", trained["root"] / "none.zarr"), "no heartctl store")
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", trained["store"], "--split", "holdout"), "--split")


@pytest.mark.parametrize("args,words", [
    (("--no-ray", "--split", "lovo:Q=1"), ("axis",)),
    (("--no-ray", "--split", "lovo:P=10"), ("no done case", "8, 12")),
    (("--split", "lovo:P=10"), ("no done case", "8, 12")),  # the Ray path: refused before Ray starts
    (("--split", "source"), ("source",)),
    (("--no-ray", "--config", "A7"), ("unknown configuration 'A7'",)),
    (("--no-ray", "--sr", "0"), ("--sr",)),
    (("--no-ray", "--epochs", "0"), ("--epochs",)),
    (("--no-ray", "--rotate-deg", "200"), ("--rotate-deg", "[0, 180]")),
    (("--no-ray", "--split-seed", "-1"), ("--split-seed",)),
    (("--no-ray", "--label-seed", "1"), ("--label-seed", "--sr")),
    (("--gpus", "1"), ("--gpus",)),
    (("--local", "--no-ray"), ("--no-ray",)),
    (("--no-ray", "--lr", "inf"), ("--lr",)),
    (("--workers", "999"), ("--workers 999", "CPUs")),  # Ray Train would wait for them for ever
])
def test_train_bad_inputs(trained, tmp_path, args, words, request):
    import torch

    if "--gpus" in args and torch.cuda.is_available():
        pytest.skip("this host has a GPU")
    if "--no-ray" not in args:
        request.getfixturevalue("local_ray")  # the tests' shared local Ray, not one of its own
    assert_bad_input(run("train", "--store", trained["store"], "--run-dir", tmp_path / "r", *args), *words)
    assert not (tmp_path / "r").exists()


def test_train_refuses_a_run_dir_of_another_config(trained):
    assert_bad_input(run("train", "--store", trained["store"], "--run-dir", trained["run"], "--no-ray", "--config", "A1"),
                     "model paper (this command: no-cycle)", "batch_size 8 (this command: 16)")
    assert_bad_input(run("train", "--store", trained["root"] / "missing.zarr", "--run-dir", trained["root"] / "x",
                         "--no-ray"), "no heartctl store")


def test_resume_refuses_a_regenerated_store(tmp_path):
    """Same case keys, another base condition: resuming would pair old weights with new data."""
    import shutil

    store = make_tiny_store(tmp_path / "s.zarr", shapes=4)
    args = ("train", "--store", store, "--run-dir", tmp_path / "r", "--no-ray", "--batch-size", 8, "--device", "cpu")
    assert run(*args, "--epochs", 1).exit_code == 0
    shutil.rmtree(store)
    make_tiny_store(store, shapes=4, attrs={"base": "clamped"})
    assert_bad_input(run(*args, "--epochs", 2), "does not match", "base")


@pytest.mark.slow
def test_bench_model_small():
    fast = ("--min-seconds", 0.05)  # figures from three calls each: this checks the output, not the speed
    r = run("bench", "model", "--nodes", 120, "--batches", "1,2", "--train-batch", 2, "--json", *fast)
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    assert [row["batch"] for row in out["inference"]] == [1, 2]
    assert out["train_graphs_per_s"] > 0 and out["parameters"] > 1e6
    assert out["gat_kernel"] == "sparse" and out["prepared_single"]["ms_per_case"] > 0
    r = run("bench", "model", "--nodes", 120, "--batches", "1", "--train-batch", 1, "--gat-kernel", "pyg", "--json", *fast)
    assert r.exit_code == 0 and json.loads(r.output.strip().splitlines()[-1])["gat_kernel"] == "pyg"
    assert out["response_ms_per_mesh"] is None  # paper: no linear response in its input
    # the mean-teacher model: the timed step runs the reverse decoder, the teacher and the weight average
    r = run("bench", "model", "--nodes", 120, "--config", "R5-resp-d0", "--batches", "1", "--train-batch", 2, *fast)
    assert r.exit_code == 0, r.output
    assert "linear FE response" in r.output and "ms" in r.output.split("linear FE response")[1]
    assert_bad_input(run("bench", "model", "--batches", "1,x"), "--batches")
    assert_bad_input(run("bench", "model", "--gat-kernel", "dense"), "--gat-kernel")
    assert_bad_input(run("bench", "model", "--min-seconds", -1), "--min-seconds")
    assert_bad_input(run("bench", "model", "--mesh", "/nonexistent/lv.vtu"), "no such file")
    import torch

    if not torch.cuda.is_available():
        assert_bad_input(run("bench", "model", "--device", "cuda"), "CUDA")


@pytest.mark.slow
def test_bench_ablation_table(trained, tmp_path):
    """Three configurations on one split (one takes the linear FE response, the others share its
    graphs): a table row each with the evaluate metrics, files written, and a rerun resumes (no
    retraining) with the same figures; an unknown name → exit 2."""
    root = tmp_path / "abl"
    args = ("bench", "ablation", "--store", trained["store"], "--root", root, "--configs", "A1,pca,A1ema-resp-d0",
            "--epochs", 1, "--batch-size", 8, "--json")
    r = run(*args)
    assert r.exit_code == 0, r.output
    table = json.loads(r.output.strip().splitlines()[-1])
    assert [row["config"] for row in table["rows"]] == ["no-cycle", "pca", "A1ema-resp-d0"]  # a code by its name
    assert [row["code"] for row in table["rows"]] == ["A1", "", ""]
    for row in table["rows"]:
        assert row["cases"] > 0 and row["md_mm"] > 0 and 0 <= row["dsc_1mm"] <= 1 and row["hd_mm"] >= row["md_mm"]
    assert (root / "ablation.csv").is_file() and (root / "no-cycle" / "checkpoint.pt").is_file()
    again = json.loads(run(*args).output.strip().splitlines()[-1])
    assert again["rows"][0]["md_mm"] == pytest.approx(table["rows"][0]["md_mm"])
    assert_bad_input(run("bench", "ablation", "--store", trained["store"], "--root", tmp_path / "x",
                         "--configs", "paper,B7"), "unknown configuration 'B7'")


def test_bench_ablation_over_seeds(trained, tmp_path):
    """--seeds: one ablation per seed under ROOT/seed<N> (its own split), a mean ± SD table and the
    summary file; bad seed lists → exit 2 before any training."""
    root = tmp_path / "seeds"
    r = run("bench", "ablation", "--store", trained["store"], "--root", root, "--configs", "pca", "--seeds", "0,1")
    assert r.exit_code == 0, r.output
    assert "mean ± SD over seeds" in r.output and "pca" in r.output
    summary = json.loads((root / "ablation_seeds.json").read_text())
    assert summary["seeds"] == [0, 1] and (root / "seed1" / "ablation.json").is_file()
    md = [res["rows"][0]["md_mm"] for res in summary["per_seed"]]
    assert summary["configs"]["pca"]["md_mm"]["mean"] == pytest.approx(sum(md) / 2)
    for bad, words in (("0,x", "comma-separated integers"), ("2,2", "repeats")):
        assert_bad_input(run("bench", "ablation", "--store", trained["store"], "--root", tmp_path / "y",
                             "--configs", "pca", "--seeds", bad), words)
    assert not (tmp_path / "y").exists()


def test_bench_learning_curve(trained, tmp_path):
    """Two fractions of the training shapes: the smaller one trains on fewer pairs, both on the same
    test cases; the fitted law and files come out; bad fractions or targets → exit 2, nothing made."""
    root = tmp_path / "lc"
    r = run("bench", "learning-curve", "--store", trained["store"], "--root", root, "--config", "pca",
            "--fractions", "0.34,1", "--json")
    assert r.exit_code == 0, r.output
    res = json.loads(r.output.strip().splitlines()[-1])
    small, full = res["rows"]
    assert small["train_cases"] < full["train_cases"] and small["cases"] == full["cases"] > 0
    assert {"md_mm", "hd_mm"} <= set(res["laws"]) and set(res["pairs_needed"]) == set(res["laws"])
    assert (root / "learning_curve.csv").is_file() and (root / "frac0.34" / "checkpoint.pt").is_file()
    r = run("bench", "learning-curve", "--store", trained["store"], "--root", root, "--config", "pca",
            "--fractions", "0.34,1")
    assert r.exit_code == 0, r.output
    assert "pairs^(" in r.output and "learning_curve.json" in r.output  # a rerun resumes and prints the fit
    for args, words in ((("--fractions", "1"), "at least two"), (("--fractions", "0,1"), "(0, 1]"),
                        (("--target-dsc", "1"), "target-dsc"), (("--config", "B7"), "unknown configuration"),
                        (("--fractions", "0.3,0.34"), "same training cases")):  # both keep 1 of 3 shapes
        assert_bad_input(run("bench", "learning-curve", "--store", trained["store"], "--root", tmp_path / "bad",
                             *args), words)
    assert not (tmp_path / "bad").exists()
    assert_bad_input(run("train", "--store", trained["store"], "--run-dir", tmp_path / "t", "--no-ray",
                         "--train-fraction", "0"), "train-fraction")


@pytest.mark.slow
def test_ensemble_is_the_mean_of_its_members_and_reports_their_spread(trained, tmp_path):
    """`--run A --run B`: evaluate scores the mean of the two networks' answers; unload writes it with
    the members' per-node spread; a member with another split (seed) is refused."""
    from solver.parameters import CaseParameters
    from trainer.evaluation.predict import unload_with_network

    other = trained["root"] / "run_a1"
    r = run("train", "--store", trained["store"], "--run-dir", other, "--no-ray", "--epochs", 1, "--batch-size", 8,
            "--device", "cpu", "--config", "A1")
    assert r.exit_code == 0, r.output
    m = lv_mesh(1)
    params = CaseParameters(8.0, 100.0, 60.0, -60.0)
    single = [unload_with_network(m, params, d).unloaded_nodes for d in (trained["run"], other)]
    both = unload_with_network(m, params, [trained["run"], other])
    np.testing.assert_allclose(both.unloaded_nodes, (single[0] + single[1]) / 2, atol=1e-5)
    half_gap = np.linalg.norm(single[0] - single[1], axis=1) / 2  # two members: RMS spread = half their distance
    np.testing.assert_allclose(both.spread_mm, half_gap, atol=1e-5)
    assert both.members == 2 and half_gap.max() > 0

    ed, o = tmp_path / "ed.vtu", tmp_path / "o.vtu"
    write_mesh(ed, m)
    r = run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "gnn", "--run", trained["run"],
            "--run", other, "-o", o)
    assert r.exit_code == 0, r.output
    assert "2 networks disagree" in r.output
    np.testing.assert_allclose(meshio.read(o).point_data["ensemble_spread"], half_gap, atol=1e-5)

    r = run("evaluate", "--run", trained["run"], "--run", trained["run"], "--store", trained["store"], "--json",
            "--no-plots")
    assert r.exit_code == 0, r.output
    twice = json.loads(r.output.strip().splitlines()[-1])
    r = run("evaluate", "--run", trained["run"], "--store", trained["store"], "--json", "--no-plots")
    once = json.loads(r.output.strip().splitlines()[-1])
    assert twice["members"] == 2 and once["members"] == 1
    for key in ("md_mm", "hd_mm", "dsc_1mm", "sd_mm"):  # a run averaged with itself is that run
        assert twice[key] == pytest.approx(once[key], rel=1e-6)
    assert (trained["run"] / "eval_test_ensemble2" / "summary.json").is_file()

    seed1 = trained["root"] / "run_seed1"
    r = run("train", "--store", trained["store"], "--run-dir", seed1, "--no-ray", "--epochs", 1, "--batch-size", 8,
            "--device", "cpu", "--seed", 1)
    assert r.exit_code == 0, r.output
    assert_bad_input(run("evaluate", "--run", trained["run"], "--run", seed1, "--store", trained["store"], "--no-plots"),
                     "another test split")
    # --split-seed 0 keeps seed 0's split with seed 1's initialisation: a seed ensemble
    seed1_split0 = trained["root"] / "run_seed1_split0"
    r = run("train", "--store", trained["store"], "--run-dir", seed1_split0, "--no-ray", "--epochs", 1, "--batch-size", 8,
            "--device", "cpu", "--seed", 1, "--split-seed", 0)
    assert r.exit_code == 0, r.output
    states = [load_run(d) for d in (trained["run"], seed1_split0)]
    assert states[0]["split"] == states[1]["split"]
    assert any(not torch.equal(a, states[1]["model"][k]) for k, a in states[0]["model"].items())  # other weights
    r = run("evaluate", "--run", trained["run"], "--run", seed1_split0, "--store", trained["store"], "--json", "--no-plots")
    assert r.exit_code == 0, r.output
    assert json.loads(r.output.strip().splitlines()[-1])["members"] == 2
    assert_bad_input(run("train", "--store", trained["store"], "--run-dir", seed1_split0, "--no-ray", "--epochs", 2,
                         "--device", "cpu", "--seed", 1), "split_seed")  # resuming needs the same split seed


def _copied_run(trained, tmp_path, name, change) -> "Path":
    """A copy of the trained run whose checkpoint `change(state)` edits (a damaged or diverged run)."""
    import shutil

    from trainer.training.checkpoint import save_checkpoint

    d = tmp_path / name
    shutil.copytree(trained["run"], d)
    state = load_run(d)
    change(state)
    save_checkpoint(d / "checkpoint.pt", {k: v for k, v in state.items() if k not in ("format", "version")})
    return d


def test_network_unloading_does_not_depend_on_where_the_mesh_lies(trained):
    """The FE answer is the same wherever the ED mesh lies; the network places every mesh in the
    training frame (centroid on the long axis, base at z = 0) first, so its answer is the same too."""
    from solver.parameters import CaseParameters
    from trainer.evaluation.predict import unload_with_network

    m = lv_mesh(1)
    params = CaseParameters(10.0, 150.0, 60.0, -60.0)
    here = unload_with_network(m, params, trained["run"]).unloaded_nodes - m.nodes
    shift = np.array([25.0, -15.0, 40.0])
    there = unload_with_network(m.with_nodes(m.nodes + shift), params, trained["run"]).unloaded_nodes - m.nodes - shift
    np.testing.assert_allclose(there, here, atol=2e-5)
    assert np.abs(here).max() > 0.1


def test_a_diverged_or_damaged_checkpoint_is_refused_in_one_line(trained, tmp_path):
    ed, o = tmp_path / "ed.vtu", tmp_path / "o.vtu"
    write_mesh(ed, lv_mesh(0))

    def nan_weights(state):
        for key in ("model", "best_model"):
            if state.get(key):
                first = next(iter(state[key]))
                state[key][first] = torch.full_like(state[key][first], float("nan"))

    diverged = _copied_run(trained, tmp_path, "diverged", nan_weights)
    assert_bad_input(run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "gnn", "--run", diverged,
                         "-o", o), "not finite", "--lr")
    assert not o.exists()
    assert_bad_input(run("evaluate", "--run", diverged, "--store", trained["store"], "--no-plots"), "not finite")
    damages = {"scale0": lambda s: s["normalisation"].update(scale_mm=0.0),
               "no_scale": lambda s: s["normalisation"].pop("scale_mm"),
               "fingerprint": lambda s: s.update(fingerprint=None),
               "split": lambda s: s.update(split=[1, 2]),
               "config": lambda s: s.update(train_config="paper"),
               "history": lambda s: s.update(history=[{"loss": 1.0}])}
    for name, change in damages.items():
        bad = _copied_run(trained, tmp_path, name, change)
        assert_bad_input(run("evaluate", "--run", bad, "--store", trained["store"], "--no-plots"), "damaged")
        assert_bad_input(run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "gnn", "--run", bad,
                             "-o", o), "damaged")
        assert not o.exists()
    assert_bad_input(run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "gnn", "--run", ed, "-o", o),
                     "is a file")
    # resuming reads more of the checkpoint: a part missing or diverged weights → one line, nothing trained
    for name, change in (("no_optimizer", lambda s: s.pop("optimizer")), ("nan_resume", nan_weights)):
        bad = _copied_run(trained, tmp_path, name, change)
        assert_bad_input(run("train", "--store", trained["store"], "--run-dir", bad, "--no-ray", "--epochs", 2,
                             "--batch-size", 8, "--device", "cpu"), "optimizer" if name == "no_optimizer" else "not finite")
        assert load_run(bad)["epoch"] == 1
    pca = tmp_path / "pca"
    r = run("train", "--store", trained["store"], "--run-dir", pca, "--no-ray", "--config", "pca", "--device", "cpu")
    assert r.exit_code == 0, r.output
    assert "pca: fitted; validation MD " in r.output  # the ridge was chosen on them: not "no validation cases"
    pca_bad = _copied_run({"run": pca}, tmp_path, "pca_bad", lambda s: [s[k].pop("ridge_w") for k in ("model", "best_model")])
    assert_bad_input(run("evaluate", "--run", pca_bad, "--store", trained["store"], "--no-plots"), "damaged", "ridge_w")
    for extra in (["--tol-mm", 1e-3], ["--fidelity", "fast"]):
        assert_bad_input(run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "gnn", "--run",
                             trained["run"], *extra, "-o", o), extra[0], "--method gnn")


def test_only_model_choices_the_user_names_draw_a_warning(trained, tmp_path):
    """A network trained on a clamped-base store, used without --base: no warning (the user asked for
    nothing else); with --base sliding: the warning."""
    clamped = _copied_run(trained, tmp_path, "clamped", lambda s: s["fingerprint"].update(base="clamped"))
    ed, o = tmp_path / "ed.vtu", tmp_path / "o.vtu"
    write_mesh(ed, lv_mesh(0))
    r = run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "gnn", "--run", clamped, "-o", o)
    assert r.exit_code == 0, r.output
    assert "trained on a store" not in r.output
    r = run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "gnn", "--run", clamped, "--base", "sliding",
            "-o", o)
    assert r.exit_code == 0, r.output
    assert "--base sliding: the network was trained on a store with base clamped" in r.output


def test_evaluation_folder_holds_one_evaluation_and_write_errors_are_one_line(trained, tmp_path, monkeypatch):
    out = tmp_path / "ev"
    r = run("evaluate", "--run", trained["run"], "--store", trained["store"], "--out", out)
    assert r.exit_code == 0, r.output
    assert (out / "error_histogram.png").is_file() and (out / "training_curves.png").is_file()
    r = run("evaluate", "--run", trained["run"], "--store", trained["store"], "--out", out, "--no-plots")
    assert r.exit_code == 0, r.output
    assert not list(out.glob("*.png"))  # the earlier evaluation's plots are gone, not left beside this summary
    r = run("evaluate", "--run", trained["run"], "--store", trained["store"], "--no-plots", "--rotations", 2)
    assert r.exit_code == 0, r.output
    assert (trained["run"] / "eval_test_rot2" / "summary.json").is_file()

    import trainer.evaluation.evaluate

    def disk_full(path, rows):
        raise OSError(28, "No space left on device")

    def no_prediction(*args, **kwargs):
        raise AssertionError("predicted before checking the output folder")

    with monkeypatch.context() as m:  # an unusable --out is refused before any case is predicted
        m.setattr(trainer.evaluation.evaluate.Ensemble, "predict_many", no_prediction)
        assert_bad_input(run("evaluate", "--run", trained["run"], "--store", trained["store"], "--out",
                             out / "summary.json" / "sub"), "cannot write the evaluation")
    monkeypatch.setattr(trainer.evaluation.evaluate, "write_csv", disk_full)
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", trained["store"], "--out", out, "--no-plots"),
                     "cannot write the evaluation", "No space left")
    assert not (out / "summary.json").exists()


def test_ensemble_warnings_speak_for_every_member(trained, tmp_path):
    """An ensemble extrapolates where any member does: each member's training grid is checked."""
    from solver.parameters import CaseParameters
    from trainer.evaluation.predict import unload_with_network

    low = _copied_run(trained, tmp_path, "low_pressures",
                      lambda s: s["normalisation"].update(param_lo=[4.0, *s["normalisation"]["param_lo"][1:]],
                                                          param_hi=[6.0, *s["normalisation"]["param_hi"][1:]]))
    params = CaseParameters(12.0, 100.0, 60.0, -60.0)
    for order in ([trained["run"], low], [low, trained["run"]]):
        warnings = unload_with_network(lv_mesh(0), params, order).warnings
        assert any("pressure 12 is outside the training grid [4, 6]" in w for w in warnings), warnings


def test_bench_model_reads_its_mesh_in_the_unit_given(tmp_path):
    cm = tmp_path / "lv_cm.vtu"
    write_mesh(cm, lv_mesh(0), units="cm")
    r = run("bench", "model", "--mesh", cm, "--units", "cm", "--batches", "1", "--train-batch", 2, "--threads", 1,
            "--min-seconds", 0.05)  # this checks the mesh read, not the speed
    assert r.exit_code == 0, r.output
    assert "warning" not in r.output and f"mesh {lv_mesh(0).n_nodes} nodes" in r.output
    assert_bad_input(run("bench", "model", "--units", "cm"), "--units gives the length unit of the --mesh file")


def test_a_mesh_in_another_unit_draws_one_size_warning_with_the_network(trained, tmp_path):
    """unload --method gnn on a cm mesh read as mm: the unit warning of the mesh reader, once, and not
    the network's own size warning beside it."""
    ed = tmp_path / "ed_cm.vtu"
    write_mesh(ed, lv_mesh(0), units="cm")
    r = run("unload", ed, "--pressure", 8, "--stiffness", 100, "--method", "gnn", "--run", trained["run"],
            "-o", tmp_path / "u.vtu")
    assert r.exit_code == 0, r.output
    warned = [ln for ln in r.output.splitlines() if "warning" in ln]
    assert len(warned) == 1 and warned[0].endswith("this looks like cm; pass --units cm"), r.output


def test_a_diverging_run_stops_and_keeps_its_last_good_checkpoint(trained, tmp_path):
    """A loss that turns non-finite is an error (exit 2), not a 'best' epoch: before, a NaN validation
    loss made the training loss the yardstick and the diverged weights the kept network, exit 0."""
    run_dir = tmp_path / "r"
    common = ("train", "--store", trained["store"], "--run-dir", run_dir, "--no-ray", "--batch-size", 8,
              "--device", "cpu")
    assert run(*common, "--epochs", 1).exit_code == 0
    good = load_run(run_dir)
    assert_bad_input(run(*common, "--epochs", 3, "--lr", "1e12"), "diverged in epoch 2", "--lr")
    kept = load_run(run_dir)
    assert kept["epoch"] == 1 and all(torch.equal(good["model"][k], v) for k, v in kept["model"].items())
    assert len(kept["history"]) == 1


def test_a_fresh_run_that_diverges_leaves_nothing(trained, tmp_path):
    run_dir = tmp_path / "fresh"
    assert_bad_input(run("train", "--store", trained["store"], "--run-dir", run_dir, "--no-ray", "--batch-size", 8,
                         "--device", "cpu", "--epochs", 2, "--lr", "1e12"), "diverged in epoch 1", "nothing of this run")
    assert not run_dir.exists()
    run_dir.mkdir()  # the user's own folder stays, empty
    assert run("train", "--store", trained["store"], "--run-dir", run_dir, "--no-ray", "--batch-size", 8,
               "--device", "cpu", "--epochs", 2, "--lr", "1e12").exit_code == 2
    assert run_dir.is_dir() and not any(run_dir.iterdir())


def test_a_damaged_chunk_in_the_store_is_one_line(trained, tmp_path):
    """A chunk that does not decompress (zarr/numcodecs raise RuntimeError): exit 2 and one line from
    train and evaluate, not a traceback with exit 1 (nor, under Ray, a failure retried --max-failures times)."""
    store = tmp_path / "damaged.zarr"
    shutil.copytree(trained["store"], store)
    chunks = sorted(p for p in store.glob("shapes/*/unloaded/c/**/*") if p.is_file())
    assert chunks
    for p in chunks:
        p.write_bytes(b"not a blosc chunk" * 4)
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", store, "--no-plots"), "damaged.zarr",
                     "is damaged")
    assert_bad_input(run("train", "--store", store, "--run-dir", tmp_path / "r", "--no-ray", "--epochs", 1,
                         "--device", "cpu"), "damaged.zarr", "is damaged")
    assert not (tmp_path / "r").exists()


def test_a_run_without_validation_cases_says_so_in_strict_json(tmp_path):
    store = make_tiny_store(tmp_path / "two.zarr", shapes=2, pressures=(8.0,), stiffness=(100.0,))
    r = run("train", "--store", store, "--run-dir", tmp_path / "r", "--no-ray", "--epochs", 2, "--device", "cpu",
            "--json")
    assert r.exit_code == 0, r.output

    def refuse(constant):
        raise AssertionError(f"{constant} is not JSON")

    summary = json.loads(r.output.strip().splitlines()[-1], parse_constant=refuse)
    assert summary["best_val_md_mm"] is None and summary["best_epoch"] in (1, 2)
    assert "no validation cases" in r.output
    r = run("train", "--store", store, "--run-dir", tmp_path / "r", "--no-ray", "--epochs", 3, "--device", "cpu")
    assert r.exit_code == 0, r.output
    assert "no validation cases, kept epoch" in r.output and "nan" not in r.output


def test_a_split_resumes_however_it_is_written(trained, tmp_path):
    common = ("train", "--store", trained["store"], "--run-dir", tmp_path / "r", "--no-ray", "--batch-size", 8,
              "--device", "cpu")
    assert run(*common, "--split", "lovo:P=8", "--epochs", 1).exit_code == 0
    r = run(*common, "--split", "lovo:p=8.0", "--epochs", 2)
    assert r.exit_code == 0, r.output
    assert load_run(tmp_path / "r")["epoch"] == 2


@pytest.mark.slow
def test_sigterm_stops_training_like_ctrl_c(trained, tmp_path):
    """kill / Slurm / systemd stop a job with SIGTERM: one line, exit 130, the checkpoint kept, resumable."""
    import signal
    import subprocess
    import sys
    from pathlib import Path

    repo = str(Path(__file__).resolve().parents[1])
    run_dir = tmp_path / "r"
    cmd = [sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); from cli import main; "
           "sys.argv = ['heartctl'] + sys.argv[2:]; main()", repo, "train", "--store", str(trained["store"]),
           "--run-dir", str(run_dir), "--no-ray", "--epochs", "100000", "--batch-size", "8", "--device", "cpu"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})
    try:
        for line in proc.stderr:
            if line.startswith("epoch 2/"):
                break
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    errors = [ln for ln in err.splitlines() if ln.startswith("heartctl: error:")]
    assert len(errors) == 1 and "interrupted" in errors[0] and "Traceback" not in err
    assert load_run(run_dir)["epoch"] >= 1  # epoch 2 may have been cut short while saving


def test_train_help_names_every_base_configuration_and_the_preset():
    """`train --help` lists every base name and `recommended`; the compatibility names stay unadvertised."""
    from app.terminal import options
    from trainer import config

    assert options.CONFIG_HELP is config.CONFIG_HELP
    for name in (*config.BASE_CONFIGS, *config.PRESETS):
        assert name in config.CONFIG_HELP, name
    assert "A1–A5" in config.CONFIG_HELP and "R1–R5" in config.CONFIG_HELP
    assert not any(alias in config.CONFIG_HELP for alias in set(config.ALIASES) - set(config.CODES))


def test_train_composes_the_configuration_from_options_and_evaluate_prints_it(trained, tmp_path):
    """Options on top of a base give the network the old coded name gave, field by field; the checkpoint
    holds every field; evaluate prints the configuration in those terms; the compatibility name trains
    the same network."""
    from trainer.config import ModelConfig, TrainConfig

    composed, alias = tmp_path / "composed", tmp_path / "alias"
    common = ("--store", trained["store"], "--no-ray", "--epochs", 1, "--batch-size", 8, "--device", "cpu",
              "--set", "hidden=8", "--set", "heads=2", "--set", "decoder_hidden=16", "--set", "param_hidden=8")
    r = run("train", "--run-dir", composed, "--config", "no-cycle", "--node-input", "wall", "--ema", 0.99, "--dropout", 0,
            "--output-scale", "load", *common)
    assert r.exit_code == 0, r.output
    r = run("train", "--run-dir", alias, "--config", "A1ema-wall-d0-load", *common)
    assert r.exit_code == 0, r.output
    saved = load_run(composed)["train_config"]
    assert set(saved["model"]) == {f.name for f in __import__("dataclasses").fields(ModelConfig)}
    assert saved["model"] == load_run(alias)["train_config"]["model"]
    assert TrainConfig.from_dict(saved).model.output_scale == "load"
    r = run("evaluate", "--run", composed, "--store", trained["store"], "--no-plots", "--out", tmp_path / "e")
    assert r.exit_code == 0, r.output
    line = next(ln for ln in r.output.splitlines() if ln.startswith("configuration:"))
    assert line.startswith("configuration: no-cycle + node-input wall, ema 0.99, dropout 0, output-scale load, hidden=8"), line
    r = run("evaluate", "--run", composed, "--store", trained["store"], "--no-plots", "--json", "--out", tmp_path / "e")
    assert json.loads(r.output.strip().splitlines()[-1])["configuration"][0] == line.removeprefix("configuration: ")


@pytest.mark.parametrize("args,words", [
    (("--set", "hiden=8"), ("unknown --set key 'hiden'",)),
    (("--set", "hidden"), ("--set takes key=value",)),
    (("--set", "hidden=1.5"), ("hidden takes an integer",)),
    (("--ema", "1"), ("ema_decay must be in [0, 1)",)),
    (("--node-input", "resp"), ("--node-input must be one of xyz, wall, response",)),
    (("--config", "A1emma"), ("unknown configuration 'A1emma'", "recommended")),
])
def test_bad_configuration_options_are_one_line(trained, tmp_path, args, words):
    assert_bad_input(run("train", "--store", trained["store"], "--run-dir", tmp_path / "r", "--no-ray", *args), *words)
    assert not (tmp_path / "r").exists()


def test_a_checkpoint_named_by_an_old_coded_name_loads_and_an_unknown_one_is_refused(trained, tmp_path):
    """A checkpoint that names its configuration without listing the network's settings resolves the
    name (a compatibility name included); one whose name is unknown, or whose settings this heartctl
    does not know, is refused in one line."""
    from trainer.config import TrainConfig, named_config

    def named(name):
        return lambda s: [s["train_config"].pop("model"), s["train_config"].update(config_name=name)]

    old = _copied_run(trained, tmp_path, "old", named("paper"))
    assert TrainConfig.from_dict(load_run(old)["train_config"]).model == named_config("paper")
    r = run("evaluate", "--run", old, "--store", trained["store"], "--no-plots", "--out", tmp_path / "e")
    assert r.exit_code == 0, r.output
    old_coded = _copied_run(trained, tmp_path, "old_coded", named("A1ema-resp-d0"))
    assert TrainConfig.from_dict(load_run(old_coded)["train_config"]).model == named_config("recommended")
    unknown = _copied_run(trained, tmp_path, "unknown", named("B7"))
    assert_bad_input(run("evaluate", "--run", unknown, "--store", trained["store"], "--no-plots"),
                     "'B7' lists no network settings")
    newer = _copied_run(trained, tmp_path, "newer", lambda s: s["train_config"]["model"].update(wings=2))
    assert_bad_input(run("evaluate", "--run", newer, "--store", trained["store"], "--no-plots"),
                     "wings", "unknown to this heartctl")


def test_evaluate_against_a_reference_store(trained, tmp_path):
    """--reference scores the network and the store's own labels against a store of the same ED meshes
    (here: the labels moved 0.3 mm, at one of the grid's parameter sets); other meshes or no shared
    case are one line, exit 2."""
    reference = make_tiny_store(tmp_path / "ref.zarr", shapes=4, pressures=(8.0,), stiffness=(100.0,),
                                attrs={"fidelity": "reference"}, shift_mm=0.3)
    r = run("evaluate", "--run", trained["run"], "--store", trained["store"], "--reference", reference,
            "--no-plots", "--json", "--out", tmp_path / "eval")
    assert r.exit_code == 0, r.output
    out = json.loads(r.output.strip().splitlines()[-1])
    ref = out["reference"]
    assert ref["fidelity"] == "reference" and ref["labels_fidelity"] == "fast"
    test_shapes = {k[0] for k in load_run(trained["run"])["split"]["test"]}
    assert ref["cases"] == len(test_shapes)  # one parameter set (8 mmHg, 100 Pa) per test shape
    assert ref["labels"]["md_mm"][0] == pytest.approx(0.3, abs=1e-5)  # stored in float32
    assert ref["labels"]["max_mm"][0] == pytest.approx(0.3, abs=1e-5)
    assert np.isfinite(ref["network"]["md_mm"][0]) and ref["network"]["md_mm"][0] > 0
    rows = (tmp_path / "eval" / "cases.csv").read_text().splitlines()
    assert "ref_md_mm" in rows[0] and "label_ref_md_mm" in rows[0]
    r = run("evaluate", "--run", trained["run"], "--store", trained["store"], "--reference", reference,
            "--no-plots", "--out", tmp_path / "eval2")
    assert r.exit_code == 0 and "vs converged (reference" in r.output, r.output
    other_meshes = make_tiny_store(tmp_path / "seed1.zarr", shapes=4, seed=1, pressures=(8.0,), stiffness=(100.0,),
                                   attrs={"fidelity": "reference"})
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", trained["store"], "--reference",
                         other_meshes, "--no-plots", "--out", tmp_path / "e3"), "another ED mesh")
    other_grid = make_tiny_store(tmp_path / "p5.zarr", shapes=4, pressures=(5.0,), stiffness=(100.0,),
                                 attrs={"fidelity": "reference"})
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", trained["store"], "--reference",
                         other_grid, "--no-plots", "--out", tmp_path / "e4"), "none of the")
    assert not (tmp_path / "e3").exists() and not (tmp_path / "e4").exists()
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", trained["store"], "--reference",
                         trained["store"], "--no-plots", "--out", tmp_path / "e5"),
                     "is of the 'fast' fidelity; --reference takes a store generated with the reference fidelity")
    assert not (tmp_path / "e5").exists()


def test_a_reference_no_finer_than_the_labels_is_refused(tmp_path):
    from trainer.errors import TrainerError
    from trainer.evaluation.reference import check_reference_fidelity

    check_reference_fidelity("r.zarr", "reference", "accurate")
    with pytest.raises(TrainerError, match="no finer than the evaluated store's labels"):
        check_reference_fidelity("r.zarr", "reference", "reference")
    with pytest.raises(TrainerError, match="is of the 'accurate' fidelity"):
        check_reference_fidelity("r.zarr", "accurate", "fast")


def test_a_checkpoint_with_a_changed_weight_is_refused(trained, tmp_path):
    """A bit flipped in a stored weight loads silently with torch.load (tensors are stored raw); the
    digest recorded at saving finds it: one line, exit 2. A checkpoint saved without a digest loads."""
    damaged = tmp_path / "run"
    shutil.copytree(trained["run"], damaged)
    path = damaged / "checkpoint.pt"
    state = torch.load(path, map_location="cpu", weights_only=True)
    assert state["tensors_sha256"]
    name = next(k for k, v in state["model"].items() if v.is_floating_point() and v.numel())
    state["model"][name].reshape(-1).view(torch.int32)[0] ^= 1 << 3  # one bit of one weight
    torch.save(state, path)
    assert_bad_input(run("evaluate", "--run", damaged, "--store", trained["store"], "--no-plots"),
                     "do not match the digest")
    del state["tensors_sha256"]
    torch.save(state, path)
    assert load_run(damaged)["model"][name].shape == state["model"][name].shape


def test_a_flipped_bit_in_a_stored_case_is_found_on_every_read(trained, tmp_path):
    """Every chunk carries a CRC-32C: one flipped bit in one case's chunk makes export, evaluate and
    train refuse in one line naming shape and case, and status --verify lists it (exit 1)."""
    store = tmp_path / "flipped.zarr"
    shutil.copytree(trained["store"], store)
    flip_byte(store, 0, "unloaded", 1, bit=0x10)  # inside case 1's chunk of the shape's shard
    assert_bad_input(run("export", "--store", store, "--shape", 0, "--case", 1, "-o", tmp_path / "c.vtu"),
                     "shape 0 case 1 is damaged", "checksum")
    assert not (tmp_path / "c.vtu").exists()
    assert run("export", "--store", store, "--shape", 0, "--case", 0, "-o", tmp_path / "ok.vtu").exit_code == 0
    assert_bad_input(run("evaluate", "--run", trained["run"], "--store", store, "--split", "all", "--no-plots",
                         "--out", tmp_path / "ev"), "shape 0 case 1 is damaged")
    r = run("status", "--store", store, "--verify")
    assert r.exit_code == 1 and "damaged: shape 0 case 1: its checksum does not match" in r.output, r.output
    r = run("status", "--store", trained["store"], "--verify")
    assert r.exit_code == 0 and "read back intact" in r.output, r.output


def test_fine_tuning_starts_from_the_parents_weights_and_records_it(trained, tmp_path):
    """--init-from: the first epoch (at a learning rate too small to move the weights) validates at the
    parent's validation loss, not at a fresh network's; config.json and the checkpoint record the
    parent's file and digest and keep its normalisation; a rerun resumes only with the same parent."""
    parent = load_run(trained["run"])
    common = ("--store", trained["store"], "--no-ray", "--device", "cpu", "--batch-size", 8, "--lr", 1e-9)

    def first_val_loss(run_dir):
        return float((run_dir / "metrics.csv").read_text().splitlines()[1].split(",")[4])

    ft, scratch = tmp_path / "ft", tmp_path / "scratch"
    r = run("train", *common, "--run-dir", ft, "--epochs", 1, "--init-from", trained["run"])
    assert r.exit_code == 0, r.output
    assert "starting from" in r.output and "fresh optimiser" in r.output
    assert run("train", *common, "--run-dir", scratch, "--epochs", 1).exit_code == 0
    assert first_val_loss(ft) == pytest.approx(parent["best_val"], rel=1e-4)
    assert abs(first_val_loss(scratch) - parent["best_val"]) > 100 * abs(first_val_loss(ft) - parent["best_val"])
    config = json.loads((ft / "config.json").read_text())
    assert config["init_from"] == str((trained["run"] / "checkpoint.pt").resolve())
    assert config["init_from_sha256"] == parent["tensors_sha256"]
    child = load_run(ft)
    assert child["normalisation"] == parent["normalisation"] and child["optimizer"]["state"]
    assert child["train_config"]["init_from_sha256"] == parent["tensors_sha256"]
    # the shape range its warnings check is both runs' training shapes (here the same store: each twice)
    own = len(child["split"]["train"] and {k[0] for k in child["split"]["train"]})
    assert len(child["train_descriptors"]["shapes"]) == len(parent["train_descriptors"]["shapes"]) + own
    r = run("train", *common, "--run-dir", ft, "--epochs", 2, "--init-from", trained["run"] / "checkpoint.pt")
    assert r.exit_code == 0 and "resuming" in r.output, r.output
    assert_bad_input(run("train", *common, "--run-dir", ft, "--epochs", 3), "init_from_sha256")


def test_fine_tuning_refuses_another_network_or_a_damaged_parent(trained, tmp_path):
    common = ("train", "--store", trained["store"], "--no-ray", "--run-dir", tmp_path / "ft", "--epochs", 1)
    assert_bad_input(run(*common, "--init-from", trained["run"], "--config", "A1"),
                     "--init-from", "holds the network paper", "this command trains no-cycle")
    damaged = tmp_path / "damaged"
    shutil.copytree(trained["run"], damaged)
    state = torch.load(damaged / "checkpoint.pt", map_location="cpu", weights_only=True)
    name = next(k for k, v in state["best_model"].items() if v.is_floating_point() and v.numel())
    state["best_model"][name].reshape(-1)[0] += 1.0
    torch.save(state, damaged / "checkpoint.pt")
    assert_bad_input(run(*common, "--init-from", damaged), "do not match the digest")
    assert_bad_input(run(*common, "--init-from", tmp_path / "nowhere"), "--init-from", "no checkpoint at")
    assert_bad_input(run(*common, "--init-from", trained["run"], "--config", "pca"), "--init-from", "PCA")
    assert not (tmp_path / "ft").exists()


def test_a_full_disk_while_saving_a_checkpoint_is_one_line_and_the_rerun_resumes(trained, tmp_path, monkeypatch):
    """ENOSPC while the second epoch's checkpoint is written (the failure injected where the bytes reach
    the file): exit 1, one line naming the run's folder and the way to resume, no temporary file left,
    the first epoch's checkpoint intact; the same command then resumes from it."""
    import builtins
    import errno

    run_dir = tmp_path / "run"
    args = ("train", "--store", trained["store"], "--run-dir", run_dir, "--no-ray", "--batch-size", 8, "--device", "cpu")
    assert run(*args, "--epochs", 1).exit_code == 0
    real_open = builtins.open

    def full_disk_open(file, mode="r", *a, **kw):
        if "w" in mode and str(file).startswith(str(run_dir / ".checkpoint.")):
            handle = real_open(file, mode, *a, **kw)
            handle.close()
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_open(file, mode, *a, **kw)

    monkeypatch.setattr(builtins, "open", full_disk_open)
    r = run(*args, "--epochs", 2)
    monkeypatch.setattr(builtins, "open", real_open)
    assert r.exit_code == 1 and isinstance(r.exception, SystemExit), r.output
    errors = [ln for ln in r.output.splitlines() if ln.startswith("heartctl: error:")]
    assert errors == [f"heartctl: error: disk full saving a checkpoint in {run_dir} (No space left on device); the run "
                      f"keeps its last checkpoint: free space and rerun the same command to resume from it"], r.output
    assert "Traceback" not in r.output
    assert sorted(p.name for p in run_dir.iterdir() if p.name.startswith(".")) == []
    assert load_run(run_dir)["epoch"] == 1
    again = run(*args, "--epochs", 2)
    assert again.exit_code == 0, again.output
    assert load_run(run_dir)["epoch"] == 2


def test_a_full_disk_in_a_ray_train_failure_is_found_and_named(tmp_path):
    """Ray Train wraps a worker's error (or its own, copying a reported checkpoint into the run's
    storage): a DiskFullError or an OSError ENOSPC anywhere in that chain becomes the one line."""
    import errno

    from trainer.training.checkpoint import DiskFullError
    from trainer.training.ray_train import worker_disk_full

    class WorkerGroupError(Exception):
        def __init__(self, failures):
            super().__init__("Training failed due to worker errors")
            self.worker_failures = failures

    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as exc:
            raise RuntimeError("persisting the checkpoint failed") from exc
    except RuntimeError as exc:
        wrapped = WorkerGroupError({0: exc})
    found = worker_disk_full(wrapped, tmp_path)
    assert isinstance(found, DiskFullError) and f"disk full saving a checkpoint in {tmp_path}" in str(found)
    assert worker_disk_full(WorkerGroupError({0: ValueError("other")}), tmp_path) is None


def test_evaluate_says_a_run_is_unfinished(trained, tmp_path):
    """A run killed in training (its checkpoint of epoch 2 of 6, not its last): evaluate's table comes
    with one warning naming the epoch it stopped at; --json carries it."""
    from trainer.training.checkpoint import save_checkpoint

    cut = tmp_path / "cut"
    shutil.copytree(trained["run"], cut)
    state = load_run(cut)
    state.update(finished=False, epoch=2, train_config={**state["train_config"], "epochs": 6})
    save_checkpoint(cut / "checkpoint.pt", {k: v for k, v in state.items() if k not in ("format", "version")})
    r = run("evaluate", "--run", cut, "--store", trained["store"], "--no-plots", "--out", tmp_path / "e")
    assert r.exit_code == 0, r.output
    warnings = [ln for ln in r.output.splitlines() if ln.startswith("warning:")]
    assert warnings == [f"warning: run {cut} is unfinished: it stopped at epoch 2 of 6 (killed, or still training); "
                        f"`heartctl train` with the same --run-dir finishes it"], r.output
    r = run("evaluate", "--run", cut, "--store", trained["store"], "--no-plots", "--json", "--out", tmp_path / "j")
    assert json.loads(r.output.strip().splitlines()[-1])["unfinished_runs"] == [{"run": str(cut), "epoch": 2, "epochs": 6}]
    r = run("evaluate", "--run", trained["run"], "--store", trained["store"], "--no-plots", "--out", tmp_path / "f")
    assert "unfinished" not in r.output
