"""The sharded store (schema version 2): objects per shape whatever the case count, cases written in
batches into a shape's shard and read back, a damaged inner chunk named alone, a version 1 store
(a chunk per case) read and resumed, a writer killed mid-write, and the driver's write batching.
No Ray here."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from orchestrator.plan import store_objects
from orchestrator.pacing import HeldResults
from storage.location import StoreError
from storage.reader import PairReader, read_cases
from storage.schema import CHUNK_PER_CASE, DONE, PENDING, inspect_store
from storage.writer import PairStore, stats_row
from trainer_fixtures import (case_chunk, flip_byte, flip_index_byte, lv_mesh, make_tiny_store, synthetic_unloaded,
                              tiny_spec)

ROOT = Path(__file__).resolve().parents[1]
STATS = {"min_jacobian": 0.9, "roundtrip_error_mm": 1e-6, "final_residual": 1e-9}


def _files(path: Path, under: str = "") -> list[Path]:
    return [p for p in (path / under).rglob("*") if p.is_file() and not p.name.endswith(".lock")]


def _empty_store(path, pressures=(8.0, 10.0, 12.0), stiffness=(100.0, 200.0), attrs=None) -> PairStore:
    spec = tiny_spec(1, 0, pressures, stiffness)
    store = PairStore.create(str(path), {**spec.store_attrs(), **(attrs or {})})
    m = lv_mesh(0)
    store.write_shape(0, m.nodes, m.tets, m.endo, m.epi, m.base, np.zeros(3), {})
    return store


def _pairs(store: PairStore, ks) -> dict:
    m = lv_mesh(0)
    return {k: (synthetic_unloaded(m.nodes, *store.params[k][:2]), m.nodes, STATS) for k in ks}


def _mark_done(store: PairStore, ks) -> None:
    for k in ks:
        store.set_case(0, k, DONE, stats_row(STATS))
    store.flush()


def test_objects_per_shape_do_not_grow_with_cases(tmp_path):
    few = Path(make_tiny_store(tmp_path / "few.zarr", shapes=2, pressures=(8.0, 12.0), stiffness=(100.0,)))
    many = Path(make_tiny_store(tmp_path / "many.zarr", shapes=2, pressures=(4.0, 8.0, 12.0, 14.0),
                                stiffness=(50.0, 100.0, 200.0, 300.0)))  # 2 and 16 cases a shape
    assert len(_files(few, "shapes/0")) == len(_files(many, "shapes/0"))
    assert len(_files(few)) == len(_files(many)) == store_objects(2, 16) - 2  # the fixture writes no coefficients
    for name in ("unloaded", "loaded"):
        assert [p.relative_to(many) for p in _files(many, f"shapes/1/{name}/c")] == [Path(f"shapes/1/{name}/c/0/0/0")]
    assert store_objects(2, 16, sharded=False) - store_objects(2, 16) == 2 * 2 * 15


def test_batches_of_cases_round_trip_through_one_shard(tmp_path):
    store = _empty_store(tmp_path / "s.zarr")  # 6 cases: k = iP * 2 + iC
    first = _pairs(store, [0, 2, 5])  # not one run: a coordinate selection
    assert store.write_pairs(0, first) == {0: None, 2: None, 5: None}
    _mark_done(store, first)
    shard = case_chunk(store.location, 0, "unloaded", 0)[0]
    before = {k: case_chunk(store.location, 0, "unloaded", k) for k in first}
    old_bytes = {k: shard.read_bytes()[o:o + n] for k, (_, o, n) in before.items()}

    second = _pairs(store, [3, 4])  # one run: a slice
    bad = _pairs(store, [1])
    bad[1] = (np.full_like(bad[1][0], np.nan), bad[1][1], STATS)
    reasons = store.write_pairs(0, {**second, **bad})
    assert reasons[3] is None and reasons[4] is None and "NaN" in reasons[1]
    _mark_done(store, second)
    new_bytes = shard.read_bytes()
    for k, (_, o, n) in before.items():  # the done cases' chunks copied, byte for byte
        o2, n2 = case_chunk(store.location, 0, "unloaded", k)[1:]
        assert new_bytes[o2:o2 + n2] == old_bytes[k]

    reader = PairReader(store.location)
    cases = {c.index: c for c in reader.iter_done()}
    assert sorted(cases) == [0, 2, 3, 4, 5]
    for k, (unloaded, loaded, _) in {**first, **second}.items():
        np.testing.assert_array_equal(cases[k].unloaded, unloaded.astype(np.float32))
        np.testing.assert_array_equal(reader.case(0, k).loaded, loaded.astype(np.float32))
    assert np.isnan(zarr.open_group(store.location, mode="r")["shapes/0/unloaded"][1]).all()  # never written
    arrays, damage = read_cases(reader._shape(0), [2, 4])
    assert sorted(arrays) == [2, 4] and damage == {}


def test_a_damaged_inner_chunk_names_that_case_alone(tmp_path):
    store = _empty_store(tmp_path / "s.zarr")
    store.write_pairs(0, _pairs(store, range(6)))
    _mark_done(store, range(6))
    flip_byte(store.location, 0, "loaded", 4)

    reader = PairReader(store.location)
    assert reader.damaged() == [(0, 4, "its checksum does not match (changed bytes)")]
    for k in (0, 1, 2, 3, 5):  # the same shard's other cases read
        assert np.isfinite(reader.case(0, k).loaded).all()
    with pytest.raises(StoreError, match="shape 0 case 4 is damaged: its checksum does not match"):
        reader.case(0, 4)
    with pytest.raises(StoreError, match="shape 0 case 4 is damaged"):
        list(reader.iter_done())

    flip_byte(store.location, 0, "unloaded", 1)
    again = PairStore.open(store.location)
    assert [k for _, k, _ in again.reset_damaged([0])] == [1, 4]
    assert again.status(0).tolist() == [DONE, PENDING, DONE, DONE, PENDING, DONE]
    # rewrites the shard, the damaged chunks replaced (not decoded: run by run)
    assert again.write_pairs(0, _pairs(again, [1, 4])) == {1: None, 4: None}
    _mark_done(again, [1, 4])
    assert PairReader(store.location).damaged() == [] and len(list(PairReader(store.location).iter_done())) == 6


def test_a_damaged_shard_index_fails_every_case_and_is_recomputed(tmp_path):
    store = _empty_store(tmp_path / "s.zarr")
    store.write_pairs(0, _pairs(store, range(6)))
    _mark_done(store, range(6))
    shard = case_chunk(store.location, 0, "unloaded", 0)[0]
    flip_index_byte(store.location, 0)

    assert [k for _, k, _ in PairReader(store.location).damaged()] == list(range(6))
    again = PairStore.open(store.location)
    assert len(again.reset_damaged([0])) == 6 and not shard.exists()  # nothing done left in it: dropped
    assert set(again.write_pairs(0, _pairs(again, range(6))).values()) == {None}
    _mark_done(again, range(6))
    assert PairReader(store.location).damaged() == []


def test_a_damaged_index_in_a_shard_without_done_cases_is_rewritten_and_with_them_named(tmp_path):
    """Cases written but not yet marked done (a driver killed between the write and the status
    flush), then the shard's index damaged: the next write drops the shard and writes afresh; with a
    done case in it, one line naming the shape and the way to recompute it."""
    store = _empty_store(tmp_path / "s.zarr")
    store.write_pairs(0, _pairs(store, range(6)))  # none marked done
    flip_index_byte(store.location, 0)

    again = PairStore.open(store.location)
    assert again.write_pairs(0, _pairs(again, [1, 3])) == {1: None, 3: None}
    _mark_done(again, [1, 3])
    assert PairReader(store.location).damaged() == []

    flip_index_byte(store.location, 0)
    with pytest.raises(StoreError, match=r"shape 0: the index of its case shard is damaged; .*`retry_damaged`"):
        PairStore.open(store.location).write_pairs(0, _pairs(again, [0]))


def _version_1(path) -> PairStore:
    """A store as schema version 1 makes it: a chunk per case, no case_layout attribute."""
    store = PairStore.create(str(path), {**tiny_spec(1).store_attrs(), "schema_version": 1})
    root = zarr.open_group(str(path), mode="r+")
    root.attrs.put({k: v for k, v in root.attrs.asdict().items() if k != "case_layout"})
    store = PairStore.open(str(path))
    m = lv_mesh(0)
    store.write_shape(0, m.nodes, m.tets, m.endo, m.epi, m.base, np.zeros(3), {})
    return store


def test_a_version_1_store_reads_and_resumes_as_it_is(tmp_path):
    store = _version_1(tmp_path / "v1.zarr")
    assert "case_layout" not in inspect_store(store.location) and not store.sharded
    assert store.write_pairs(0, _pairs(store, [0, 3])) == {0: None, 3: None}
    _mark_done(store, [0, 3])
    chunks = sorted(str(p.relative_to(tmp_path)) for p in _files(tmp_path / "v1.zarr", "shapes/0/unloaded/c"))
    assert chunks == ["v1.zarr/shapes/0/unloaded/c/0/0/0", "v1.zarr/shapes/0/unloaded/c/3/0/0"]  # one object a case

    resumed = PairStore.open(store.location)  # a sweep resuming it keeps its layout
    assert resumed.write_pairs(0, _pairs(resumed, [1, 2])) == {1: None, 2: None}
    _mark_done(resumed, [1, 2])
    reader = PairReader(store.location)
    assert [c.index for c in reader.iter_done()] == [0, 1, 2, 3]
    flip_byte(store.location, 0, "unloaded", 2)
    assert reader.damaged() == [(0, 2, "its checksum does not match (changed bytes)")]
    from storage.schema import case_layout
    assert case_layout(reader.attrs) == CHUNK_PER_CASE


# A writer that dies (SIGKILL, no clean-up) halfway through writing the bytes of the unloaded shard:
# whatever way the local store writes a file, only those bytes are cut short.
KILLED_WRITER = """
import builtins, io, os, pathlib, signal, sys
sys.path.insert(0, {tests!r})
from test_store_shards import _pairs
from storage.writer import PairStore

class Dying(io.FileIO):
    def write(self, b):
        super().write(bytes(memoryview(b))[:len(memoryview(b)) // 2])
        self.flush()
        os.kill(os.getpid(), signal.SIGKILL)

real_open, real_path_open = io.open, pathlib.Path.open
def writes_the_shard(file, mode):
    return any(c in mode for c in "wa+") and "/shapes/0/unloaded/c/" in str(file)
def dying_open(file, mode="r", *args, **kwargs):
    if writes_the_shard(file, mode):
        return Dying(file, mode.replace("b", "").replace("t", "") or "w")
    return real_open(file, mode, *args, **kwargs)
def dying_path_open(path, mode="r", *args, **kwargs):
    if writes_the_shard(path, mode):
        return dying_open(path, mode)
    return real_path_open(path, mode, *args, **kwargs)

store = PairStore.open({location!r})
io.open = builtins.open = dying_open
pathlib.Path.open = dying_path_open
store.write_pairs(0, _pairs(store, [1, 3, 5]))
print("survived")
"""


def test_a_writer_killed_mid_write_leaves_the_done_cases_intact(tmp_path):
    store = _empty_store(tmp_path / "s.zarr")
    done = _pairs(store, [0, 2, 4])
    store.write_pairs(0, done)
    _mark_done(store, done)
    shard = case_chunk(store.location, 0, "unloaded", 0)[0]
    before = shard.read_bytes()

    code = KILLED_WRITER.format(tests=str(ROOT / "tests"), location=store.location)
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stdout + proc.stderr
    assert shard.read_bytes() == before  # the old shard, whole

    resumed = PairStore.open(store.location)  # removes the cut-short temporary file
    assert not list((tmp_path / "s.zarr").rglob("*.partial"))
    assert resumed.status(0).tolist() == [DONE, PENDING] * 3
    reader = PairReader(store.location)
    assert reader.damaged() == []
    for k, (unloaded, _, _) in done.items():
        np.testing.assert_array_equal(reader.case(0, k).unloaded, unloaded.astype(np.float32))
    assert set(resumed.write_pairs(0, _pairs(resumed, [1, 3, 5])).values()) == {None}
    _mark_done(resumed, [1, 3, 5])
    assert len(list(PairReader(store.location).iter_done())) == 6


def test_the_driver_writes_a_shapes_cases_together():
    now, stored = [0.0], {0: 0, 1: 0}
    held = HeldResults(True, stored.get, clock=lambda: now[0])
    for s in (0, 0, 0, 0, 1):
        held.expect(s)
    held.add(0, [(0, {}, 0.0), (1, {}, 0.0)])
    assert held.due() == [0]  # an empty shard: written at once
    assert len(held.take(0)) == 2
    stored[0] = 2
    held.add(0, [(2, {}, 0.0)])
    assert held.due() == []  # fewer held than the shard holds, chains still out
    held.add(0, [(3, {}, 0.0)])
    assert held.due() == [0]  # as many as the shard holds
    held.take(0)
    stored[0] = 4
    held.add(0, [(4, {}, 0.0)])
    assert held.due() == [0]  # the shape's last chain
    held.take(0)
    held.add(1, [])  # a chain lost with its worker: nothing to write
    assert held.due() == []

    held = HeldResults(True, lambda s: 100, clock=lambda: now[0])
    held.expect(0), held.expect(0)
    held.add(0, [(0, {}, 0.0)])
    assert held.due() == []
    now[0] = 31.0  # WRITE_HOLD_S
    assert held.due() == [0]
    one_by_one = HeldResults(False, lambda s: 100)  # a version 1 store: each task's cases at once
    one_by_one.expect(0), one_by_one.expect(0)
    one_by_one.add(0, [(0, {}, 0.0)])
    assert one_by_one.due() == [0]
