"""The Ray sweep: failures recorded and skipped over, resume, a killed worker, a killed driver,
bad arguments. The tests' shared two-CPU Ray (conftest.py); coarse meshes (~200 nodes), the fast preset."""
from __future__ import annotations

import hashlib
import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import zarr
from typer.testing import CliRunner

from orchestrator.grid import SweepSpec
from orchestrator.sweep import run_sweep
from killed_driver import generate_killed_after_first_write
from process_tree import processes_titled
from storage.reader import PairReader
from storage.schema import DONE, FAILED, STAT_NAMES, inspect_store
from storage.status import summarize
from storage.writer import PairStore

COL = {n: i for i, n in enumerate(STAT_NAMES)}


def spec(**kw) -> SweepSpec:
    base = dict(shapes=1, pressure_mmhg=(8.0,), stiffness_pa=(100.0,), helix_endo_deg=(60.0,),
                helix_epi_deg=(-60.0,), fidelity="fast", seed=0, nodes=200)
    base.update(kw)
    return SweepSpec(**base).validate()


@pytest.fixture
def ray_cluster(local_ray):
    return local_ray


def _stats(location, shape=0):
    r = PairReader(location)
    return r.status(shape), r.stats(shape)


def test_local_ray_workers_are_not_niced(ray_cluster):
    """Ray's default nice 15 let any other busy process starve the solves ~20× (README). Ray sets a
    worker's niceness relative to the process that started it, so under `nice make test` the workers
    share the driver's niceness (the README's advice for letting generation yield)."""
    import ray

    from orchestrator.ray_session import WORKER_NICENESS

    assert ray.get(ray.remote(num_cpus=1)(lambda: os.nice(0)).remote()) == os.nice(0) + WORKER_NICENESS
    assert WORKER_NICENESS == 0


@pytest.mark.slow
def test_failed_case_recorded_and_sweep_goes_on_then_resume(ray_cluster, tmp_path):
    loc = str(tmp_path / "f.zarr")
    sp = spec(pressure_mmhg=(8.0, 1e5, 12.0))  # 1e5 mmHg cannot be inflated
    rep = run_sweep(sp, loc, progress=False)
    assert (rep.done, rep.failed, rep.submitted) == (2, 1, 3)
    status, stats = _stats(loc)
    assert status.tolist() == [DONE, FAILED, DONE]
    assert stats[1, COL["solve_attempts"]] == 2  # retried once with the robust setting
    s = summarize(loc).as_dict()
    assert (s["done"], s["failed"], s["pending"]) == (2, 1, 0)
    assert s["failure_reasons"][0]["cases"] == [[0, 1]]
    assert "load" in s["failure_reasons"][0]["example"]

    # resume: nothing is resubmitted; done cases keep their data and timestamps
    before = PairReader(loc).case(0, 0)
    rep2 = run_sweep(sp, loc, progress=False)
    assert rep2.submitted == 0 and rep2.done_before == 2 and rep2.failed_before == 1
    status2, stats2 = _stats(loc)
    np.testing.assert_array_equal(stats2[[0, 2]], stats[[0, 2]])
    np.testing.assert_array_equal(PairReader(loc).case(0, 0).unloaded, before.unloaded)
    # --retry-failed reruns only the failed case (and it fails again, with its reason)
    from orchestrator.plan import make_plan

    attrs = inspect_store(loc)
    assert make_plan(sp, loc, attrs, calibration=False).to_run == 0
    assert make_plan(sp, loc, attrs, calibration=False, retry_failed=True).to_run == 1  # the dry run agrees
    rep3 = run_sweep(sp, loc, progress=False, retry_failed=True)
    assert rep3.submitted == 1 and rep3.records == [(0, 1, FAILED)]
    assert rep3.failed_now == 1  # the store's one failed case, not the retried one counted twice
    _, stats3 = _stats(loc)
    np.testing.assert_array_equal(stats3[[0, 2]], stats[[0, 2]])
    assert len(inspect_runs(loc)) == 3


def inspect_runs(loc):
    return zarr.open_group(loc, mode="r").attrs["runs"]


def _busy_case_workers() -> list[int]:
    """PIDs of this test's Ray worker processes currently running a pair (process title
    ray::run_chain); the local Ray started by the fixture descends from this process, so other
    Ray jobs on the machine are left alone."""
    return processes_titled(b"ray::run_chain", os.getpid())


@pytest.mark.slow
def test_killed_worker_sweep_still_finishes(ray_cluster, tmp_path):
    loc = str(tmp_path / "w.zarr")
    # four chains of four pairs, two in flight, so that workers are still mid-chain when the first
    # events arrive (with two chains, a faster solver could finish both before the first event)
    sp = spec(pressure_mmhg=(6.0, 8.0, 10.0, 12.0), stiffness_pa=(50.0, 100.0, 200.0, 300.0))
    killed = []

    def on_event(ev):
        if killed:
            return
        for pid in _busy_case_workers():
            os.kill(pid, signal.SIGKILL)  # a worker in the middle of a pair
            killed.append(pid)
            break

    rep = run_sweep(sp, loc, progress=False, on_event=on_event)
    assert killed, "no busy worker was found to kill"
    assert rep.done == sp.n_cases and rep.failed == 0
    ks = [k for _, k, _ in rep.records]
    assert sorted(ks) == list(range(sp.n_cases))  # every case recorded exactly once
    status, stats = _stats(loc)
    assert (status == DONE).all()
    for c in PairReader(loc).iter_done():
        assert np.isfinite(c.unloaded).all() and np.isfinite(c.loaded).all()


@pytest.mark.slow
def test_driver_killed_then_rerun_finishes(ray_cluster, tmp_path):
    loc = str(tmp_path / "d.zarr")
    # 2 pressure chains of 2 cases, one in flight: the first write holds the first chain's cases
    args = ["generate", "--store", loc, "--shapes", "1", "--pressures", "8,12", "--stiffness", "100,200",
            "--endo", "60", "--epi=-60", "--fidelity", "fast", "--nodes", "200", "--max-in-flight", "1"]
    total = 4
    generate_killed_after_first_write(args, ray_cluster)

    reader = PairReader(loc)  # opens cleanly after the kill
    done_before = {}
    for s in reader.shape_ids():
        st, stats = reader.status(s), reader.stats(s)
        for k in np.flatnonzero(st == DONE):
            done_before[(s, int(k))] = stats[k].copy()
    assert len(done_before) == 2

    # the same command again, in this process (whose Ray it uses)
    from cli import app

    out = CliRunner().invoke(app, args + ["--json"])
    assert out.exit_code == 0, out.output[-2000:]
    rep = json.loads(out.stdout.strip().splitlines()[-1])
    assert rep["done_before"] == len(done_before)
    assert rep["submitted"] == total - len(done_before)  # no done case recomputed
    reader = PairReader(loc)
    assert reader.shape_ids() == [0]
    assert len(reader.done_cases()) == total
    for (s, k), row in done_before.items():
        np.testing.assert_array_equal(reader.stats(s)[k], row)
    for c in reader.iter_done():
        assert np.isfinite(c.unloaded).all() and np.isfinite(c.loaded).all()
    assert not list(Path(loc).rglob("*.partial"))
    assert len(zarr.open_group(loc, mode="r").attrs["runs"]) == 2


# --------------------------------------------------------------------------- bad arguments (no Ray needed)


def _snapshot(path: Path) -> dict:
    if path.is_file():
        return {"": hashlib.sha256(path.read_bytes()).hexdigest()}
    return {str(p.relative_to(path)): (hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir")
            for p in sorted(path.rglob("*"))}


def _run_cli(args):
    from cli import app

    res = CliRunner().invoke(app, args)
    err = getattr(res, "stderr", res.output)
    return res.exit_code, err


@pytest.fixture
def small_store(tmp_path):
    sp = spec(pressure_mmhg=(8.0, 12.0))
    PairStore.create(str(tmp_path / "s.zarr"), sp.store_attrs())
    return tmp_path / "s.zarr"


SMALL = ["--shapes", "1", "--pressures", "8,12", "--stiffness", "100", "--endo", "60", "--epi=-60",
         "--fidelity", "fast", "--nodes", "200"]


@pytest.mark.parametrize("case", ["fidelity", "empty", "file", "schema", "grid", "seed", "version", "fibres",
                                  "fibres_conflict", "base"])
def test_bad_arguments_exit_2_one_line_store_untouched(tmp_path, small_store, case):
    target = small_store
    args = SMALL[:]
    if case == "fidelity":
        args[args.index("fast")] = "medium"
    elif case == "empty":
        args[args.index("8,12")] = ""
    elif case == "file":
        target = tmp_path / "file.zarr"
        target.write_text("not a store")
    elif case == "schema":
        target = tmp_path / "other.zarr"
        zarr.open_group(str(target), mode="w").attrs.update({"schema": "other", "schema_version": 1})
    elif case == "grid":
        args[args.index("8,12")] = "8,10"
    elif case == "seed":
        args += ["--seed", "3"]
    elif case == "version":
        zarr.open_group(str(small_store), mode="r+").attrs.update({"schema_version": 99})
    elif case == "fibres":
        args += ["--fibres", "random"]
    elif case == "fibres_conflict":  # the store was made with Laplace fibres
        args += ["--fibres", "heartfem"]
    elif case == "base":
        args += ["--base", "glued"]
    before = _snapshot(target)
    code, err = _run_cli(["generate", "--store", str(target)] + args)
    assert code == 2
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("heartctl: error:"), err
    assert _snapshot(target) == before


@pytest.mark.parametrize("edit", ["runs_null", "no_acceptance", "case_params_reversed", "shape_params_reversed"])
def test_a_hand_edited_store_is_refused_and_left_alone(tmp_path, edit):
    """Root attributes of the wrong type or missing, or a case table that no longer follows the
    grid (its data would be labelled with the wrong parameters): exit 2, one line, store unchanged."""
    from trainer_fixtures import make_tiny_store

    store = Path(make_tiny_store(tmp_path / "t.zarr", shapes=1))
    group = zarr.open_group(str(store), mode="r+")
    if edit == "runs_null":
        group.attrs["runs"] = None
    elif edit == "no_acceptance":
        del group.attrs["acceptance"]
    elif edit == "case_params_reversed":
        group.attrs["case_params"] = group.attrs["case_params"][::-1]
    else:  # the shape's own table, which readers label its cases with
        params = group["shapes/0/params"]
        params[...] = params[...][::-1]
    before = _snapshot(store)
    for args in (["status", "--store", str(store)], ["generate", "--store", str(store)]):
        if edit.endswith("_reversed") and args[0] == "status":
            continue  # status reports it; generate must not resume it
        code, err = _run_cli(args)
        lines = [ln for ln in err.strip().splitlines() if ln.strip()]
        assert code == 2 and len(lines) == 1 and lines[0].startswith("heartctl: error:"), err
        assert ("edited" in lines[0]) or ("damaged" in lines[0]), lines[0]
    assert _snapshot(store) == before


def test_a_store_whose_parts_this_user_cannot_write_is_refused_before_ray(tmp_path, monkeypatch):
    """A resumed store must be writable below its top folder too (the lock, the shapes' folders):
    found by check_request, not as a PermissionError mid-run."""
    import orchestrator.sweep as sweep
    from trainer_fixtures import make_tiny_store, tiny_spec

    store = Path(make_tiny_store(tmp_path / "t.zarr", shapes=1))
    (store / ".heartctl-writer.lock").touch()
    real = os.access
    for blocked in (".heartctl-writer.lock", "0"):
        monkeypatch.setattr(sweep.os, "access", lambda p, mode, b=blocked: False if Path(p).name == b else real(p, mode))
        with pytest.raises(ValueError, match="is not writable by this user"):
            sweep.check_request(tiny_spec(shapes=1), str(store))


def test_a_memory_store_is_refused_for_writing(tmp_path):
    code, err = _run_cli(["generate", "--store", "memory://m1"] + SMALL)
    assert code == 2 and "memory:// store vanishes" in err, err


def test_status_and_dry_run_cli(tmp_path, small_store):
    code, err = _run_cli(["status", "--store", str(tmp_path / "absent.zarr")])
    assert code == 2 and "no heartctl store" in err
    from cli import app

    res = CliRunner().invoke(app, ["status", "--store", str(small_store), "--json"])
    assert res.exit_code == 0
    s = json.loads(res.stdout)
    assert (s["done"], s["failed"], s["pending"]) == (0, 0, 2)
    new = tmp_path / "plan.zarr"
    res = CliRunner().invoke(app, ["generate", "--store", str(new), "--dry-run", "--json"] + SMALL)
    assert res.exit_code == 0, res.output
    plan = json.loads(res.stdout.strip().splitlines()[-1])
    assert plan["cases"] == 2 and plan["to_run"] == 2 and plan["core_hours"] > 0
    assert plan["calibration"]["ok"] and plan["calibration"]["case_bytes"] > 0
    assert not new.exists()  # a dry run writes nothing


def test_a_damaged_status_chunk_is_one_line_and_the_store_untouched(tmp_path):
    """status and a resuming generate read every shape's status array: a chunk that does not decompress
    (numcodecs raises RuntimeError) is damage of the shape, not a traceback: status names it (exit 1),
    generate refuses the store in one line naming --retry-damaged (exit 2), and nothing is written."""
    from cli import app
    from trainer_fixtures import make_tiny_store

    store = Path(make_tiny_store(tmp_path / "t.zarr", shapes=2))
    chunks = sorted(p for p in store.glob("shapes/1/status/c/**/*") if p.is_file())
    assert chunks
    chunks[0].write_bytes(b"\x00garbage" * 5)
    before = _snapshot(store)
    status = CliRunner().invoke(app, ["status", "--store", str(store)])
    assert status.exit_code == 1 and "damaged: shape 1 every case: its array 'status' is damaged" in status.output
    assert "Traceback" not in status.output
    code, err = _run_cli(["generate", "--store", str(store)])
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and "shape 1 is damaged: its array 'status' is damaged" in lines[0], err
    assert "--retry-damaged" in lines[0]
    assert _snapshot(store) == before


def test_an_unwritable_store_folder_is_refused_before_ray(tmp_path, monkeypatch):
    """Found by check_request (before Ray starts), not as a PermissionError traceback mid-run."""
    import orchestrator.sweep as sweep
    from cli import app

    assert sweep.check_request(spec(), "file://" + str(tmp_path / "t.zarr")) is None  # file:// URLs are local paths
    asked = []

    def no_write(path, mode):
        asked.append(Path(path))
        return False

    monkeypatch.setattr(sweep.os, "access", no_write)
    with pytest.raises(ValueError, match="not writable"):
        sweep.check_request(spec(), str(tmp_path / "s.zarr"))
    assert asked == [tmp_path]
    sweep.check_request(spec(), "file://" + str(tmp_path / "s.zarr"), for_writing=False)  # a plan writes nothing
    res = CliRunner().invoke(app, ["generate", "--store", str(tmp_path / "s.zarr"), "--local"])
    assert res.exit_code == 2 and "not writable" in res.output and not (tmp_path / "s.zarr").exists()


def test_retry_damaged_recomputes_only_the_damaged_case(ray_cluster, tmp_path):
    """A flipped bit in one done case: status --verify names the case (exit 1), a sweep with
    retry_damaged (generate --retry-damaged) solves it again, and only it, after which every case
    reads back intact."""
    from trainer_fixtures import flip_byte, make_tiny_store

    store = Path(make_tiny_store(tmp_path / "t.zarr", shapes=1))
    reader = PairReader(str(store))
    intact = reader.case(0, 0).unloaded.copy()
    flip_byte(store, 0, "loaded", 2, where=1 / 3)  # inside case 2's chunk of the shape's shard
    assert PairReader(str(store)).damaged() == [(0, 2, "its checksum does not match (changed bytes)")]
    code, _ = _run_cli(["status", "--store", str(store), "--verify"])
    assert code == 1
    report = run_sweep(SweepSpec.from_attrs(reader.attrs), str(store), progress=False, retry_damaged=True)
    assert report.damaged_reset == [(0, 2)] and report.done == 1
    after = PairReader(str(store))
    assert after.damaged() == [] and after.status(0).tolist() == [DONE] * 4
    assert np.array_equal(after.case(0, 0).unloaded, intact)  # the intact cases were not recomputed
    assert np.linalg.norm(after.case(0, 2).loaded - after.mesh(0).nodes, axis=1).max() < 1e-3


@pytest.mark.slow
def test_retry_damaged_recomputes_missing_data_and_a_shape_with_edited_metadata(ray_cluster, tmp_path):
    """Shape 0's loaded shard deleted (its 4 cases' data missing) and shape 1's unloaded node count
    edited: verify names both, a plain sweep refuses the store in one line, and one with retry_damaged
    recomputes shape 0's cases and meshes shape 1 again (on a Ray worker, the mesh this process makes of
    the store's shape model version) and solves its cases, after which every case reads back intact."""
    from storage.location import StoreError
    from test_store_damage import add_nodes_to
    from trainer_fixtures import case_chunk, make_tiny_store

    from orchestrator.tasks import mesh_shape

    store = make_tiny_store(tmp_path / "t.zarr", shapes=2)
    reader = PairReader(store)
    case_chunk(store, 0, "loaded", 0)[0].unlink()
    add_nodes_to(store, 1)
    found = PairReader(store).damaged()
    assert [(s, k) for s, k, _ in found] == [(0, 0), (0, 1), (0, 2), (0, 3), (1, None)]
    spec_ = SweepSpec.from_attrs(reader.attrs)
    with pytest.raises(StoreError, match=r"shape 1 is damaged: its array 'unloaded' has shape"):
        run_sweep(spec_, store, progress=False)

    report = run_sweep(spec_, store, progress=False, retry_damaged=True)
    assert report.damaged_reset == [(0, 0), (0, 1), (0, 2), (0, 3), (1, None)] and report.done == 8
    after = PairReader(store)
    assert after.damaged() == [] and [len(after.done_cases([s])) for s in (0, 1)] == [4, 4]
    mesh1 = mesh_shape(1, spec_.seed, spec_.nodes, shape_model_version=spec_.shape_model_version)["mesh"]
    assert np.array_equal(after.mesh(1).nodes, mesh1.nodes) and np.array_equal(after.mesh(1).tets, mesh1.tets)
