"""The Zarr store: schema, round trip, done-only reads, validation before `done`, crash-safe
table writes, store inspection errors, summary, VTU export. No Ray here."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import zarr

from orchestrator.grid import LOCAL_SPEC, SweepSpec, parse_axis, resolve_spec
from orchestrator.tasks import mesh_shape, run_case
from storage.export import export_case
from storage.location import StoreError
from storage.reader import PairReader, read_done_cases
from storage.schema import DONE, FAILED, PENDING, STAT_NAMES, inspect_store
from storage.status import summarize
from storage.writer import PairStore, stats_row

SPEC = SweepSpec(shapes=2, pressure_mmhg=(8.0, 12.0), stiffness_pa=(100.0,), helix_endo_deg=(60.0,),
                 helix_epi_deg=(-60.0,), fidelity="fast", seed=0, nodes=200)


@pytest.fixture(scope="module")
def shape0():
    return mesh_shape(0, 0, 200)


@pytest.fixture(scope="module")
def real_pair(shape0):
    res = run_case(shape0["mesh"], (8.0, 100.0, 60.0, -60.0), "fast")
    assert res["ok"], res["reason"]
    return res


def _new_store(tmp_path, shape0, name="s.zarr"):
    store = PairStore.create(str(tmp_path / name), SPEC.store_attrs())
    m = shape0["mesh"]
    for s in range(SPEC.shapes):
        store.write_shape(s, m.nodes, m.tets, m.endo, m.epi, m.base, shape0["coefficients"], shape0["info"])
    return store


def _synthetic(m):
    """A valid-looking pair: a uniformly shrunk unloaded geometry and the ED nodes."""
    stats = {"min_jacobian": 0.9, "roundtrip_error_mm": 1e-5, "final_residual": 1e-9}
    return m.nodes * 0.97, m.nodes.copy(), stats


def test_round_trip_and_done_only_reads(tmp_path, shape0, real_pair):
    store = _new_store(tmp_path, shape0)
    loc = store.location
    assert store.write_pair(0, 1, real_pair["unloaded"], real_pair["loaded"], real_pair["stats"]) is None
    row = stats_row({**real_pair["stats"], "solve_attempts": 1, "run": 0})
    store.set_case(0, 1, DONE, row, host="h1")
    store.set_case(1, 0, FAILED, stats_row({}), host="h2", reason="step size collapsed at 0.0% of load")
    store.flush()

    reader = PairReader(loc)
    assert reader.shape_ids() == [0, 1]
    assert reader.done_cases() == [(0, 1)]
    cases = list(read_done_cases(loc))
    assert len(cases) == 1
    c = cases[0]
    assert (c.shape_id, c.index) == (0, 1)
    assert c.params == {"pressure_mmhg": 12.0, "stiffness_pa": 100.0, "helix_endo_deg": 60.0, "helix_epi_deg": -60.0}
    np.testing.assert_array_equal(c.unloaded, real_pair["unloaded"].astype(np.float32))
    np.testing.assert_allclose(c.loaded, real_pair["loaded"], atol=1e-4)  # float32: ~4e-6 mm
    np.testing.assert_array_equal(c.ed_reference, shape0["mesh"].nodes)
    assert c.stats["min_jacobian"] == pytest.approx(real_pair["stats"]["min_jacobian"])
    mesh = reader.mesh(0)
    np.testing.assert_array_equal(mesh.tets, shape0["mesh"].tets)
    np.testing.assert_array_equal(mesh.endo, shape0["mesh"].endo)
    for k in (0,):  # pending and failed cases are not readable
        with pytest.raises(StoreError, match="pending"):
            reader.case(0, k)
    with pytest.raises(StoreError, match="failed"):
        reader.case(1, 0)

    attrs = inspect_store(loc)
    assert attrs["schema_version"] == 2 and attrs["units"]["length"] == "mm"
    assert attrs["case_layout"] == "shard per shape"
    assert attrs["grid"]["pressure_mmhg"] == [8.0, 12.0] and attrs["fidelity"] == "fast" and attrs["seed"] == 0
    root = zarr.open_group(loc, mode="r")
    u = root["shapes/0/unloaded"]
    n = shape0["mesh"].n_nodes
    assert u.shape == (2, n, 3) and u.chunks == (1, n, 3) and u.shards == (2, n, 3)  # one shard per shape
    (sharding,) = u.metadata.codecs
    codecs = [c.__class__.__name__ for c in sharding.codecs]
    assert u.dtype == np.float32 and codecs[-2:] == ["BloscCodec", "Crc32cCodec"]  # each case compressed, then checksummed
    assert sharding.index_codecs[-1].__class__.__name__ == "Crc32cCodec"
    assert root["shapes/0/loaded"].metadata.codecs == u.metadata.codecs
    for name in ("ed_reference", "tets", "endo", "params", "status", "stats"):
        assert root[f"shapes/0/{name}"].metadata.codecs[-1].__class__.__name__ == "Crc32cCodec", name

    s = summarize(loc).as_dict()
    assert (s["done"], s["failed"], s["pending"], s["total"]) == (1, 1, 2, 4)
    assert s["failure_reasons"][0]["count"] == 1 and "step size collapsed" in s["failure_reasons"][0]["reason"]
    assert s["hosts"] == {"h1": 1}

    out = tmp_path / "case.vtu"
    export_case(loc, 0, 1, out)
    import meshio

    m = meshio.read(out)
    np.testing.assert_allclose(m.points, c.unloaded, atol=1e-6)
    np.testing.assert_allclose(m.point_data["displacement"], c.loaded - c.unloaded, atol=1e-6)
    with pytest.raises(StoreError):
        export_case(loc, 0, 0, tmp_path / "pending.vtu")
    assert not (tmp_path / "pending.vtu").exists()
    with pytest.raises(StoreError, match=r"shape 7 is not meshed .*shapes with data: 0–1"):
        export_case(loc, 7, 0, tmp_path / "absent.vtu")  # was a KeyError traceback
    assert not (tmp_path / "absent.vtu").exists()


@pytest.mark.parametrize("defect", ["nan", "inverted", "min_j", "roundtrip", "shape"])
def test_invalid_results_are_never_written_or_done(tmp_path, shape0, defect):
    store = _new_store(tmp_path, shape0)
    m = shape0["mesh"]
    unloaded, loaded, stats = _synthetic(m)
    if defect == "nan":
        loaded[3, 1] = np.nan
    elif defect == "inverted":
        t = m.tets[0]
        unloaded[t[0]] = unloaded[t[1]] + 5 * (unloaded[t[1]] - unloaded[t[0]])  # folds tets around node t0
    elif defect == "min_j":
        stats["min_jacobian"] = -0.1
    elif defect == "roundtrip":
        stats["roundtrip_error_mm"] = 0.5
    elif defect == "shape":
        unloaded = unloaded[:-1]
    reason = store.write_pair(0, 0, unloaded, loaded, stats)
    assert reason is not None and reason.startswith("invalid result")
    root = zarr.open_group(store.location, mode="r")
    assert np.all(np.isnan(root["shapes/0/unloaded"][0]))  # nothing landed
    assert np.all(np.isnan(root["shapes/0/loaded"][0]))


def test_done_needs_a_flushed_status(tmp_path, shape0):
    """Data written but the table not flushed (driver killed) → the case is still pending."""
    store = _new_store(tmp_path, shape0)
    u, l, st = _synthetic(shape0["mesh"])
    assert store.write_pair(0, 0, u, l, st) is None
    store.set_case(0, 0, DONE, stats_row(st))
    # no flush: a new reader sees nothing done
    assert PairReader(store.location).done_cases() == []
    assert PairStore.open(store.location).status(0).tolist() == [PENDING, PENDING]
    store.flush()
    assert PairReader(store.location).done_cases() == [(0, 0)]


def test_unfinished_shape_is_rewritten(tmp_path, shape0):
    store = _new_store(tmp_path, shape0)
    g = store.root["shapes/1"]
    g.attrs.update({"ready": False})  # as if the driver died while writing shape 1
    assert not store.shape_ready(1) and PairReader(store.location).shape_ids() == [0]
    m = shape0["mesh"]
    store.write_shape(1, m.nodes, m.tets, m.endo, m.epi, m.base, shape0["coefficients"])
    assert store.shape_ready(1)


def test_inspect_store_errors(tmp_path, shape0):
    assert inspect_store(str(tmp_path / "absent.zarr")) is None
    (tmp_path / "empty").mkdir()
    assert inspect_store(str(tmp_path / "empty")) is None
    f = tmp_path / "file.zarr"
    f.write_text("x")
    with pytest.raises(StoreError, match="is a file"):
        inspect_store(str(f))
    d = tmp_path / "folder"
    d.mkdir()
    (d / "notes.txt").write_text("x")
    with pytest.raises(StoreError, match="not a Zarr"):
        inspect_store(str(d))
    other = zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    other.attrs.update({"schema": "someone-else"})
    with pytest.raises(StoreError, match="another schema"):
        inspect_store(str(tmp_path / "other.zarr"))
    store = _new_store(tmp_path, shape0, "old.zarr")
    store.update_attrs(schema_version=99)
    with pytest.raises(StoreError, match="schema version 99"):
        inspect_store(store.location)
    with pytest.raises(StoreError, match="does not exist"):
        inspect_store(str(tmp_path / "no" / "such" / "x.zarr"))


def test_grid_spec():
    assert SweepSpec().n_cases == 19_440 and SweepSpec().cases_per_shape == 324
    assert SweepSpec().fidelity == "accurate"
    p = SPEC.case_params()
    assert p.tolist() == [[8.0, 100.0, 60.0, -60.0], [12.0, 100.0, 60.0, -60.0]]
    full = SweepSpec(shapes=1).case_params()
    assert full[1].tolist() == [4.0, 50.0, 60.0, -65.0]  # θepi varies fastest
    for bad, match in [(dict(pressure_mmhg=()), "`pressures` is empty"), (dict(fidelity="medium"), "unknown fidelity"),
                       (dict(shapes=0), "`shapes`"), (dict(stiffness_pa=(100.0, 100.0)), "repeated"),
                       (dict(pressure_mmhg=(-1.0,)), "pressure"), (dict(nodes=10), "`nodes`")]:
        with pytest.raises(ValueError, match=match):
            SweepSpec(**{**SPEC.__dict__, **bad}).validate()
    assert SPEC.conflicts(SPEC.store_attrs()) == []
    other = SweepSpec(**{**SPEC.__dict__, "pressure_mmhg": (8.0,), "fidelity": "accurate"})
    msgs = other.conflicts(SPEC.store_attrs())
    assert any("pressures=8" in m for m in msgs) and any("fidelity=accurate" in m for m in msgs)
    edited = SPEC.store_attrs()  # the same preset name, its tolerance edited since the store was made
    edited["fidelity_settings"] = {**edited["fidelity_settings"], "inverse_tol_mm": 1.0}
    msgs = SPEC.conflicts(edited)
    assert len(msgs) == 1 and f"the {SPEC.fidelity} preset's settings (inverse_tol_mm 1.0 → " in msgs[0]
    older = SPEC.store_attrs()  # a store written before a setting existed still resumes
    older["fidelity_settings"] = {k: v for k, v in older["fidelity_settings"].items() if k != "inverse_tol_mm"}
    assert SPEC.conflicts(older) == []
    assert parse_axis("epi", "-60, -65") == (-60.0, -65.0) and parse_axis("epi", "") == ()
    with pytest.raises(ValueError, match="comma-separated"):
        parse_axis("pressures", "4;6")
    # precedence: explicit > --local preset > store's values > paper defaults
    assert resolve_spec({"shapes": None}, local=True) == LOCAL_SPEC
    assert resolve_spec({"fidelity": None}, stored_attrs={**SPEC.store_attrs()}) == SPEC
    assert resolve_spec({"fidelity": "accurate"}, stored_attrs=SPEC.store_attrs()).fidelity == "accurate"
    assert resolve_spec({}) == SweepSpec()


def test_run_case_without_ray(shape0):
    res = run_case(shape0["mesh"], (1e5, 100.0, 60.0, -60.0), "fast")
    assert not res["ok"] and res["attempts"] == 2 and res["reason"] and res["unloaded"] is None
    assert len(STAT_NAMES) == len(stats_row({}))


def test_opens_by_fsspec_url(shape0):
    """Any fsspec URL works (a cluster uses s3://…); memory:// stands in for it here."""
    url = "memory://heartctl-test/pairs.zarr"
    assert inspect_store(url) is None
    store = PairStore.create(url, SPEC.store_attrs())
    m = shape0["mesh"]
    store.write_shape(0, m.nodes, m.tets, m.endo, m.epi, m.base, shape0["coefficients"])
    u, l, st = _synthetic(m)
    assert store.write_pair(0, 1, u, l, st) is None
    store.set_case(0, 1, DONE, stats_row(st))
    store.flush()
    assert PairReader(url).done_cases() == [(0, 1)]
    assert summarize(url).done == 1


def test_a_shape_meshed_later_loses_its_mesh_failure(tmp_path, shape0):
    store = PairStore.create(str(tmp_path / "m.zarr"), SPEC.store_attrs())
    store.record_mesh_failure(1, "gmsh: could not recover the boundary")
    store.record_mesh_failure(0, "gmsh: timeout")
    m = shape0["mesh"]
    store.write_shape(0, m.nodes, m.tets, m.endo, m.epi, m.base, shape0["coefficients"], shape0["info"])
    store.flush()
    assert summarize(store.location).mesh_failures == {"1": "gmsh: could not recover the boundary"}


def test_one_writer_per_store(tmp_path, shape0):
    """A store another process writes is refused (one line, naming it); the lock dies with its
    holder, however it ends (killed here), so a rerun takes it."""
    import json
    import subprocess
    import sys

    from orchestrator.sweep import check_request
    from storage.lock import LOCK_NAME, WriterLock, holder

    store = _new_store(tmp_path, shape0)
    hold = ("import sys, time; sys.path.insert(0, sys.argv[2]); from storage.lock import WriterLock; "
            "WriterLock(sys.argv[1]).acquire(); print('held', flush=True); time.sleep(120)")
    repo = str(Path(__file__).resolve().parents[1])
    other = subprocess.Popen([sys.executable, "-c", hold, store.location, repo], stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "held"
        assert holder(store.location)["pid"] == other.pid
        assert summarize(store.location).writer["pid"] == other.pid  # `status` tells running from interrupted
        with pytest.raises(StoreError, match=f"being written by pid {other.pid}"):
            check_request(SPEC, store.location)
        with pytest.raises(StoreError, match="being written"):
            WriterLock(store.location).acquire()
    finally:
        other.kill()  # SIGKILL: no clean-up runs in the holder
        other.wait()
    assert holder(store.location) is None and summarize(store.location).writer is None
    with WriterLock(store.location) as lock:
        assert lock.held and json.loads((tmp_path / "s.zarr" / LOCK_NAME).read_text())["pid"] == os.getpid()
        assert holder(store.location) is None  # this process's own lock does not refuse it
    assert (tmp_path / "s.zarr" / LOCK_NAME).read_text() == ""


def test_status_probing_the_lock_does_not_refuse_a_writer(tmp_path, shape0):
    """`status` (holder()) takes the lock for a moment to see whether anybody holds it; a writer
    starting in that moment must not be refused as if another sweep held the store."""
    import subprocess
    import sys

    from storage.lock import WriterLock

    store = _new_store(tmp_path, shape0)
    probe = ("import sys, time; sys.path.insert(0, sys.argv[2]); from storage.lock import holder; "
             "holder(sys.argv[1]); print('probing', flush=True); end = time.time() + 60\n"
             "while time.time() < end: holder(sys.argv[1])")
    repo = str(Path(__file__).resolve().parents[1])
    other = subprocess.Popen([sys.executable, "-c", probe, store.location, repo], stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "probing"
        for _ in range(400):
            WriterLock(store.location).acquire().release()
    finally:
        other.kill()
        other.wait()


def test_dry_run_object_count_matches_a_written_store(tmp_path):
    """generate --dry-run's object count (the files a complete store holds) against a written one."""
    from orchestrator.plan import store_objects
    from trainer_fixtures import make_tiny_store

    path = tmp_path / "objects.zarr"
    make_tiny_store(path, shapes=2, pressures=(8.0, 12.0), stiffness=(100.0, 200.0))
    files = [p for p in path.rglob("*") if p.is_file() and p.name != ".lock"]
    # the fixture's shape coefficients are all 0, Zarr's fill value: their chunks are never written
    assert store_objects(2, 4) - 2 == len(files), sorted(str(p.relative_to(path)) for p in files)
