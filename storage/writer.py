"""Write access for the one writer of a store, the sweep driver: creating it, meshing shapes into it,
writing pairs only after they validate and read back equal, and the case tables it flushes in an
order that a killed driver cannot leave half-written (docs/data.md, "The store").
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import numpy as np

from .location import StoreError, is_checksum_error, is_url, local_path, open_group
from .reader import RECOMPUTE_HINT, shape_damage
from .schema import (COORD_DTYPE, DONE, PARAM_NAMES, PENDING, SCHEMA, SCHEMA_VERSION, SHARD_PER_SHAPE, STAT_NAMES,
                     STATUS_NAMES, UNITS, CaseCounts, case_layout, chunk_codecs, inspect_store, jsonable)


def validate_pair(tets: np.ndarray, n_nodes: int, unloaded, loaded, stats: dict, roundtrip_tol_mm: float) -> str | None:
    """None when the pair may be marked done, else the reason (one line)."""
    for name, x in (("unloaded", unloaded), ("loaded", loaded)):
        x = np.asarray(x)
        if x.shape != (n_nodes, 3):
            return f"{name} geometry has shape {x.shape}, expected ({n_nodes}, 3)"
        if not np.all(np.isfinite(x)):
            return f"{name} geometry has NaN or infinite coordinates"
        from solver.mesh import signed_tet_volumes

        if signed_tet_volumes(x, tets).min() <= 0:
            return f"{name} geometry has an inverted or degenerate tetrahedron"
    min_j = stats.get("min_jacobian", float("nan"))
    if not (np.isfinite(min_j) and min_j > 0):
        return f"min det F {min_j} is not > 0"
    err = stats.get("roundtrip_error_mm", float("nan"))
    if not (np.isfinite(err) and err <= roundtrip_tol_mm):
        return f"round-trip error {err:.3g} mm exceeds the tolerance {roundtrip_tol_mm:g} mm"
    res = stats.get("final_residual", float("nan"))
    if not np.isfinite(res):
        return "final residual is not finite"
    return None


def _write_rows(array, ks: list, block: np.ndarray) -> None:
    """array[k] = block[i] for the sorted case indices ks. Into a shard, in one write (one rewrite of
    the shard) as a coordinate selection (orthogonal ones fail to write into a sharded array in zarr
    3.1): that decodes the inner chunks it replaces, so when one of them is damaged (a case written
    before and damaged since) the rows are written run by run instead, whole inner chunks that
    nothing decodes. A chunk per case (version 1) is written run by run, each chunk whole, unread."""
    runs = [list(run) for _, run in itertools.groupby(range(len(ks)), key=lambda i: ks[i] - i)]
    if array.shards is not None and len(runs) > 1:
        n, d = block.shape[1:]
        try:
            array.vindex[np.asarray(ks)[:, None, None], np.arange(n)[None, :, None], np.arange(d)[None, None, :]] = block
            return
        except ValueError as exc:
            if not is_checksum_error(exc):
                raise
    for run in runs:
        array[ks[run[0]]:ks[run[-1]] + 1] = block[run[0]:run[-1] + 1]


def remove_partial_files(location) -> int:
    """Delete temporary `*.partial` files a killed writer left behind (local stores only)."""
    if is_url(location):
        return 0
    removed = 0
    for p in local_path(location).rglob("*.partial"):
        try:
            p.unlink()
            removed += 1
        except OSError:
            pass
    return removed


# --------------------------------------------------------------------------- the driver's writer


@dataclass
class _Table:
    status: np.ndarray  # [K] int8
    stats: np.ndarray  # [K, S]
    hosts: dict  # str(k) -> host
    failures: dict  # str(k) -> reason
    losses: dict  # str(k) -> runs whose task for it was lost with its worker or node (case left pending)
    dirty: bool = False


class PairStore:
    """Write access for the (single) sweep driver."""

    def __init__(self, root, location):
        self.root = root
        self.location = str(location)
        self.attrs = dict(root.attrs)
        self.n_cases = int(self.attrs["n_cases_per_shape"])
        self.params = np.asarray(self.attrs["case_params"], dtype=float).reshape(self.n_cases, len(PARAM_NAMES))
        self.roundtrip_tol_mm = float(self.attrs["acceptance"]["roundtrip_tol_mm"])
        self.sharded = case_layout(self.attrs) == SHARD_PER_SHAPE  # else a version 1 store, resumed as it is
        self._tables: dict[int, _Table] = {}
        self._handles: dict[int, dict] = {}  # shape → cached tets and array handles
        self._last_flush = time.monotonic()

    # ---- creation / opening

    @classmethod
    def create(cls, location, attrs: dict, storage_options: dict | None = None) -> "PairStore":
        """Create the root group with its attributes (fails if a store exists there)."""
        base = {"schema": SCHEMA, "schema_version": SCHEMA_VERSION, "units": UNITS,
                "param_names": list(PARAM_NAMES), "stat_names": list(STAT_NAMES),
                "status_codes": {v: k for k, v in STATUS_NAMES.items()},
                "coordinate_dtype": np.dtype(COORD_DTYPE).name, "case_layout": SHARD_PER_SHAPE,
                "created": _now_iso(), "runs": [],
                "mesh_failures": {}}
        base.update(attrs)
        for key in ("n_cases_per_shape", "case_params", "acceptance", "grid"):
            if key not in base:
                raise ValueError(f"store attributes need {key!r}")
        if not is_url(location) and not local_path(location).parent.exists():
            raise StoreError(f"folder {local_path(location).parent} does not exist")
        # "w-" refuses a folder with anything in it; the writer lock's file (the driver creating the
        # store holds it, storage.lock) is the one thing allowed there, once inspect_store found no store
        only_lock = not is_url(location) and local_path(location).is_dir() and inspect_store(location) is None
        root = open_group(location, "a" if only_lock else "w-", storage_options)
        root.attrs.update(jsonable(base))
        root.create_group("shapes")
        return cls(root, location)

    @classmethod
    def open(cls, location, storage_options: dict | None = None) -> "PairStore":
        if inspect_store(location, storage_options) is None:
            raise StoreError(f"no heartctl store at {location}")
        remove_partial_files(location)
        return cls(open_group(location, "r+", storage_options), location)

    def update_attrs(self, **values) -> None:
        self.root.attrs.update(jsonable(values))
        self.attrs.update(jsonable(values))

    @property
    def shapes(self) -> int:
        """The store's shape count (the root attr grid["shapes"]): its shapes are 0 … shapes − 1."""
        return int(self.attrs["grid"]["shapes"])

    def grow_shapes(self, shapes: int) -> None:
        """Raise the shape count to `shapes`; the shapes added are pending until a sweep meshes them
        (write_shape, in the store's own case layout) and solves their cases. Done cases stay as they
        are. StoreError for a count below the store's: a store does not shrink."""
        if shapes < self.shapes:
            raise StoreError(f"{self.location} has {self.shapes} shapes; shrinking a store to {shapes} is not "
                             f"supported")
        if shapes > self.shapes:
            self.update_attrs(grid={**self.attrs["grid"], "shapes": int(shapes)})

    # ---- runs (audit trail)

    def begin_run(self, info: dict) -> int:
        runs = list(self.attrs.get("runs", []))
        runs.append(jsonable({"started_at": time.time(), "started": _now_iso(), **info}))
        self.update_attrs(runs=runs)
        return len(runs) - 1

    def end_run(self, index: int, info: dict) -> None:
        runs = list(self.attrs.get("runs", []))
        runs[index] = {**runs[index], **jsonable({"ended_at": time.time(), **info})}
        self.update_attrs(runs=runs)

    def record_mesh_failure(self, shape_id: int, reason: str) -> None:
        failures = dict(self.attrs.get("mesh_failures", {}))
        failures[str(shape_id)] = reason
        self.update_attrs(mesh_failures=failures)

    # ---- shapes

    def _shapes(self):
        return self.root["shapes"]

    def shape_ready(self, shape_id: int) -> bool:
        shapes = self._shapes()
        key = str(shape_id)
        if key not in shapes:
            return False
        return bool(shapes[key].attrs.get("ready", False))

    def write_shape(self, shape_id: int, nodes, tets, endo, epi, base, coefficients, info: dict | None = None) -> None:
        """Write a shape's mesh and create every case array of it, then mark the shape ready."""
        shapes = self._shapes()
        key = str(shape_id)
        if key in shapes:
            del shapes[key]  # a shape group left unfinished by a killed driver
        n, K = int(np.asarray(nodes).shape[0]), self.n_cases
        g = shapes.create_group(key)
        comp = chunk_codecs()
        g.create_array("ed_reference", data=np.asarray(nodes, dtype=np.float64), compressors=comp)
        for name, arr in (("tets", tets), ("endo", endo), ("epi", epi), ("base", base)):
            g.create_array(name, data=np.asarray(arr, dtype=np.int32), compressors=comp)
        g.create_array("coefficients", data=np.asarray(coefficients, dtype=np.float64), compressors=comp)
        g.create_array("params", data=self.params.astype(np.float64), compressors=comp)
        g.create_array("status", shape=(K,), chunks=(K,), dtype=np.int8, fill_value=PENDING, compressors=comp)
        g.create_array("stats", shape=(K, len(STAT_NAMES)), chunks=(K, len(STAT_NAMES)), dtype=np.float64,
                       fill_value=np.nan, compressors=comp)
        for name in ("unloaded", "loaded"):  # a shard per shape (an object per case in a version 1 store)
            g.create_array(name, shape=(K, n, 3), chunks=(1, n, 3), shards=(K, n, 3) if self.sharded else None,
                           dtype=COORD_DTYPE, fill_value=np.nan, compressors=comp,
                           dimension_names=("case", "node", "xyz"))
        g.attrs.update(jsonable({"shape_id": shape_id, "n_nodes": n, "n_tets": int(np.asarray(tets).shape[0]),
                                  "n_cases": K, "hosts": {}, "failures": {}, "info": info or {}}))
        g.attrs.update({"ready": True})  # last: a shape without it is re-meshed on resume
        self._tables.pop(shape_id, None)
        failures = dict(self.attrs.get("mesh_failures", {}))
        if failures.pop(key, None) is not None:  # an earlier run's failure to mesh it no longer holds
            self.update_attrs(mesh_failures=failures)
        self._handles.pop(shape_id, None)

    def update_shape_attrs(self, shape_id: int, **values) -> None:
        """Extra per-shape attributes (e.g. provenance of imported data). Written through the cached
        group handle, whose attribute dict later flushes rewrite whole."""
        self._handle(shape_id)["group"].attrs.update(jsonable(values))

    def _handle(self, shape_id: int) -> dict:
        if shape_id not in self._handles:
            g = self._shapes()[str(shape_id)]
            self._handles[shape_id] = {"group": g, "tets": g["tets"][...], "n": int(g.attrs["n_nodes"]),
                                       "unloaded": g["unloaded"], "loaded": g["loaded"], "status": g["status"],
                                       "stats": g["stats"]}
        return self._handles[shape_id]

    def tets(self, shape_id: int) -> np.ndarray:
        return self._shapes()[str(shape_id)]["tets"][...]

    def mesh_arrays(self, shape_id: int) -> dict:
        g = self._shapes()[str(shape_id)]
        return {name: g[name][...] for name in ("ed_reference", "tets", "endo", "epi", "base")}

    # ---- the case table (cached in memory, flushed by the driver)

    def table(self, shape_id: int) -> _Table:
        if shape_id not in self._tables:
            g = self._shapes()[str(shape_id)]
            self._tables[shape_id] = _Table(g["status"][...], g["stats"][...], dict(g.attrs.get("hosts", {})),
                                            dict(g.attrs.get("failures", {})), dict(g.attrs.get("losses", {})))
        return self._tables[shape_id]

    def status(self, shape_id: int) -> np.ndarray:
        return self.table(shape_id).status.copy()

    def counts(self, shapes: int) -> CaseCounts:
        """The cases of shapes 0 … shapes − 1 by status, as this writer's case tables hold them now."""
        return sum((CaseCounts.of_status(self.table(s).status) if self.shape_ready(s)
                    else CaseCounts(pending=self.n_cases) for s in range(shapes)), CaseCounts())

    def write_pair(self, shape_id: int, k: int, unloaded, loaded, stats: dict) -> str | None:
        """write_pairs for one case: None when case k may be marked done, else the reason it may not."""
        return self.write_pairs(shape_id, {k: (unloaded, loaded, stats)})[k]

    def write_pairs(self, shape_id: int, pairs: dict) -> dict:
        """Validate, write and read back cases of one shape; pairs maps k → (unloaded, loaded, stats).
        The valid ones are written in one write per array (in a sharded store, one rewrite of the
        shape's shard, whose other cases are copied as they are), then read back. Returns k → None
        when the case may be marked done, else the reason it may not (nothing is marked here)."""
        h = self._handle(shape_id)
        reasons, valid = {}, {}
        for k, (unloaded, loaded, stats) in pairs.items():
            reason = validate_pair(h["tets"], h["n"], unloaded, loaded, stats, self.roundtrip_tol_mm)
            if reason is None:
                valid[int(k)] = (unloaded, loaded)
            else:
                reasons[k] = f"invalid result: {reason}"
        ks = sorted(valid)
        try:
            self._write_and_read_back(h, ks, valid, reasons)
        except ValueError as exc:  # a shard whose index is damaged cannot be rewritten in part
            if not (self.sharded and is_checksum_error(exc)):
                raise
            if (self.table(shape_id).status == DONE).any():
                raise StoreError(f"{self.location}: shape {shape_id}: the index of its case shard is damaged; "
                                 f"{RECOMPUTE_HINT}") from None
            self._drop_cases(shape_id)  # no done case in it: nothing a reader may see
            self._write_and_read_back(h, ks, valid, reasons)
        return {k: reasons.get(k) for k in pairs}

    @staticmethod
    def _write_and_read_back(h: dict, ks: list, valid: dict, reasons: dict) -> None:
        """Both arrays' rows ks written, read back, and a reason noted for any that differ."""
        for i, name in enumerate(("unloaded", "loaded") if ks else ()):
            block = np.stack([np.asarray(valid[k][i], dtype=COORD_DTYPE) for k in ks])
            _write_rows(h[name], ks, block)
            back = h[name].oindex[ks]
            for j, k in enumerate(ks):
                if k not in reasons and not np.array_equal(back[j], block[j]):
                    reasons[k] = f"read-back of {name} differs from what was written"

    def set_case(self, shape_id: int, k: int, status: int, stats_row: np.ndarray, host: str | None = None,
                 reason: str | None = None) -> None:
        t = self.table(shape_id)
        t.status[k] = status
        t.stats[k] = stats_row
        if host:
            t.hosts[str(k)] = host
        if reason is None:
            t.failures.pop(str(k), None)
        else:
            t.failures[str(k)] = reason
        t.dirty = True

    def reset_damaged(self, shape_ids) -> list[tuple[int, int | None, str]]:
        """Mark every damaged case of the shapes pending again, so that a sweep recomputes it: a done
        case whose chunks do not read back intact, a status code out of range. A shape whose arrays
        are not what the schema implies is marked not ready: the sweep meshes it again and solves
        every case of it. Returns the damage as (shape, case, reason), case None for a whole shape."""
        found = []
        for s in shape_ids:
            damage = shape_damage(self._shapes()[str(s)], self.attrs)
            if damage and damage[0][0] is None:
                self._unready(s)
            for k, _ in (damage if not damage or damage[0][0] is not None else ()):
                self.set_case(s, k, PENDING, np.full(len(STAT_NAMES), np.nan))
            found.extend((s, k, why) for k, why in damage)
        self.flush()
        for s in sorted({s for s, k, _ in found if k is not None}):
            if self.sharded and not (self.table(s).status == DONE).any():
                self._drop_cases(s)
        return found

    def _unready(self, shape_id: int) -> None:
        """Mark a shape not ready: the next sweep meshes it again, its cases all pending."""
        self._shapes()[str(shape_id)].attrs.update({"ready": False})
        self._tables.pop(shape_id, None)
        self._handles.pop(shape_id, None)

    def _drop_cases(self, shape_id: int) -> None:
        """Delete the case shards of a shape that has no done case: a shard whose index is damaged
        cannot be rewritten in part (zarr reads it first), and holds nothing a reader may see."""
        from zarr.core.sync import sync

        h = self._handle(shape_id)
        for name in ("unloaded", "loaded"):
            array = h[name]
            sync(array.store.delete(f"{array.path}/{array.metadata.encode_chunk_key((0, 0, 0))}"))

    def note_loss(self, shape_id: int, k: int) -> int:
        """Count a task for case k lost with its worker or node (the case stays pending); returns
        how many times that has happened to it, over all runs."""
        t = self.table(shape_id)
        t.losses[str(k)] = int(t.losses.get(str(k), 0)) + 1
        t.dirty = True
        return t.losses[str(k)]

    def flush(self, min_interval_s: float = 0.0) -> bool:
        """Write changed case tables: stats, then attrs (hosts, reasons), then status."""
        if time.monotonic() - self._last_flush < min_interval_s:
            return False
        for shape_id, t in self._tables.items():
            if not t.dirty:
                continue
            h = self._handle(shape_id)
            h["stats"][...] = t.stats
            h["group"].attrs.update({"hosts": t.hosts, "failures": t.failures, "losses": t.losses})
            h["status"][...] = t.status
            t.dirty = False
        self._last_flush = time.monotonic()
        return True


def _now_iso() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


def stats_row(values: dict) -> np.ndarray:
    return np.array([float(values.get(name, np.nan)) if values.get(name) is not None else np.nan
                     for name in STAT_NAMES], dtype=np.float64)
