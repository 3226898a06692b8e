"""The schema of the Zarr 3 store of FE pairs (docs/data.md, "The store"): names, codes, units, the
arrays a shape must hold, and the checks that a store and a shape are what the schema says.

Layout (one writer: the sweep driver)::

    /                       attrs: schema, schema_version, units, grid, fidelity, seed, mesh_nodes,
                                   base, solver_version, stat_names, runs, ...
    shapes/<id>/            attrs: shape_id, n_nodes, n_tets, n_cases, ready, hosts, failures, losses,
                                   info (cavity_volume_ml, mesh quality, meshing host and time)
        ed_reference [n,3]  float64, mm (the ED mesh the pairs were solved on)
        tets [m,4]          int32
        endo/epi/base [k,3] int32 boundary triangles (outward)
        coefficients [d]    float64, shape-model mode coefficients (SD units)
        params [K,4]        float64, the case table's parameters (P mmHg, C Pa, θendo °, θepi °)
        status [K]          int8, 0 pending / 1 done / 2 failed
        stats [K,S]         float64, solver and timing statistics (names in the root attr stat_names)
        unloaded [K,n,3]    float32, mm, one shard per shape holding one chunk per case (fill NaN)
        loaded [K,n,3]      float32, mm, likewise

Schema version 2 stores `unloaded` and `loaded` with Zarr's sharding codec (root attr case_layout
"shard per shape"): one object per shape and array, an inner chunk per case, each inner chunk with its
own CRC-32C (and the shard index with one), so a damaged case is named alone. Version 1 stores (no
case_layout: "chunk per case") hold one object per case and array; they are read and resumed as
they are.

Coordinates are float32 (precision ≈ 4e-6 mm at 60 mm, far below the solver's 1e-4 mm tolerance);
this keeps the full paper sweep at ~1000 nodes near 0.4 GB compressed.

A case's status becomes `done` only after its two chunks were written, read back and found equal,
finite, free of inverted tets, and the solve met its convergence tolerance. Status, stats and the
per-case hosts/failure reasons are rewritten by the driver in that order (stats, attrs, status), so
a driver killed at any point leaves, at worst, a finished case still `pending` (it is recomputed),
never a `done` case with missing data. Every object is written whole: local writes are atomic
(zarr ≥ 3.1.3's LocalStore writes a temporary file and renames it), object stores (S3, GCS) put
whole objects. Writing cases into a shard rewrites it whole, the other cases' inner chunks copied as
they are (bytes and checksum), so a writer killed mid-write leaves the old shard or the new one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .location import (StoreError, check_bucket, first_line, is_url, local_path, object_store_problem, open_group,
                       read_error_words)
from .lock import LOCK_NAME

SCHEMA = "heartctl.lv-pairs"
SCHEMA_VERSION = 2
READ_VERSIONS = (1, 2)
CHUNK_PER_CASE, SHARD_PER_SHAPE = "chunk per case", "shard per shape"  # the root attr case_layout (version 1: absent)
PENDING, DONE, FAILED = 0, 1, 2
STATUS_NAMES = {PENDING: "pending", DONE: "done", FAILED: "failed"}
PARAM_NAMES = ("pressure_mmhg", "stiffness_pa", "helix_endo_deg", "helix_epi_deg")
PAIR_STAT_NAMES = (
    "inverse_updates", "inverse_newton_iterations", "forward_newton_iterations", "forward_load_steps",
    "inverse_mismatch_mm", "roundtrip_error_mm", "final_residual", "min_jacobian",
    "inverse_wall_s", "forward_wall_s", "assembly_s", "linear_s",
)
STAT_NAMES = PAIR_STAT_NAMES + (
    "solve_attempts",  # 1, or 2 when the robust retry ran
    "task_wall_s",  # solve time inside the task (all attempts)
    "submitted_at", "started_at", "finished_at", "stored_at",  # unix times: driver, worker, worker, driver
    "worker_pid",
    "run",  # index into the root attr `runs`
)
UNITS = {"length": "mm", "pressure": "mmHg", "stiffness": "Pa", "angle": "deg", "time": "s"}


@dataclass(frozen=True)
class CaseCounts:
    """Cases of a store by status. `pending` includes every case of a shape not meshed yet; `unknown`
    counts cases whose status cannot be known (their shape's arrays are not what the schema implies,
    or their status code is out of range); `meshed` counts shapes."""
    done: int = 0
    failed: int = 0
    pending: int = 0
    unknown: int = 0
    meshed: int = 0

    @classmethod
    def of_status(cls, status: np.ndarray) -> "CaseCounts":
        """The counts of one meshed shape's status codes."""
        status = np.asarray(status)
        known = int(np.isin(status, list(STATUS_NAMES)).sum())
        return cls(int((status == DONE).sum()), int((status == FAILED).sum()), int((status == PENDING).sum()),
                   status.size - known, 1)

    def __add__(self, other: "CaseCounts") -> "CaseCounts":
        return CaseCounts(*(getattr(self, f) + getattr(other, f) for f in self.__dataclass_fields__))

    @property
    def total(self) -> int:
        return self.done + self.failed + self.pending + self.unknown

    def to_run(self, retry_failed: bool = False) -> int:
        """Cases a sweep would submit: pending and unknown ones, and failed ones when retried."""
        return self.pending + self.unknown + (self.failed if retry_failed else 0)
COORD_DTYPE = np.float32


def jsonable(value):
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def inspect_store(location, storage_options: dict | None = None) -> dict | None:
    """Root attributes of the heartctl store at `location`, or None when there is none yet.
    Read-only. Raises StoreError for a path that is a file, a folder that is not a Zarr store,
    a Zarr store of another schema or schema version."""
    if not is_url(location):
        path = local_path(location)
        if path.is_file():
            raise StoreError(f"store path {path} is a file, not a Zarr store")
        if not path.exists():
            if not path.parent.exists():
                raise StoreError(f"folder {path.parent} does not exist")
            return None
        if path.is_dir() and all(p.name == LOCK_NAME for p in path.iterdir()):
            return None  # empty, or holding only the lock of a driver about to create the store (storage.lock)
        if not (path / "zarr.json").is_file():
            raise StoreError(f"{path} is a non-empty folder that is not a Zarr 3 store")
    try:
        root = open_group(location, "r", storage_options)
    except Exception as exc:  # zarr raises several types for missing / unreadable groups
        if isinstance(exc, FileNotFoundError) or type(exc).__name__ in ("GroupNotFoundError", "NodeNotFoundError"):
            check_bucket(location, storage_options)
            return None
        problem = object_store_problem(location, exc)
        raise StoreError(f"store {location}: {problem}" if problem else
                         f"cannot open {location} as a Zarr 3 group: {first_line(exc)}") from None
    attrs = dict(root.attrs)
    if attrs.get("schema") != SCHEMA:
        found = attrs.get("schema", "none")
        raise StoreError(f"{location} is a Zarr store of another schema ({found!r}, expected {SCHEMA!r})")
    if attrs.get("schema_version") not in READ_VERSIONS:
        raise StoreError(f"{location} has schema version {attrs.get('schema_version')!r}; "
                         f"this heartctl reads versions {' and '.join(map(str, READ_VERSIONS))}")
    _check_root_attrs(location, attrs)
    if case_layout(attrs) not in (CHUNK_PER_CASE, SHARD_PER_SHAPE):
        raise StoreError(f"{location}: root attribute 'case_layout' is {attrs.get('case_layout')!r}, expected "
                         f"{SHARD_PER_SHAPE!r}; the store was edited or damaged")
    return attrs


def case_layout(attrs: dict) -> str | None:
    """How a store keeps its case arrays: SHARD_PER_SHAPE (schema version 2) or CHUNK_PER_CASE (version 1)."""
    return CHUNK_PER_CASE if attrs.get("schema_version") == 1 else attrs.get("case_layout")


ROOT_ATTR_TYPES = {"grid": dict, "case_params": list, "n_cases_per_shape": int, "acceptance": dict, "runs": list,
                   "param_names": list, "stat_names": list}


def _check_root_attrs(location, attrs: dict) -> None:
    """StoreError when a root attribute every reader and writer relies on is missing, of the wrong
    type, or when the case table disagrees with its own size (a hand-edited store)."""
    for name, kind in ROOT_ATTR_TYPES.items():
        if not isinstance(attrs.get(name), kind) or isinstance(attrs.get(name), bool):
            raise StoreError(f"{location}: root attribute {name!r} is missing or not a {kind.__name__} "
                             f"(got {type(attrs.get(name)).__name__}); the store was edited or damaged")
    if len(attrs["case_params"]) != attrs["n_cases_per_shape"]:
        raise StoreError(f"{location}: case_params lists {len(attrs['case_params'])} cases, n_cases_per_shape says "
                         f"{attrs['n_cases_per_shape']}; the store was edited or damaged")


# --------------------------------------------------------------------------- a shape's arrays, as the schema says

CODEC_NAMES = ("bytes", "blosc", "crc32c")  # every chunk: chunk_codecs() after zarr's bytes codec
INDEX_CODEC_NAMES = ("bytes", "crc32c")  # a shard's index
MESH_ARRAYS = ("ed_reference", "tets", "endo", "epi", "base", "coefficients")
SHAPE_ARRAYS = MESH_ARRAYS + ("params", "status", "stats", "unloaded", "loaded")


@dataclass(frozen=True)
class ArraySpec:
    """What one array of a shape must be: its shape (None: any length), dtype, and for the case
    arrays their chunks, shards (None: a chunk per case) and NaN fill."""
    shape: tuple
    dtype: str
    chunks: tuple | None = None
    shards: tuple | None = None
    case_array: bool = False


def expected_arrays(shape_attrs: dict, root_attrs: dict) -> dict[str, ArraySpec]:
    """The arrays of a shape as the schema, the store's case table and the shape's node and tet
    counts imply."""
    n, m = shape_attrs["n_nodes"], shape_attrs["n_tets"]
    K, S = int(root_attrs["n_cases_per_shape"]), len(root_attrs["stat_names"])
    shards = (K, n, 3) if case_layout(root_attrs) == SHARD_PER_SHAPE else None
    case = ArraySpec((K, n, 3), np.dtype(COORD_DTYPE).name, (1, n, 3), shards, case_array=True)
    return {"ed_reference": ArraySpec((n, 3), "float64"), "tets": ArraySpec((m, 4), "int32"),
            **{name: ArraySpec((None, 3), "int32") for name in ("endo", "epi", "base")},
            "coefficients": ArraySpec((None,), "float64"), "params": ArraySpec((K, len(PARAM_NAMES)), "float64"),
            "status": ArraySpec((K,), "int8"), "stats": ArraySpec((K, S), "float64"),
            "unloaded": case, "loaded": case}


def shape_problem(group, root_attrs: dict, read: bool = False) -> str | None:
    """Why a ready shape's arrays cannot be trusted, in words, or None: a node or tet count attribute
    missing, an array missing, or of another shape, dtype, chunking or codecs than expected_arrays.
    With `read`, its mesh and case table are read too: each must read back (checksums), the mesh be
    finite and its tets and boundary triangles index its nodes."""
    attrs = group.attrs
    for name in ("n_nodes", "n_tets"):
        if not isinstance(attrs.get(name), int) or isinstance(attrs.get(name), bool) or attrs.get(name) < 1:
            return f"its attribute {name!r} is missing or not a positive integer"
    arrays = {}
    for name, spec in expected_arrays(dict(attrs), root_attrs).items():
        array, problem = _open_array(group, name)
        problem = problem or _array_mismatch(name, array, spec)
        if problem:
            return problem
        arrays[name] = array
    return _content_problem(arrays, attrs["n_nodes"]) if read else None


def _open_array(group, name: str):
    try:
        return group[name], None
    except (TypeError, AttributeError, NameError):
        raise
    except KeyError:
        return None, f"its array {name!r} is missing"
    except Exception as exc:
        return None, f"its array {name!r} does not open ({first_line(exc)[:100]})"


def _array_mismatch(name: str, array, spec: ArraySpec) -> str | None:
    """How an array differs from its spec, or None."""
    import zarr

    if not isinstance(array, zarr.Array):
        return f"{name!r} is not an array"
    shape = tuple(array.shape)
    if len(shape) != len(spec.shape) or any(e is not None and e != g for e, g in zip(spec.shape, shape)):
        want = "(" + ", ".join("any" if e is None else str(e) for e in spec.shape) + ")"
        return f"its array {name!r} has shape {shape}, expected {want}"
    if str(array.dtype) != spec.dtype:
        return f"its array {name!r} has dtype {array.dtype}, expected {spec.dtype}"
    if spec.case_array:
        if tuple(array.chunks) != spec.chunks or (array.shards and tuple(array.shards)) != spec.shards:
            return (f"its array {name!r} is chunked {tuple(array.chunks)} in shards {array.shards}, expected "
                    f"{spec.chunks} in shards {spec.shards}")
        if not np.isnan(array.fill_value):
            return f"its array {name!r} has fill value {array.fill_value}, expected NaN"
    codecs = _codec_problem(array)
    return f"its array {name!r} {codecs}" if codecs else None


def _codec_problem(array) -> str | None:
    names = lambda codecs: tuple(c.to_dict()["name"] for c in codecs)  # noqa: E731
    codecs = array.metadata.codecs
    if array.shards is None:
        found = names(codecs)
        return None if found == CODEC_NAMES else f"has codecs {list(found)}, expected {list(CODEC_NAMES)}"
    inner, index = names(codecs[0].codecs), names(codecs[0].index_codecs)
    if (inner, index) == (CODEC_NAMES, INDEX_CODEC_NAMES) and names(codecs) == ("sharding_indexed",):
        return None
    return (f"has shard codecs {list(inner)} and index codecs {list(index)}, expected {list(CODEC_NAMES)} and "
            f"{list(INDEX_CODEC_NAMES)}")


def _content_problem(arrays: dict, n_nodes: int) -> str | None:
    """Why the mesh and case table of a shape do not read back as data, or None."""
    values = {}
    for name in MESH_ARRAYS + ("params", "status", "stats"):
        try:
            values[name] = arrays[name][...]
        except (TypeError, AttributeError, NameError):
            raise
        except Exception as exc:
            return f"its array {name!r} is damaged: {read_error_words(exc)}"
    if not np.isfinite(values["ed_reference"]).all():
        return "its mesh's node coordinates are not finite"
    for name in ("tets", "endo", "epi", "base"):
        if values[name].size and (values[name].min() < 0 or values[name].max() >= n_nodes):
            return f"its array {name!r} indexes nodes outside 0–{n_nodes - 1}"
    return None


def chunk_codecs() -> tuple:
    """Every chunk is compressed, then carries a CRC-32C of its bytes, checked on every read: a damaged
    chunk fails to read (one line, by reading_store) instead of returning wrong geometry."""
    from zarr.codecs import BloscCodec, Crc32cCodec

    return BloscCodec(cname="zstd", clevel=5, shuffle="shuffle"), Crc32cCodec()


SHARD_INDEX_BYTES_PER_CASE = 16  # a shard index's (offset, length) per inner chunk; plus 4 bytes of CRC-32C a shard


def encoded_case_bytes(unloaded: np.ndarray, loaded: np.ndarray) -> int:
    """Bytes one case takes in the store (both chunks, compressed as the store does, and their
    entries in the shards' indexes)."""
    import zarr
    from zarr.storage import MemoryStore

    store = MemoryStore()
    g = zarr.open_group(store, mode="w", zarr_format=3)
    n = np.asarray(unloaded).shape[0]
    for name, x in (("unloaded", unloaded), ("loaded", loaded)):
        a = g.create_array(name, shape=(1, n, 3), chunks=(1, n, 3), dtype=COORD_DTYPE, fill_value=np.nan,
                           compressors=chunk_codecs())
        a[0] = np.asarray(x, dtype=COORD_DTYPE)
    chunks = sum(len(v.to_bytes()) for k, v in store._store_dict.items() if "/c/" in k)
    return chunks + 2 * SHARD_INDEX_BYTES_PER_CASE
