"""Damage of every kind, in schema 1 and 2 stores, named by `status --verify` and reset by
`--retry-damaged` (PairStore.reset_damaged): a done case's data missing, short, unreadable or not
finite; a shape's arrays of another shape, dtype or codecs than the schema implies; a status array
deleted; a status code out of range. `export` says each in one line. No Ray here (test_sweep.py
recomputes them on Ray)."""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from typer.testing import CliRunner

from cli import app
from orchestrator.grid import SweepSpec
from orchestrator.sweep import check_request
from storage.location import StoreError
from storage.reader import PairReader
from storage.schema import DONE, PENDING
from storage.status import summarize
from storage.writer import PairStore
from trainer_fixtures import case_chunk, make_tiny_store

runner = CliRunner()
CASES = 4  # make_tiny_store's 2 pressures × 2 stiffnesses, one shape


def _metadata(loc: str, array: str) -> tuple[Path, dict]:
    path = Path(loc) / "shapes" / "0" / array / "zarr.json"
    return path, json.loads(path.read_text())


def _edit_metadata(loc: str, array: str, edit) -> None:
    path, meta = _metadata(loc, array)
    edit(meta)
    path.write_text(json.dumps(meta))


def delete_case_object(loc):  # schema 2: the shape's loaded shard, every case; schema 1: case 1's chunk
    case_chunk(loc, 0, "loaded", 1)[0].unlink()


def truncate_case_object(loc):
    path = case_chunk(loc, 0, "loaded", 1)[0]
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def write_nan(loc):  # bypasses the driver's validation, as a hand edit would
    array = zarr.open_group(loc, mode="r+")["shapes/0/unloaded"]
    row = array[1]
    row[5, 0] = np.nan
    array[1] = row


def add_nodes(loc):
    add_nodes_to(loc, 0)


def add_nodes_to(loc, shape_id: int) -> None:
    """Seven more nodes in the metadata of a shape's unloaded array than its mesh has."""
    path = Path(loc) / "shapes" / str(shape_id) / "unloaded" / "zarr.json"
    meta = json.loads(path.read_text())
    meta["shape"][1] += 7
    path.write_text(json.dumps(meta))


def change_dtype(loc):
    _edit_metadata(loc, "loaded", lambda m: m.__setitem__("data_type", "float64"))


def drop_checksums(loc):
    def edit(meta):
        codecs = meta["codecs"][0]["configuration"]["codecs"] if meta["codecs"][0]["name"] == "sharding_indexed" \
            else meta["codecs"]
        codecs[:] = [c for c in codecs if c["name"] != "crc32c"]
    _edit_metadata(loc, "unloaded", edit)


def delete_status(loc):
    shutil.rmtree(Path(loc) / "shapes" / "0" / "status")


def status_seven(loc):
    array = zarr.open_group(loc, mode="r+")["shapes/0/status"]
    codes = array[...]
    codes[3] = 7
    array[...] = codes


def tets_out_of_range(loc):
    array = zarr.open_group(loc, mode="r+")["shapes/0/tets"]
    tets = array[...]
    tets[0, 0] = 10_000
    array[...] = tets


SHARD = {1: [1], 2: list(range(CASES))}  # the cases a deleted or cut-short case object holds, by schema
# (damage, schema → the cases named (None: the shape), what the reason says)
DAMAGE = [
    (delete_case_object, SHARD, "loaded data are missing"),
    (truncate_case_object, SHARD, "does not read|checksum does not match"),
    (write_nan, {1: [1], 2: [1]}, "unloaded data are not finite"),
    (add_nodes, None, r"'unloaded' has shape \(4, 129, 3\), expected \(4, 122, 3\)"),
    (change_dtype, None, "'loaded' has dtype float64, expected float32"),
    (drop_checksums, None, "'unloaded' has (shard )?codecs"),
    (delete_status, None, "'status' is missing"),
    (status_seven, {1: [3], 2: [3]}, "status code 7 is none of 0 pending, 1 done, 2 failed"),
    (tets_out_of_range, None, "'tets' indexes nodes outside"),
]
IDS = [d[0].__name__ for d in DAMAGE]


@pytest.fixture(scope="module")
def intact(tmp_path_factory):
    """An intact store of each schema version (one shape, every case done)."""
    root = tmp_path_factory.mktemp("intact")
    return {v: make_tiny_store(root / f"v{v}.zarr", shapes=1, schema_version=v) for v in (1, 2)}


@pytest.fixture(params=[1, 2], ids=["schema1", "schema2"])
def store(request, intact, tmp_path):
    loc = str(tmp_path / "s.zarr")
    shutil.copytree(intact[request.param], loc)
    return request.param, loc


@pytest.mark.parametrize("damage,cases,reason", DAMAGE, ids=IDS)
def test_verify_names_every_kind_of_damage_and_retry_resets_it(store, damage, cases, reason):
    version, loc = store
    assert PairReader(loc).damaged() == []
    damage(loc)

    found = PairReader(loc).damaged()
    assert [k for _, k, _ in found] == ([None] if cases is None else cases[version])
    assert all(s == 0 and re.search(reason, why) for s, _, why in found), found
    res = runner.invoke(app, ["status", "--store", loc, "--verify"])
    assert res.exit_code == 1 and "damaged: shape 0" in res.output and "--retry-damaged" in res.output

    reset = PairStore.open(loc).reset_damaged([0])
    assert [(s, k) for s, k, _ in reset] == [(s, k) for s, k, _ in found]
    after = PairStore.open(loc)
    if cases is None:  # meshed again by the next sweep, every case of it solved again
        assert not after.shape_ready(0)
    else:
        assert after.status(0)[cases[version]].tolist() == [PENDING] * len(cases[version])
        assert PairReader(loc).damaged() == []


@pytest.mark.parametrize("damage,case", [(delete_case_object, 1), (add_nodes, 0), (delete_status, 0),
                                        (status_seven, 3)], ids=lambda d: getattr(d, "__name__", str(d)))
def test_export_train_and_generate_say_damage_in_one_line(store, damage, case, tmp_path):
    """export (no traceback, no file), the training reader and generate (without --retry-damaged) each
    name the store, the shape and the way to recompute it."""
    _, loc = store
    attrs = PairReader(loc).attrs
    damage(loc)
    out = tmp_path / "case.vtu"
    res = runner.invoke(app, ["export", "--store", loc, "--shape", "0", "--case", str(case), "-o", str(out)])
    assert res.exit_code == 2 and not out.exists(), res.output
    assert isinstance(res.exception, SystemExit) and len(res.output.strip().splitlines()) == 1
    assert loc in res.output and "--retry-damaged" in res.output

    from trainer.data.store_cases import read_store
    with pytest.raises(StoreError, match=r"shape 0 .*damaged.*`retry_damaged`"):
        read_store(loc)
    if damage is not delete_case_object:  # found without reading the cases: refused before Ray starts
        with pytest.raises(StoreError, match=r"shape 0 .*is damaged: .*generating with `retry_damaged`"):
            check_request(SweepSpec.from_attrs(attrs), loc, for_writing=False)
        check_request(SweepSpec.from_attrs(attrs), loc, for_writing=False, retry_damaged=True)


def test_status_counts_a_case_it_cannot_know(store):
    """A status code out of range or a damaged shape is counted ("unknown") and named without --verify,
    not left out of the counts."""
    _, loc = store
    status_seven(loc)
    s = summarize(loc).as_dict()
    assert (s["done"], s["unknown"], s["done"] + s["failed"] + s["pending"] + s["unknown"]) == (3, 1, CASES)
    assert s["table_damage"] == [{"shape": 0, "case": 3, "reason": "its status code 7 is none of 0 pending, "
                                                                    "1 done, 2 failed"}]
    res = runner.invoke(app, ["status", "--store", loc])
    assert res.exit_code == 1 and "status unknown 1 (25.0 %)" in res.output and "damaged: shape 0 case 3" in res.output

    delete_status(loc)
    s = summarize(loc).as_dict()
    assert (s["done"], s["unknown"]) == (0, CASES) and s["table_damage"][0]["case"] is None


def test_an_intact_store_has_no_damage(intact):
    for loc in intact.values():
        reader = PairReader(loc)
        assert reader.damaged() == [] and summarize(loc).table_damage == []
        assert len(list(reader.iter_done())) == CASES and (reader.status(0) == DONE).all()
