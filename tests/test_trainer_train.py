"""The plain training loop (checkpoint, metrics CSV, resume, refusal to mix runs), safe checkpoint
loading, the PCA baseline, Ray Train on gloo CPU workers resuming a plain run, and evaluation
metrics against hand-computed values."""
from __future__ import annotations

import csv
import os
import pickle
from dataclasses import replace

import numpy as np
import pytest
import torch

from trainer.training.checkpoint import load_checkpoint, load_run, save_checkpoint
from trainer.config import PAPER, TrainConfig, named_config
from trainer.errors import TrainerError
from trainer.evaluation.evaluate import evaluate_run
from trainer.training.loop import Dist, fit
from trainer.evaluation.metrics import case_metrics, fraction_within, hausdorff, nn_mean_distance, nodewise_error
from trainer.evaluation.predict import Predictor
from trainer.training.schedule import cosine_lr
from gloo_ranks import refusal_rank, spawn_ranks
from trainer_fixtures import make_tiny_store

SMALL = replace(PAPER, hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_tiny_store(tmp_path_factory.mktemp("trainer_train") / "tiny.zarr", shapes=4)


def _cfg(store, **kw) -> TrainConfig:
    base = dict(store=store, config_name="paper-small", model=SMALL, epochs=2, batch_size=4, num_threads=1)
    base.update(kw)
    return TrainConfig(**base)


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_plain_loop_checkpoints_and_resumes(store, tmp_path):
    run = tmp_path / "run"
    s = fit(_cfg(store), run)
    assert s.epoch == 2 and s.resumed_from == 0
    state = load_run(run)
    assert state["epoch"] == 2 and state["kind"] == "gnn"
    assert {"model", "best_model", "optimizer", "scheduler", "normalisation", "train_config", "split"} <= set(state)
    assert len(_rows(run / "metrics.csv")) == 2
    assert set(_rows(run / "metrics.csv")[0]) >= {"epoch", "train_loss", "val_loss", "val_md_mm", "lr"}
    s = fit(_cfg(store, epochs=3), run)
    assert s.resumed_from == 2 and s.epoch == 3 and s.epochs_run == 1
    assert [int(r["epoch"]) for r in _rows(run / "metrics.csv")] == [1, 2, 3]
    assert load_run(run)["epoch"] == 3
    with pytest.raises(TrainerError, match=r"started with sr 1.0 \(this command: 0.5\)"):
        fit(_cfg(store, epochs=3, sr=0.5), run)
    with pytest.raises(TrainerError, match="model settings other than"):
        fit(_cfg(store, epochs=3, model=replace(SMALL, cycle=False)), run)
    with pytest.raises(TrainerError, match=r"rotate_deg 0.0 \(this command: 10.0\)"):
        fit(_cfg(store, epochs=3, rotate_deg=10.0), run)
    # options that change what an epoch is (a silent change mixed two recipes in one run)
    for option, value in (("batch_size", 3), ("lr_schedule", "cosine"), ("labelled_share", 0.5)):
        with pytest.raises(TrainerError, match=f"started with {option} "):
            fit(_cfg(store, epochs=3, **{option: value}), run)


def test_resume_removes_the_temporary_files_of_a_save_cut_short(store, tmp_path):
    """A run killed while saving leaves save_checkpoint's temporary file (`.checkpoint.XXXX.pt`, as
    mkstemp names it); resuming deletes it and touches no other file."""
    run = tmp_path / "run"
    fit(_cfg(store, epochs=1), run)
    stale = [run / ".checkpoint.k3j_9x2a.pt", run / ".checkpoint.q0w8e7r6.pt"]
    for path in stale:
        path.write_bytes(b"PK\x03\x04 half a zip")
    kept = [run / "checkpoint_copy.pt", run / ".checkpoint.notes"]
    for path in kept:
        path.write_bytes(b"mine")
    logged = []
    s = fit(_cfg(store, epochs=2), run, Dist(log=logged.append))
    assert s.resumed_from == 1 and load_run(run)["epoch"] == 2
    assert not any(p.exists() for p in stale) and all(p.exists() for p in kept)
    assert any("removed 2 temporary checkpoint file(s)" in line for line in logged), logged


def test_resume_obeys_a_new_patience_and_learning_rate(store, tmp_path):
    """A run stopped early trains on when rerun with a longer --patience; a new --lr is the rate the
    resumed epochs use (the plateau schedule would otherwise keep the saved one)."""
    run = tmp_path / "stop"
    s = fit(_cfg(store, epochs=8, patience=1, lr=0.1), run)  # a rate this high stops it within a few epochs
    assert s.stopped_early and s.epoch < 8
    assert fit(_cfg(store, epochs=8, patience=1, lr=0.1), run).epochs_run == 0  # same patience: stays stopped
    s2 = fit(_cfg(store, epochs=s.epoch + 1, patience=50, lr=3e-4), run)
    assert s2.epochs_run == 1 and s2.epoch == s.epoch + 1
    assert float(_rows(run / "metrics.csv")[-1]["lr"]) == pytest.approx(3e-4)


def test_resumed_run_equals_an_uninterrupted_one(store, tmp_path):
    """Dropout draws, rotation angles, optimiser, scheduler and weight average all continue where
    they stopped: two epochs in one go and one epoch + a resumed second give the same weights (one
    thread, CPU)."""
    model = replace(SMALL, ema_decay=0.9, reverse_weight=1.0, cycle_grad="teacher")
    fit(_cfg(store, model=model, rotate_deg=30.0), tmp_path / "once")
    fit(_cfg(store, model=model, rotate_deg=30.0, epochs=1), tmp_path / "twice")
    fit(_cfg(store, model=model, rotate_deg=30.0), tmp_path / "twice")
    once, twice = load_run(tmp_path / "once"), load_run(tmp_path / "twice")
    for part in ("model", "best_model"):
        for name, w in once[part].items():
            torch.testing.assert_close(twice[part][name], w, rtol=0, atol=0, msg=f"{part}.{name}")
    assert once["history"][-1]["train_loss"] == twice["history"][-1]["train_loss"]


def test_resume_does_not_lean_on_a_saved_generator_state(store, tmp_path):
    """Each epoch's dropout draws come from (seed, epoch, rank), not from a generator state carried in
    the checkpoint: under DDP rank 0 writes the checkpoint for every rank, and on CUDA its generator
    state is not another rank's. A resume with a foreign generator state (here: a checkpoint whose
    saved state was another process's) still equals the uninterrupted run, and ranks draw apart."""
    from trainer.training.loop import seed_epoch

    fit(_cfg(store), tmp_path / "once")
    fit(_cfg(store, epochs=1), tmp_path / "twice")
    path = tmp_path / "twice" / "checkpoint.pt"
    state = load_checkpoint(path)
    torch.manual_seed(12345)
    foreign = torch.get_rng_state()
    state = {k: v for k, v in state.items() if k not in ("format", "version")}
    state["rng_torch"] = foreign  # what an older heartctl restored on every rank
    save_checkpoint(path, state)
    torch.manual_seed(999)  # and this process's own generator is elsewhere too
    fit(_cfg(store), tmp_path / "twice")
    once, twice = load_run(tmp_path / "once"), load_run(tmp_path / "twice")
    for name, w in once["model"].items():
        torch.testing.assert_close(twice["model"][name], w, rtol=0, atol=0, msg=name)
    draws = []
    for rank in (0, 1, 0):
        seed_epoch(0, 3, rank)
        draws.append(torch.rand(4))
    assert torch.equal(draws[0], draws[2]) and not torch.equal(draws[0], draws[1])


def test_cosine_schedule_sets_each_epochs_rate(store, tmp_path):
    """--lr-schedule cosine: epoch e trains at cosine_lr(e, E, lr), from lr down towards 1 % of it
    (run with the wall-coordinate model, which must train end to end too)."""
    model = replace(SMALL, node_features="wall", cycle=False, ema_decay=0.9)
    s = fit(_cfg(store, model=model, epochs=3, lr_schedule="cosine", lr=2e-3), tmp_path / "cos")
    assert s.epoch == 3
    rates = [float(r["lr"]) for r in _rows(tmp_path / "cos" / "metrics.csv")]
    assert rates == pytest.approx([cosine_lr(e, 3, 2e-3) for e in range(3)], rel=1e-6)
    assert rates[0] == pytest.approx(2e-3) and rates[0] > rates[1] > rates[2] > 2e-5
    assert cosine_lr(99, 100, 1.0) == pytest.approx(0.01, abs=3e-4)
    with pytest.raises(TrainerError, match="`lr_schedule`"):
        _cfg(store, lr_schedule="step")


def test_checkpoints_load_without_unpickling_objects(tmp_path):
    good = tmp_path / "good.pt"
    from trainer.config import TrainConfig
    from trainer.data.normalisation import Normalisation

    norm = Normalisation((0.0, 0.0, -30.0), 30.0, 2.0, (4, 50, 60, -70), (14, 300, 70, -60)).as_dict()
    save_checkpoint(good, {"kind": "gnn", "train_config": TrainConfig(store="s.zarr").as_dict(), "normalisation": norm,
                           "fingerprint": {}, "split": {}, "epoch": 1, "model": {"w": torch.ones(2)}})
    assert load_checkpoint(good)["model"]["w"].sum() == 2
    umask = os.umask(0)
    os.umask(umask)
    assert good.stat().st_mode & 0o777 == 0o666 & ~umask  # an ordinary file, like the run's other files
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.pt"]  # no temporary file left
    evil = tmp_path / "evil.pt"
    torch.save({"format": "heartctl.trainer.checkpoint", "payload": _Evil()}, evil)  # an arbitrary object
    with pytest.raises(TrainerError, match="cannot read checkpoint"):
        load_checkpoint(evil)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint at all")
    with pytest.raises(TrainerError, match="cannot read checkpoint"):
        load_checkpoint(junk)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(1)}, other)
    with pytest.raises(TrainerError, match="not a heartctl"):
        load_checkpoint(other)
    with pytest.raises(TrainerError, match="no checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")


class _Evil:
    def __reduce__(self):
        return (pickle.loads, (b"I1\n.",))


@pytest.mark.parametrize("n,world", [(7, 2), (5, 3), (1, 2), (6, 3)])
def test_validation_shards_cover_each_case_once(n, world):
    from trainer.training.loop import validation_shard

    shards = [validation_shard(list(range(n)), rank, world) for rank in range(world)]
    assert sorted(i for s in shards for i in s) == list(range(n))


def test_result_files_are_whole_or_absent(tmp_path):
    """write_csv / write_json: an ordinary file mode (not mkstemp's 0600), and a writer that fails
    leaves neither the target nor its temporary file."""
    import json

    from trainer.files import write_csv, write_json

    write_csv(tmp_path / "a.csv", [{"x": 1, "y": 2}], ["y"])
    assert (tmp_path / "a.csv").read_text().split() == ["y", "2"]
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "a.csv").stat().st_mode & 0o777 == 0o666 & ~umask
    write_json(tmp_path / "b.json", {"md_mm": 0.5})
    assert json.loads((tmp_path / "b.json").read_text()) == {"md_mm": 0.5}
    with pytest.raises(TypeError):
        write_json(tmp_path / "c.json", {"bad": {1, 2}})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b.json"]


def test_metrics_on_a_hand_computed_case():
    true = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    pred = true + np.array([[0.05, 0, 0], [0, 0.5, 0], [0, 0, -2.0], [0, 0, 0]])
    err = nodewise_error(pred, true)
    np.testing.assert_allclose(err, [0.05, 0.5, 2.0, 0.0])
    assert fraction_within(err, 1.0) == 0.75 and fraction_within(err, 0.1) == 0.5
    assert hausdorff(pred, true) == pytest.approx(2.0)  # every node's nearest is its own partner here
    assert nn_mean_distance(pred, true) == pytest.approx(2.55 / 4)
    m = case_metrics(pred, true)
    assert m["md_mm"] == pytest.approx(2.55 / 4)
    assert m["sd_mm"] == pytest.approx(np.sqrt(np.mean((np.array([0.05, 0.5, 2.0, 0.0]) - 2.55 / 4) ** 2)))
    # Hausdorff is of node sets: a node moved onto another one's place costs nothing
    swapped = true[[1, 0, 2, 3]]
    assert hausdorff(swapped, true) == 0.0 and case_metrics(swapped, true)["md_mm"] > 0


def test_evaluate_equals_hand_computed_metrics(store, tmp_path):
    run = tmp_path / "run"
    fit(_cfg(store, epochs=1), run)
    report = evaluate_run(run, store, "test", plots=False)
    state = load_run(run)
    pred = Predictor(state)
    from trainer.data.store_cases import read_store

    cases = read_store(store)
    keys = [tuple(k) for k in state["split"]["test"]]
    md, sd, hd, d1, d01 = [], [], [], [], []
    for k in keys:
        f = cases.features[k[0]]
        guess = f.ed_mm + pred.predict(f, cases.params[k])
        e = np.sqrt(((guess - cases.unloaded[k]) ** 2).sum(axis=1))
        md.append(e.mean())
        sd.append(e.std())
        d1.append((e < 1.0).mean())
        d01.append((e < 0.1).mean())
        dists = np.sqrt(((guess[:, None, :] - cases.unloaded[k][None, :, :]) ** 2).sum(axis=2))
        hd.append(max(dists.min(axis=1).max(), dists.min(axis=0).max()))
    s = report.as_dict()
    assert s["cases"] == len(keys)
    assert s["md_mm"] == pytest.approx(np.mean(md), rel=1e-6)
    assert s["sd_mm"] == pytest.approx(np.mean(sd), rel=1e-6)
    assert s["hd_mm"] == pytest.approx(np.mean(hd), rel=1e-6)
    assert s["dsc_1mm"] == pytest.approx(np.mean(d1)) and s["dsc_01mm"] == pytest.approx(np.mean(d01))
    assert s["ms_per_case"] > 0
    out = tmp_path / "run" / "eval_test"
    assert (out / "cases.csv").is_file() and (out / "by_parameter.csv").is_file() and (out / "summary.json").is_file()
    assert len(_rows(out / "cases.csv")) == len(keys)


def test_evaluate_prices_the_linear_response_of_networks_that_take_it(store, tmp_path):
    """ms_per_case times the network alone; a network with the linear FE response as node input
    also pays that solve once per mesh, which evaluate reports beside it (None for the others)."""
    run = tmp_path / "resp"
    fit(_cfg(store, config_name="resp-small", model=replace(SMALL, node_features="wall-response"), epochs=1), run)
    report = evaluate_run(run, store, "test", plots=False)
    assert report.response_ms_per_mesh > 0 and report.mean("md_mm") > 0
    plain = tmp_path / "plain"
    fit(_cfg(store, epochs=1), plain)
    assert evaluate_run(plain, store, "test", plots=False).response_ms_per_mesh is None


@pytest.mark.slow
def test_compiled_training_learns_what_eager_training_learns(store, tmp_path, monkeypatch):
    """--compile: torch.compile runs the training step (the attention graph built inside it) and
    gives the eager run's losses; the checkpoint holds the plain model's weights.

    TorchDynamo traces heartctl's model (its graph breaks and recompilations included) and runs
    the training step through the frames it rewrote; the graphs it captures run eagerly (backend
    "eager"). Inductor's code generation for the ~25 graphs of the step would add ~50 s on a 2-core
    box with a cold compile cache, and tests torch rather than heartctl."""
    import functools

    monkeypatch.setattr(torch, "compile", functools.partial(torch.compile, backend="eager"))
    cfg = _cfg(store, model=replace(SMALL, dropout=0.0), epochs=1)
    eager, compiled = fit(cfg, tmp_path / "eager"), fit(replace(cfg, compile=True), tmp_path / "compiled")
    a, b = _rows(tmp_path / "eager" / "metrics.csv")[0], _rows(tmp_path / "compiled" / "metrics.csv")[0]
    for k in ("train_loss", "val_loss"):
        assert float(b[k]) == pytest.approx(float(a[k]), rel=1e-4)
    weights = load_run(tmp_path / "compiled")["best_model"]
    assert set(weights) == set(load_run(tmp_path / "eager")["best_model"])  # no "_orig_mod." prefixes
    assert eager.epochs_run == compiled.epochs_run == 1


def test_single_cases_go_through_one_prepared_runner_per_mesh(store, tmp_path):
    """Batch size 1 (unload, evaluate's single-case timing): one PreparedCase per mesh, made on first
    use and kept for the last few meshes; the answers are the batched ones."""
    from trainer.data.store_cases import read_store

    run = tmp_path / "run"
    fit(_cfg(store, epochs=1), run)
    pred = Predictor(load_run(run))
    cases = read_store(store)
    items = [(cases.features[k[0]], cases.params[k], None) for k in cases.keys]
    meshes = {id(f) for f, _, _ in items}
    assert len(meshes) > 1
    one, many = pred.predict_many(items, 1), pred.predict_many(items, 32)
    for a, b in zip(one, many):
        np.testing.assert_allclose(a, b, atol=1e-5 * np.abs(b).max())
    assert set(pred._runners) == meshes  # one runner per mesh, not per case
    first = next(iter(pred._runners.values()))[1]
    pred.predict_many(items, 1)
    assert next(iter(pred._runners.values()))[1] is first  # reused, not rebuilt
    pred._single(*items[0][:2], keep=1)
    assert list(pred._runners) == [id(items[0][0])]  # the oldest dropped beyond `keep`
    assert pred.time_ms_per_case(items, 1) > 0 and pred.time_ms_per_case(items, 4) > 0


def test_rotation_averaged_prediction_turns_with_the_mesh(store, tmp_path):
    """Averaged over K turns about the long axis, the network's answer is exactly symmetric under a
    turn by 2π/K of the input (about the normalisation centre); K = 1 is the plain network."""
    from dataclasses import replace as dc_replace

    from trainer.data.store_cases import read_store

    run = tmp_path / "run"
    fit(_cfg(store, epochs=1), run)
    state = load_run(run)
    cases = read_store(store)
    key = tuple(state["split"]["test"][0])
    feat, params = cases.features[key[0]], cases.params[key]
    centre = np.asarray(state["normalisation"]["centre_mm"])
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # a quarter turn about z
    turned = dc_replace(feat, ed_mm=(feat.ed_mm - centre) @ rot.T + centre)
    plain, averaged = Predictor(state), Predictor(state, rotations=4)
    d, d_turned = averaged.predict(feat, params), averaged.predict(turned, params)
    scale = np.abs(d).max()
    np.testing.assert_allclose(d_turned, d @ rot.T, atol=1e-4 * scale)
    assert np.abs(plain.predict(turned, params) - plain.predict(feat, params) @ rot.T).max() > 1e-3 * scale
    np.testing.assert_array_equal(Predictor(state, rotations=1).predict(feat, params), plain.predict(feat, params))
    assert averaged.time_ms_per_case([(feat, params, None)]) > 0
    with pytest.raises(TrainerError, match="`rotations`"):
        Predictor(state, rotations=0)


def test_pca_baseline_fits_and_evaluates(store, tmp_path):
    run = tmp_path / "pca"
    fit(_cfg(store, config_name="pca", model=named_config("pca")), run)
    assert load_run(run)["kind"] == "pca"
    with pytest.raises(TrainerError, match="PCA baseline takes no rotations"):
        Predictor(load_run(run), rotations=4)
    r = evaluate_run(run, store, "test", plots=False)
    # the synthetic displacement is smooth and low-dimensional: the baseline should get close
    assert r.mean("md_mm") < 0.5 and r.cases > 0
    from trainer.network.pca import RIDGE_GRID, PCABaseline
    fitted = load_run(run)["best_model"]
    assert float(fitted["ridge"]) in RIDGE_GRID  # chosen on the validation cases
    older = {k: v for k, v in fitted.items() if k != "feature_map"}  # a fit without the feature map
    with pytest.raises(TrainerError, match="older feature map"):
        PCABaseline(older)
    # the ridge chosen on the validation cases is the grid's best there
    from trainer.data.store_cases import read_store
    from trainer.data.normalisation import Normalisation
    state, cases = load_run(run), read_store(store)
    norm = Normalisation.from_dict(state["normalisation"])
    train, val = ([tuple(k) for k in state["split"][name]] for name in ("train", "val"))
    disp = {k: cases.displacement(k) for k in train + val}
    val_disp = {k: disp[k] for k in val}

    def pca(**kw):
        return PCABaseline.fit(cases.features, train, cases.params, disp, norm, **kw)

    grid_md = [pca(ridge=r).mean_distance_mm(cases.features, cases.params, val_disp, norm) for r in RIDGE_GRID]
    chosen = pca(validation=val_disp)
    assert float(chosen.s["ridge"]) == RIDGE_GRID[int(np.argmin(grid_md))]
    assert chosen.mean_distance_mm(cases.features, cases.params, val_disp, norm) == pytest.approx(min(grid_md))


@pytest.mark.slow
def test_ray_train_resumes_a_plain_run_and_a_divergence_is_one_line(store, tmp_path, local_ray):
    """Two gloo CPU workers take a run on from the plain loop's checkpoint.pt (a run Ray Train starts
    from scratch, two workers on two nodes, checkpoints and resumes: tests/test_cluster_nodes.py)."""
    from trainer.training.ray_train import serves_state_api, train_with_ray

    run = tmp_path / "ray_run"
    assert not serves_state_api()  # so the runs below go without the placement-group cleaner
    fit(_cfg(store, epochs=2), run)
    # a diverging epoch: the driver gets the one-line error (not Ray's retried worker failure), the run
    # directory keeps epoch 2, and a rerun at a sane rate resumes from it past Ray's divergence marker
    with pytest.raises(TrainerError, match="diverged in epoch 3"):
        train_with_ray(_cfg(store, epochs=5, lr=1e12), run, gpus=0, cpu_workers=2, max_failures=2)
    assert load_run(run)["epoch"] == 2
    # a rerun with nothing left to train reports nothing: the divergence marker Ray restores (its latest
    # checkpoint's metrics) is the earlier call's, not a new divergence, and the state it resumes from
    # is the run's, not the marker (a run resumed through Ray and trained on: tests/test_cluster_nodes.py)
    assert train_with_ray(_cfg(store, epochs=2), run, gpus=0, cpu_workers=1, max_failures=0).epoch == 2
    assert [h["epoch"] for h in load_run(run)["history"]] == [1, 2]


def test_a_worker_that_cannot_read_the_store_refuses_in_one_line_naming_itself(tmp_path):
    """The driver's checks passed (e.g. a path on the driver's own disk) but a worker cannot read the
    store: its refusal names it, and on another machine says what every worker needs."""
    from trainer.training.ray_train import worker_data

    missing = _cfg(str(tmp_path / "gone" / "missing.zarr"))
    bundle, here = worker_data(missing, 0, "10.0.0.2", same_host=True)
    assert bundle is None and here == f"folder {tmp_path / 'gone'} does not exist (Ray worker 0 on 10.0.0.2)"
    _, elsewhere = worker_data(missing, 1, "10.0.0.3", same_host=False)
    assert "(Ray worker 1 on 10.0.0.3, not the driver's machine: every worker must reach the store" in elsewhere


def test_a_refusal_before_any_checkpoint_leaves_nothing(store, tmp_path, monkeypatch, local_ray):
    """The workers refused before any checkpoint (Ray Train's run stubbed by what it returns then: the
    refusal marker's metrics, no checkpoint): the driver raises the refusal as its one line and
    removes Ray's storage and the run directory it made, so nothing is left to resume from (a
    refusal reported through real workers: the divergence above)."""
    from types import SimpleNamespace

    from ray.train.torch import TorchTrainer

    from trainer.training.ray_train import REFUSED, train_with_ray

    run = tmp_path / "fresh"
    refusal = "folder /elsewhere does not exist (Ray worker 0 on 10.0.0.2)"

    def refused(trainer):
        (run / "ray" / "checkpoint_tmp").mkdir(parents=True)  # what Ray's storage holds by then
        return SimpleNamespace(error=None, metrics={REFUSED: refusal, "heartctl_call": trainer.train_loop_config["call"]},
                               best_checkpoints=[], checkpoint=None)

    monkeypatch.setattr(TorchTrainer, "fit", refused)
    with pytest.raises(TrainerError) as info:
        train_with_ray(_cfg(store), run, gpus=0, cpu_workers=2, max_failures=2)
    assert str(info.value) == refusal and not run.exists()
    run.mkdir()  # the user's own folder stays, empty
    with pytest.raises(TrainerError):
        train_with_ray(_cfg(store), run, gpus=0, cpu_workers=2, max_failures=2)
    assert run.is_dir() and not any(run.iterdir())


def test_a_refusal_on_one_rank_stops_every_rank(tmp_path):
    """Only rank 1 cannot read the store: every rank gets its message (a collective, so rank 0 does not
    wait for ever in DDP's first broadcast), and with no refusal every rank trains."""
    got = spawn_ranks(refusal_rank, 2, str(tmp_path / "rendezvous"))
    assert got == [(0, "cannot read store s.zarr (rank 1)", None), (1, "cannot read store s.zarr (rank 1)", None)]


def test_local_ray_setup_hook_resolves_and_quietens_the_autoscaling_client():
    """The hook is given to Ray as a dotted path: it must import, and it drops the warnings (not the
    errors) of the autoscaling-coordinator client (a traceback when its first request times out on a
    busy box), also after a logging.config.dictConfig of their parent, as Ray Train's controller runs."""
    import importlib
    import logging
    import logging.config

    from trainer.training.ray_local import LOCAL_RAY_NOISY_LOGGERS, NO_DASHBOARD_SETUP_HOOK

    module, name = NO_DASHBOARD_SETUP_HOOK.rsplit(".", 1)
    hook = getattr(importlib.import_module(module), name)
    loggers = [logging.getLogger(n) for n in LOCAL_RAY_NOISY_LOGGERS]
    before = [list(lg.filters) for lg in loggers]
    try:
        hook()
        hook()  # idempotent
        logging.config.dictConfig({"version": 1, "disable_existing_loggers": False,
                                   "loggers": {"ray.train": {"level": "INFO"}}})
        for lg in loggers:
            assert lg.filter(logging.makeLogRecord({"levelno": logging.WARNING})) is False
            assert lg.filter(logging.makeLogRecord({"levelno": logging.ERROR}))
            assert len(lg.filters) == len(before[loggers.index(lg)]) + 1
    finally:
        for lg, filters in zip(loggers, before):
            lg.filters = filters


def test_local_ray_environment_names_ray_trains_own_flags():
    """The local Ray's environment names the flags Ray Train reads (a renamed flag would bring back the
    preemption watcher's error line, or the 2 s checks, or the 60 s start timeout, in every local training run)."""
    pytest.importorskip("ray")
    from ray.train.v2._internal.constants import (ENABLE_PREEMPTION_WATCHER_ENV_VAR, HEALTH_CHECK_INTERVAL_S_ENV_VAR,
                                                  WORKER_GROUP_START_TIMEOUT_S_ENV_VAR)

    from trainer.training.ray_local import LOCAL_RAY_TRAIN_ENV

    assert set(LOCAL_RAY_TRAIN_ENV) == {ENABLE_PREEMPTION_WATCHER_ENV_VAR, HEALTH_CHECK_INTERVAL_S_ENV_VAR,
                                        WORKER_GROUP_START_TIMEOUT_S_ENV_VAR}
    assert LOCAL_RAY_TRAIN_ENV[ENABLE_PREEMPTION_WATCHER_ENV_VAR] == "0"


def test_the_placement_group_cleaner_is_dropped_and_nothing_else():
    """Without the State API the trainer's controller gets every default callback but the cleaner."""
    pytest.importorskip("ray")
    from ray.train import ScalingConfig
    from ray.train.torch import TorchTrainer
    from ray.train.v2._internal.callbacks.placement_group_callback import PlacementGroupCleanerCallback

    from trainer.training.ray_train import without_pg_cleaner

    trainer = TorchTrainer(lambda: None, scaling_config=ScalingConfig(num_workers=1))
    full = [type(c) for c in trainer._create_default_callbacks()]
    assert PlacementGroupCleanerCallback in full
    without_pg_cleaner(trainer)
    assert [type(c) for c in trainer._create_default_callbacks()] == [t for t in full if t is not PlacementGroupCleanerCallback]


def _captured(logger_name: str, emit) -> list[str]:
    import logging

    records = []
    handler = logging.Handler()
    handler.emit = lambda record: records.append(record.getMessage())
    logger = logging.getLogger(logger_name)
    logger.addHandler(handler)
    try:
        emit()
    finally:
        logger.removeHandler(handler)
    return records


def test_ray_notices_are_dropped_and_warnings_kept():
    """A local Ray's 'token authentication is enabled' notice (Ray's own function, emitting through Ray's
    own logger) is dropped, its warning that authentication is disabled is not; Ray Train's per-report
    INFO line in a worker is dropped, a warning on the same logger is not."""
    import logging

    from ray._private.authentication import authentication_token_setup as auth
    from ray.train.v2._internal.execution import storage

    from orchestrator.ray_session import RAY_AUTH_LOGGER, not_auth_enabled_notice
    from trainer.training.ray_train import RAY_REPORT_LOGGERS, quieten_checkpoint_reports

    assert auth.logger.name == RAY_AUTH_LOGGER and storage.logger.name in RAY_REPORT_LOGGERS
    auth_logger, report_logger = logging.getLogger(RAY_AUTH_LOGGER), storage.logger
    before = list(auth_logger.filters), list(report_logger.filters)
    try:
        auth_logger.addFilter(not_auth_enabled_notice)
        assert _captured(RAY_AUTH_LOGGER, auth._warn_token_auth_enabled) == []
        assert "disabled" in " ".join(_captured(RAY_AUTH_LOGGER, auth._warn_token_auth_disabled))
        quieten_checkpoint_reports()
        quieten_checkpoint_reports()  # idempotent
        assert len(report_logger.filters) == len(before[1]) + 1
        level = report_logger.level
        report_logger.setLevel(logging.INFO)
        try:
            got = _captured(storage.logger.name, lambda: (storage.logger.info("Checkpoint successfully created at: x"),
                                                          storage.logger.warning("upload failed")))
        finally:
            report_logger.setLevel(level)
        assert got == ["upload failed"]
    finally:
        auth_logger.filters, report_logger.filters = before


def test_a_workers_bad_input_reaches_the_driver_by_its_type():
    """Ray Train wraps a worker's exception (WorkerGroupError → the rank's wrapper → the exception):
    the TrainerError is found by type, the lowest rank's first; other failures give None."""
    pytest.importorskip("ray")
    from ray.train import WorkerGroupError
    from ray.train.v2._internal.exceptions import UserExceptionWithTraceback

    from trainer.training.ray_train import worker_trainer_error

    failures = {1: UserExceptionWithTraceback(TrainerError("rank 1's refusal"), "Traceback …"),
                0: UserExceptionWithTraceback(RuntimeError("rank 0 crashed"), "Traceback …")}
    found = worker_trainer_error(WorkerGroupError("two workers failed", failures))
    assert isinstance(found, TrainerError) and str(found) == "rank 1's refusal"
    crashed = {0: UserExceptionWithTraceback(RuntimeError("rank 0 crashed"), "Traceback …")}
    assert worker_trainer_error(WorkerGroupError("one worker failed", crashed)) is None
