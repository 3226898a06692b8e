"""A store grows with a larger --shapes: the count raised in its attributes, the added shapes meshed
and solved in the store's own layout (a shard per shape, or a version 1 store's chunk per case), the
done cases left byte for byte; a smaller --shapes is refused. The tests' shared two-CPU Ray (conftest.py); coarse
meshes (~200 nodes), the fast preset, two cases a shape."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import zarr
from typer.testing import CliRunner

from orchestrator.grid import SweepSpec
from orchestrator.plan import make_plan
from orchestrator.sweep import run_sweep
from storage.location import StoreError
from storage.reader import PairReader
from storage.schema import DONE, case_layout, inspect_store
from storage.status import summarize
from storage.writer import PairStore

ARGS = ["--pressures", "8,12", "--stiffness", "100", "--endo", "60", "--epi=-60", "--fidelity", "fast",
        "--nodes", "200"]


def spec(shapes: int) -> SweepSpec:
    return SweepSpec(shapes=shapes, pressure_mmhg=(8.0, 12.0), stiffness_pa=(100.0,), helix_endo_deg=(60.0,),
                     helix_epi_deg=(-60.0,), fidelity="fast", seed=0, nodes=200).validate()


@pytest.fixture
def ray_cluster(local_ray):
    return local_ray


def _snapshot(path: Path) -> dict:
    return {str(p.relative_to(path)): (hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir")
            for p in sorted(path.rglob("*")) if not p.name.endswith(".lock")}


def _version_1(location: str, sp: SweepSpec) -> None:
    """An empty store as schema version 1 makes it: a chunk per case, no case_layout attribute."""
    PairStore.create(location, {**sp.store_attrs(), "schema_version": 1})
    root = zarr.open_group(location, mode="r+")
    root.attrs.put({k: v for k, v in root.attrs.asdict().items() if k != "case_layout"})


def _grow(location: str) -> dict:
    """Solve 1 shape, then grow to 2; the first shape's files before and after, and the reports."""
    first = run_sweep(spec(1), location, progress=False)
    assert (first.done, first.failed) == (2, 0)
    stats_before = PairReader(location).stats(0)
    shape0 = _snapshot(Path(location) / "shapes" / "0")
    grown = run_sweep(spec(2), location, progress=False)
    return {"shape0": shape0, "stats0": stats_before, "report": grown}


def _check_grown(location: str, grown: dict) -> None:
    report = grown["report"]
    assert (report.done_before, report.submitted, report.done, report.total) == (2, 2, 2, 4)
    assert sorted(report.records) == [(1, 0, DONE), (1, 1, DONE)]  # only the added shape's cases ran
    assert _snapshot(Path(location) / "shapes" / "0") == grown["shape0"]  # done cases byte for byte
    reader = PairReader(location)
    np.testing.assert_array_equal(reader.stats(0), grown["stats0"])
    assert reader.attrs["grid"]["shapes"] == 2 and reader.shape_ids() == [0, 1]
    run = reader.attrs["runs"][-1]
    assert (run["shapes"], run["shapes_before"], run["done"]) == (2, 1, 2) and "ended_at" in run
    s = summarize(location).as_dict()
    assert (s["shapes"], s["done"], s["pending"], s["failed"]) == (2, 4, 0, 0)
    assert run_sweep(spec(2), location, progress=False).submitted == 0  # and it resumes as any store


@pytest.mark.slow
def test_a_larger_shapes_grows_the_store_and_keeps_its_done_cases(ray_cluster, tmp_path):
    loc = str(tmp_path / "g.zarr")
    grown = _grow(loc)
    _check_grown(loc, grown)
    shard = zarr.open_array(f"{loc}/shapes/1/unloaded", mode="r")
    assert shard.shards is not None  # the added shape in the store's layout: a shard per shape

    # a dry run of a further growth counts the added shape's cases and its meshing
    attrs = inspect_store(loc)
    plan = make_plan(spec(3), loc, attrs, calibration=False)
    assert (plan.cases, plan.done, plan.to_run, plan.grows_from, plan.shapes_to_mesh) == (6, 4, 2, 2, 1)
    from cli import app

    res = CliRunner().invoke(app, ["generate", "--store", loc, "--dry-run", "--shapes", "3"] + ARGS)
    assert res.exit_code == 0, res.output
    assert "growing the store from 2 shapes" in res.output and "6 cases; 4 done, 0 failed, 2 to run" in res.output

    # a smaller --shapes: one line, exit 2, the store untouched
    before = _snapshot(Path(loc))
    res = CliRunner().invoke(app, ["generate", "--store", loc, "--shapes", "1"] + ARGS)
    lines = [ln for ln in getattr(res, "stderr", res.output).strip().splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("heartctl: error:"), res.output
    assert "store has 2" in lines[0] and "shrinking a store is not supported" in lines[0]
    assert _snapshot(Path(loc)) == before
    # without --shapes the store's own count
    res = CliRunner().invoke(app, ["status", "--store", loc, "--json"])
    assert json.loads(res.stdout)["shapes"] == 2


@pytest.mark.slow
def test_a_version_1_store_grows_in_its_own_layout(ray_cluster, tmp_path):
    loc = str(tmp_path / "v1.zarr")
    _version_1(loc, spec(1))
    grown = _grow(loc)
    _check_grown(loc, grown)
    attrs = inspect_store(loc)
    assert attrs["schema_version"] == 1 and "case_layout" not in attrs and case_layout(attrs) == "chunk per case"
    for s in (0, 1):
        assert zarr.open_array(f"{loc}/shapes/{s}/unloaded", mode="r").shards is None
        chunks = sorted(str(p.relative_to(Path(loc))) for p in (Path(loc) / f"shapes/{s}/unloaded/c").rglob("*")
                        if p.is_file())
        assert chunks == [f"shapes/{s}/unloaded/c/0/0/0", f"shapes/{s}/unloaded/c/1/0/0"]  # an object per case


def test_shape_count_checks_without_ray(tmp_path):
    """The request check, the store's own guard, and a training run's store fingerprint."""
    from trainer.data.store_cases import check_fingerprint, store_fingerprint
    from trainer.errors import TrainerError

    small, large = spec(2).store_attrs(), spec(3).store_attrs()
    assert spec(3).conflicts(small) == [] and spec(3).grows(small) == 2 and spec(2).grows(small) is None
    assert spec(1).conflicts(small) == ["shapes=1 (store has 2; shrinking a store is not supported)"]

    store = PairStore.create(str(tmp_path / "s.zarr"), small)
    with pytest.raises(StoreError, match="shrinking"):
        store.grow_shapes(1)
    store.grow_shapes(3)
    assert inspect_store(str(tmp_path / "s.zarr"))["grid"]["shapes"] == 3 == PairStore.open(store.location).shapes

    # a run trained on the 2-shape store does not resume on it grown (its split would change): one line
    saved, now = store_fingerprint(small, {}), store_fingerprint(large, {})
    with pytest.raises(TrainerError, match=r"changed since the run started: it grew from 2 to 3 shapes") as err:
        check_fingerprint(saved, now, "s.zarr")
    assert "\n" not in str(err.value)
    check_fingerprint(saved, now, "s.zarr", grown_ok=True)  # evaluation: the run's cases are there, unchanged
    with pytest.raises(TrainerError, match="grid"):  # shrunk, or another grid besides: another store
        check_fingerprint(now, saved, "s.zarr", grown_ok=True)
    other = store_fingerprint({**large, "grid": {**large["grid"], "pressure_mmhg": [8.0]}}, {})
    with pytest.raises(TrainerError, match="grid"):
        check_fingerprint(saved, other, "s.zarr", grown_ok=True)


def test_a_run_trained_on_the_smaller_store_is_evaluated_on_it_grown_not_resumed(tmp_path):
    """Resuming would train on another split (the added shape's cases join it): one line, exit 2 at the
    CLI. Evaluation scores the run's own split, whose cases the grown store holds unchanged."""
    from dataclasses import replace

    from storage.writer import stats_row
    from trainer.config import PAPER, TrainConfig
    from trainer.errors import TrainerError
    from trainer.evaluation.evaluate import evaluate_run
    from trainer.training.loop import fit
    from trainer_fixtures import lv_mesh, make_tiny_store, synthetic_unloaded, tiny_spec

    loc = make_tiny_store(tmp_path / "tiny.zarr", shapes=4)
    cfg = TrainConfig(store=loc, config_name="paper-small", epochs=1, batch_size=4, num_threads=1,
                      model=replace(PAPER, hidden=8, heads=2, decoder_hidden=(16,), param_hidden=8))
    fit(cfg, tmp_path / "run")
    scored = evaluate_run(tmp_path / "run", loc, "test", plots=False)

    store = PairStore.open(loc)  # grown as a sweep grows it: the count raised, then the shape written
    store.grow_shapes(5)
    m, stats = lv_mesh(4), {"min_jacobian": 0.9, "roundtrip_error_mm": 1e-6, "final_residual": 1e-9}
    store.write_shape(4, m.nodes, m.tets, m.endo, m.epi, m.base, np.zeros(3), {})
    pairs = {k: (synthetic_unloaded(m.nodes, p, c), m.nodes, stats) for k, (p, c, _, _) in
             enumerate(tiny_spec(5).case_params())}
    assert set(store.write_pairs(4, pairs).values()) == {None}
    for k in pairs:
        store.set_case(4, k, DONE, stats_row(stats))
    store.flush()

    with pytest.raises(TrainerError, match="grew from 4 to 5 shapes; train on the grown store with a new `run_dir`"):
        fit(replace(cfg, epochs=2), tmp_path / "run")
    again = evaluate_run(tmp_path / "run", loc, "test", plots=False)
    assert again.cases == scored.cases == 4
    assert again.mean("md_mm") == scored.mean("md_mm")  # the same cases, the same answers
