"""The Zarr 3 store of FE pairs (DESIGN.md, "The Zarr store").

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

import itertools
import json
import os
import re
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
COORD_DTYPE = np.float32


class StoreError(ValueError):
    """A store that cannot be used as asked; the message is one line."""


@contextmanager
def reading_store(location, keep: tuple = ()):
    """Errors from zarr, numcodecs or the filesystem while a store is read (a damaged chunk fails its
    CRC-32C, or raises RuntimeError from its decompressor) as one-line StoreErrors, which the CLI
    reports with exit 2 and Ray Train workers refuse at once instead of retrying. StoreErrors, the
    exception types in `keep` and programming errors (TypeError, AttributeError, NameError) pass
    unchanged, except a checksum mismatch (a ValueError in zarr), which is always damage, and an
    object store's refusal or silence (object_store_problem), which is said in words."""
    try:
        yield
    except Exception as exc:
        if _is_checksum_error(exc):
            raise StoreError(f"cannot read store {location}: a stored chunk is damaged (its checksum does not "
                             f"match)") from None
        if isinstance(exc, (StoreError, TypeError, AttributeError, NameError)):
            raise
        reason = object_store_problem(location, exc)
        if reason is None and isinstance(exc, keep):
            raise
        reason = reason or (f"missing {exc.args[0]!r}" if isinstance(exc, KeyError) and exc.args else
                            (str(exc).splitlines()[0] if str(exc) else type(exc).__name__))
        raise StoreError(f"cannot read store {location}: {reason}") from None


def _is_checksum_error(exc: Exception) -> bool:
    return type(exc) is ValueError and "checksum do not match" in str(exc)


# --------------------------------------------------------------------------- opening


def is_url(location: str) -> bool:
    return "://" in str(location) and not str(location).startswith("file://")


def _local_path(location) -> Path:
    s = str(location)
    return Path(s[len("file://"):] if s.startswith("file://") else s)


def _open_group(location, mode: str, storage_options: dict | None = None):
    import zarr

    if is_url(location):
        return zarr.open_group(str(location), mode=mode, zarr_format=3,
                               storage_options=url_options(location, storage_options))
    from zarr.storage import LocalStore

    return zarr.open_group(LocalStore(_local_path(location), read_only=(mode == "r")), mode=mode, zarr_format=3)


# --------------------------------------------------------------------------- object stores (s3://)

ENDPOINT_VARS = ("AWS_ENDPOINT_URL_S3", "AWS_ENDPOINT_URL")  # botocore's names, the service's own first


def s3_endpoint(storage_options: dict | None = None) -> str | None:
    """The S3-compatible server an s3:// store is opened at (MinIO, Ceph, moto): the options' own
    endpoint_url, else AWS_ENDPOINT_URL_S3, else AWS_ENDPOINT_URL; None means AWS itself."""
    given = (storage_options or {}).get("endpoint_url")
    return given or next((os.environ[v] for v in ENDPOINT_VARS if os.environ.get(v)), None)


def url_options(location, storage_options: dict | None = None) -> dict | None:
    """fsspec options of a store URL. For s3://, the endpoint of s3_endpoint (older botocore does not
    read the variables itself), and no cached listings, so that a reader sees the shapes a running
    sweep adds; credentials and region come from the usual AWS variables (AWS_ACCESS_KEY_ID,
    AWS_SECRET_ACCESS_KEY, AWS_DEFAULT_REGION) or an instance profile, read by botocore."""
    options = dict(storage_options or {})
    if not str(location).startswith("s3://"):
        return options or None
    endpoint = s3_endpoint(options)
    if endpoint:
        options["endpoint_url"] = endpoint
    options.setdefault("use_listings_cache", False)
    return options


def _exception_chain(exc: BaseException):
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


CREDENTIAL_CODES = frozenset({"InvalidAccessKeyId", "SignatureDoesNotMatch", "AccessDenied", "Forbidden", "403",
                              "ExpiredToken", "InvalidToken", "InvalidClientTokenId"})
UNREACHABLE_ERRORS = frozenset({"EndpointConnectionError", "ConnectTimeoutError", "ReadTimeoutError",
                                "ClientConnectorError", "ServerDisconnectedError", "ConnectionClosedError"})


def object_store_problem(location, exc: BaseException) -> str | None:
    """What an object store (s3://) said, in words, when exc (or an error it was raised from) is its
    refusal or its silence: a missing bucket, credentials refused or missing, an endpoint that does
    not answer. None for a local store and for any other error."""
    if not str(location).startswith("s3://"):
        return None
    server = _server()
    for e in _exception_chain(exc):
        name = type(e).__name__
        code = str(((getattr(e, "response", None) or {}).get("Error") or {}).get("Code", ""))
        if name == "NoSuchBucket" or code == "NoSuchBucket" or "bucket does not exist" in str(e):
            return f"its bucket {_bucket(location)!r} does not exist on {server}; create it or fix the URL"
        if name in ("NoCredentialsError", "PartialCredentialsError"):
            return (f"no AWS credentials found for {server}; set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY "
                    f"(or use an instance profile)")
        if code in CREDENTIAL_CODES or isinstance(e, PermissionError):
            return (f"{server} refused access ({_first_line(e)}); check AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY "
                    f"and the bucket's permissions")
        if name in UNREACHABLE_ERRORS or isinstance(e, (ConnectionError, TimeoutError)):
            return (f"{server} does not answer ({name})"
                    + ("" if s3_endpoint() else "; an S3-compatible server is named by AWS_ENDPOINT_URL"))
    return None


def _bucket(location) -> str:
    return str(location)[len("s3://"):].split("/", 1)[0]


def _check_bucket(location, storage_options: dict | None = None) -> None:
    """StoreError when the bucket of an s3:// store is missing or refuses these credentials: an s3://
    URL where no store is yet is a new store only in a bucket that exists."""
    import fsspec

    if not str(location).startswith("s3://"):
        return
    fs = fsspec.filesystem("s3", **(url_options(location, storage_options) or {}))
    try:
        fs.info(_bucket(location))
    except Exception as exc:
        problem = (f"its bucket {_bucket(location)!r} does not exist on {_server()}; create it or fix the URL"
                   if isinstance(exc, FileNotFoundError) else object_store_problem(location, exc))  # 404: head_bucket's
        if problem is None:
            raise
        raise StoreError(f"store {location}: {problem}") from None


def _server() -> str:
    where = s3_endpoint()
    return f"the S3 endpoint {where}" if where else "S3"


LOCK_NAME = ".heartctl-writer.lock"  # the writer lock's file in a local store (storage.lock)


def inspect_store(location, storage_options: dict | None = None) -> dict | None:
    """Root attributes of the heartctl store at `location`, or None when there is none yet.
    Read-only. Raises StoreError for a path that is a file, a folder that is not a Zarr store,
    a Zarr store of another schema or schema version."""
    if not is_url(location):
        path = _local_path(location)
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
        root = _open_group(location, "r", storage_options)
    except Exception as exc:  # zarr raises several types for missing / unreadable groups
        if isinstance(exc, FileNotFoundError) or type(exc).__name__ in ("GroupNotFoundError", "NodeNotFoundError"):
            _check_bucket(location, storage_options)
            return None
        problem = object_store_problem(location, exc)
        raise StoreError(f"store {location}: {problem}" if problem else
                         f"cannot open {location} as a Zarr 3 group: {_first_line(exc)}") from None
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


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _damage(exc: Exception) -> str:
    """A chunk read error in words: a checksum mismatch, or the error's first line."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return "its checksum does not match (changed bytes)" if _is_checksum_error(exc) else f"it does not read ({text[:100]})"


RECOMPUTE_HINT = "`heartctl status --verify` lists the damaged cases, `heartctl generate --retry-damaged` recomputes them"


def _chunk_damage(group, k: int) -> tuple[tuple | None, str | None]:
    """((unloaded, loaded), None) of case k from a shape's group, or (None, the damage in words) when a
    chunk does not read back (checksum mismatch, or it does not decompress) or reads back absent or
    not finite."""
    try:
        pair = group["unloaded"][k], group["loaded"][k]
    except (TypeError, AttributeError, NameError):
        raise
    except Exception as exc:
        return None, _damage(exc)
    why = missing_or_not_finite(*pair)
    return (None, why) if why else (pair, None)


def missing_or_not_finite(unloaded: np.ndarray, loaded: np.ndarray) -> str | None:
    """Why a done case's geometries are not data, or None: a chunk that is absent reads as the fill
    value (NaN everywhere), one with a NaN or an infinity was never written by the driver."""
    for name, x in (("unloaded", unloaded), ("loaded", loaded)):
        if np.isnan(x).all():
            return f"its {name} data are missing (no stored chunk)"
        if not np.isfinite(x).all():
            return f"its {name} data are not finite"
    return None


def cases_per_object(array) -> int:
    """Cases one stored object of a case array holds: a shard's (version 2) or a chunk's (1)."""
    return int((array.shards or array.chunks)[0])


def read_cases(group, ks) -> tuple[dict, dict]:
    """({k: (unloaded, loaded)}, {k: the damage in words}) of cases ks of a shape's group, read one
    stored object at a time (a shape's shard in one read, a version 1 store's chunk per case). An object
    that does not read whole is read case by case, so that each damaged case is named alone; a case
    whose data read back absent or not finite is damaged too."""
    unloaded, loaded = group["unloaded"], group["loaded"]
    per_object = cases_per_object(unloaded)
    arrays, damage = {}, {}
    ks = sorted(int(k) for k in ks)
    for _, members in itertools.groupby(ks, key=lambda k: k // per_object):
        members = list(members)
        lo, hi = members[0], members[-1] + 1
        try:
            u, l = unloaded[lo:hi], loaded[lo:hi]
        except (TypeError, AttributeError, NameError):
            raise
        except Exception:
            for k in members:
                pair, why = _chunk_damage(group, k)
                if why is None:
                    arrays[k] = pair
                else:
                    damage[k] = why
            continue
        for k in members:
            why = missing_or_not_finite(u[k - lo], l[k - lo])
            if why is None:
                arrays[k] = (u[k - lo], l[k - lo])
            else:
                damage[k] = why
    return arrays, damage


def _damaged_error(location: str, shape_id: int, k: int, damage: str) -> StoreError:
    where = f"store {location}: " if location else ""
    return StoreError(f"{where}shape {shape_id} case {k} is damaged: {damage}; {RECOMPUTE_HINT}")


def read_case_chunks(group, shape_id: int, k: int, location: str = "") -> tuple[np.ndarray, np.ndarray]:
    """(unloaded, loaded) of case k from a shape's group; StoreError naming the store and the case
    when a chunk is damaged."""
    arrays, damage = _chunk_damage(group, k)
    if damage is not None:
        raise _damaged_error(location, shape_id, k, damage)
    return arrays


def shape_damage(group, root_attrs: dict) -> list[tuple[int | None, str]]:
    """(case, the damage in words) of a shape read whole: (None, …) when its arrays are not what the
    schema implies (every case of it is then damaged), else each status code out of range and each
    done case whose chunks do not read back intact."""
    problem = shape_problem(group, root_attrs, read=True)
    if problem is not None:
        return [(None, problem)]
    status = group["status"][...]
    _, damage = read_cases(group, np.flatnonzero(status == DONE))
    return sorted(status_damage(status) + list(damage.items()), key=lambda d: d[0])


def status_damage(status: np.ndarray) -> list[tuple[int, str]]:
    """(case, reason) of every status code that is none of pending, done or failed."""
    return [(int(k), f"its status code {int(status[k])} is none of "
                     + ", ".join(f"{code} {name}" for code, name in STATUS_NAMES.items()))
            for k in np.flatnonzero(~np.isin(status, list(STATUS_NAMES)))]


# --------------------------------------------------------------------------- a shape's arrays, as the schema says

CODEC_NAMES = ("bytes", "blosc", "crc32c")  # every chunk: _codecs() after zarr's bytes codec
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
        return None, f"its array {name!r} does not open ({_first_line(exc)[:100]})"


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
            return f"its array {name!r} is damaged: {_damage(exc)}"
    if not np.isfinite(values["ed_reference"]).all():
        return "its mesh's node coordinates are not finite"
    for name in ("tets", "endo", "epi", "base"):
        if values[name].size and (values[name].min() < 0 or values[name].max() >= n_nodes):
            return f"its array {name!r} indexes nodes outside 0–{n_nodes - 1}"
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
            if not _is_checksum_error(exc):
                raise
    for run in runs:
        array[ks[run[0]]:ks[run[-1]] + 1] = block[run[0]:run[-1] + 1]


def _codecs() -> tuple:
    """Every chunk is compressed, then carries a CRC-32C of its bytes, checked on every read: a damaged
    chunk fails to read (one line, by reading_store) instead of returning wrong geometry."""
    from zarr.codecs import BloscCodec, Crc32cCodec

    return BloscCodec(cname="zstd", clevel=5, shuffle="shuffle"), Crc32cCodec()


def remove_partial_files(location) -> int:
    """Delete temporary `*.partial` files a killed writer left behind (local stores only)."""
    if is_url(location):
        return 0
    removed = 0
    for p in _local_path(location).rglob("*.partial"):
        try:
            p.unlink()
            removed += 1
        except OSError:
            pass
    return removed


# --------------------------------------------------------------------------- validation


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
        if not is_url(location) and not _local_path(location).parent.exists():
            raise StoreError(f"folder {_local_path(location).parent} does not exist")
        # "w-" refuses a folder with anything in it; the writer lock's file (the driver creating the
        # store holds it, storage.lock) is the one thing allowed there, once inspect_store found no store
        only_lock = not is_url(location) and _local_path(location).is_dir() and inspect_store(location) is None
        root = _open_group(location, "a" if only_lock else "w-", storage_options)
        root.attrs.update(_jsonable(base))
        root.create_group("shapes")
        return cls(root, location)

    @classmethod
    def open(cls, location, storage_options: dict | None = None) -> "PairStore":
        if inspect_store(location, storage_options) is None:
            raise StoreError(f"no heartctl store at {location}")
        remove_partial_files(location)
        return cls(_open_group(location, "r+", storage_options), location)

    def update_attrs(self, **values) -> None:
        self.root.attrs.update(_jsonable(values))
        self.attrs.update(_jsonable(values))

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
        runs.append(_jsonable({"started_at": time.time(), "started": _now_iso(), **info}))
        self.update_attrs(runs=runs)
        return len(runs) - 1

    def end_run(self, index: int, info: dict) -> None:
        runs = list(self.attrs.get("runs", []))
        runs[index] = {**runs[index], **_jsonable({"ended_at": time.time(), **info})}
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
        comp = _codecs()
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
        g.attrs.update(_jsonable({"shape_id": shape_id, "n_nodes": n, "n_tets": int(np.asarray(tets).shape[0]),
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
        self._handle(shape_id)["group"].attrs.update(_jsonable(values))

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
            if not (self.sharded and _is_checksum_error(exc)):
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


# --------------------------------------------------------------------------- readers


@dataclass
class Case:
    shape_id: int
    index: int  # k, the case's row in the shape's table
    params: dict  # pressure_mmhg, stiffness_pa, helix_endo_deg, helix_epi_deg
    unloaded: np.ndarray  # [n,3] mm (float32 as stored)
    loaded: np.ndarray  # [n,3] mm
    ed_reference: np.ndarray  # [n,3] mm
    tets: np.ndarray  # [m,4]
    stats: dict


class PairReader:
    """Read access for training and evaluation: only `done` cases are visible."""

    def __init__(self, location, storage_options: dict | None = None):
        if inspect_store(location, storage_options) is None:
            raise StoreError(f"no heartctl store at {location}")
        self.location = str(location)
        self.root = _open_group(location, "r", storage_options)
        self.attrs = dict(self.root.attrs)
        self.stat_names = tuple(self.attrs["stat_names"])
        self.n_cases = int(self.attrs["n_cases_per_shape"])
        self._cache: dict[int, dict] = {}
        self._groups: dict = {}

    def shape_ids(self) -> list[int]:
        """Shapes whose mesh and case arrays exist (ready), sorted."""
        shapes = self.root["shapes"]
        ids = []
        for key in shapes.group_keys():
            if shapes[key].attrs.get("ready", False):
                ids.append(int(key))
        return sorted(ids)

    def _group(self, shape_id: int):
        """The group of a ready shape, unchecked; StoreError for one the store has not meshed."""
        shapes = self.root["shapes"]
        key = str(shape_id)
        if key not in shapes or not shapes[key].attrs.get("ready", False):
            raise StoreError(f"shape {shape_id} is not meshed in this store (shapes with data: "
                             f"{_id_ranges(self.shape_ids())})")
        return shapes[key]

    def _shape(self, shape_id: int):
        """The group of a ready shape (looked up and checked once); StoreError for one the store has
        not meshed, or whose arrays are not what the schema implies (shape_problem)."""
        if shape_id not in self._groups:
            group = self._group(shape_id)
            problem = shape_problem(group, self.attrs)
            if problem is not None:
                raise StoreError(f"store {self.location}: shape {shape_id} is damaged: {problem}; {RECOMPUTE_HINT}")
            self._groups[shape_id] = group
        return self._groups[shape_id]

    def table_damage(self, shape_id: int) -> list[tuple[int | None, str]]:
        """The damage that shows without reading any case: (None, …) when the shape's arrays are not
        what the schema implies or its status array does not read, else its status codes out of range."""
        group = self._group(shape_id)
        problem = shape_problem(group, self.attrs)
        if problem is not None:
            return [(None, problem)]
        try:
            return status_damage(group["status"][...])
        except (TypeError, AttributeError, NameError):
            raise
        except Exception as exc:
            return [(None, f"its array 'status' is damaged: {_damage(exc)}")]

    def shape_problem(self, shape_id: int) -> str | None:
        """Why a ready shape's arrays are not what the schema implies, or None (module shape_problem)."""
        return shape_problem(self._group(shape_id), self.attrs)

    def status_codes(self, shape_id: int) -> np.ndarray:
        """The shape's status array as stored, codes out of range included."""
        return self._shape(shape_id)["status"][...]

    def _static(self, shape_id: int) -> dict:
        if shape_id not in self._cache:
            g = self._shape(shape_id)
            self._cache[shape_id] = {name: g[name][...] for name in
                                     ("ed_reference", "tets", "endo", "epi", "base", "params", "coefficients")}
        return self._cache[shape_id]

    def mesh(self, shape_id: int):
        """The shape's ED mesh as a solver TetMesh (mm)."""
        from solver.mesh import TetMesh

        s = self._static(shape_id)
        return TetMesh(s["ed_reference"].astype(float), s["tets"].astype(np.int64), s["endo"].astype(np.int64),
                       s["epi"].astype(np.int64), s["base"].astype(np.int64),
                       {"shape_id": shape_id, "coefficients": s["coefficients"].tolist()})

    def status(self, shape_id: int) -> np.ndarray:
        """The shape's status codes; StoreError naming the first that is out of range."""
        status = self.status_codes(shape_id)
        for k, why in status_damage(status)[:1]:
            raise _damaged_error(self.location, shape_id, k, why)
        return status

    def case_params(self, shape_id: int) -> np.ndarray:
        """[n_cases, 4] the shape's case parameters (PARAM_NAMES order), done or not; no mesh is read."""
        return self._shape(shape_id)["params"][...]

    def stats(self, shape_id: int) -> np.ndarray:
        return self._shape(shape_id)["stats"][...]

    def done_cases(self, shape_ids=None) -> list[tuple[int, int]]:
        out = []
        for s in (self.shape_ids() if shape_ids is None else shape_ids):
            out.extend((s, int(k)) for k in np.flatnonzero(self.status(s) == DONE))
        return out

    def case(self, shape_id: int, k: int, _status=None, _stats=None) -> Case:
        status = self.status(shape_id) if _status is None else _status
        if not 0 <= k < self.n_cases:
            raise StoreError(f"case {k} out of range 0..{self.n_cases - 1}")
        if status[k] != DONE:
            raise StoreError(f"case {k} of shape {shape_id} is {STATUS_NAMES.get(int(status[k]))}, not done")
        unloaded, loaded = read_case_chunks(self._shape(shape_id), shape_id, k, self.location)
        return self._case(shape_id, k, unloaded, loaded, self.stats(shape_id) if _stats is None else _stats)

    def _case(self, shape_id: int, k: int, unloaded, loaded, stats: np.ndarray) -> Case:
        why = missing_or_not_finite(unloaded, loaded)
        if why is not None:
            raise _damaged_error(self.location, shape_id, k, why)
        s = self._static(shape_id)
        return Case(shape_id, int(k), dict(zip(PARAM_NAMES, map(float, s["params"][k]))), unloaded, loaded,
                    s["ed_reference"], s["tets"], dict(zip(self.stat_names, map(float, stats[k]))))

    def damaged(self, shape_ids=None) -> list[tuple[int, int | None, str]]:
        """(shape, case, reason) of all damage (shape_damage; reads every done case): case None when a
        shape's arrays are not what the schema implies."""
        return [(s, k, why) for s in (self.shape_ids() if shape_ids is None else shape_ids)
                for k, why in shape_damage(self._group(s), self.attrs)]

    def iter_done(self, shape_ids=None):
        """Every done case, shape by shape, each shape's cases read one stored object at a time
        (read_cases: a shard in one read); StoreError at the first damaged case."""
        for s in (self.shape_ids() if shape_ids is None else shape_ids):
            status, stats = self.status(s), self.stats(s)
            ks = np.flatnonzero(status == DONE)
            arrays, damage = read_cases(self._shape(s), ks)
            for k in map(int, ks):
                if k in damage:
                    raise _damaged_error(self.location, s, k, damage[k])
                yield self._case(s, k, *arrays[k], stats)


def read_done_cases(location, shape_ids=None, storage_options: dict | None = None):
    """Every done case of the store (optionally of some shapes), as Case records."""
    yield from PairReader(location, storage_options).iter_done(shape_ids)


# --------------------------------------------------------------------------- export (ParaView)


def case_to_meshio(reader: PairReader, shape_id: int, k: int, geometry: str = "unloaded"):
    """A meshio mesh of a done case: points = the unloaded (or loaded) geometry; point data
    `displacement` = loaded − unloaded (mm), `ed_reference`; tets + tagged surface triangles."""
    import meshio

    from .meshfiles import SURFACE_CODES, TAG_NAME

    case = reader.case(shape_id, k)
    s = reader._static(shape_id)
    if geometry not in ("unloaded", "loaded"):
        raise ValueError("geometry must be 'unloaded' or 'loaded'")
    points = (case.unloaded if geometry == "unloaded" else case.loaded).astype(np.float64)
    tris = np.vstack([s["endo"], s["epi"], s["base"]])
    codes = np.concatenate([np.full(len(s[n]), SURFACE_CODES[n], np.int32) for n in ("endo", "epi", "base")])
    mesh = meshio.Mesh(points, [("tetra", s["tets"].astype(np.int64)), ("triangle", tris.astype(np.int64))],
                       point_data={"displacement": (case.loaded - case.unloaded).astype(np.float64),
                                   "ed_reference": case.ed_reference.astype(np.float64)},
                       cell_data={TAG_NAME: [np.zeros(len(s["tets"]), np.int32), codes]})
    mesh.field_data = {}
    return mesh


def _id_ranges(ids: list) -> str:
    """[0, 1, 2, 5, 7, 8] → "0–2, 5, 7–8" ("none" when empty)."""
    runs, start = [], None
    for i, v in enumerate(ids):
        if start is None:
            start = v
        if i + 1 == len(ids) or ids[i + 1] != v + 1:
            runs.append(f"{start}" if start == v else f"{start}–{v}")
            start = None
    return ", ".join(runs) or "none"


def export_case(location, shape_id: int, k: int, out, geometry: str = "unloaded") -> dict:
    """Write a done case as a mesh file (VTU etc.), atomically. Returns the case parameters."""
    import meshio

    from .meshfiles import _format_of, atomic_write

    if geometry not in ("unloaded", "loaded"):
        raise ValueError("geometry must be 'unloaded' or 'loaded'")
    with reading_store(location):
        reader = PairReader(location)
        mesh = case_to_meshio(reader, shape_id, k, geometry)
        params = dict(zip(PARAM_NAMES, map(float, reader.case_params(shape_id)[k])))
    out = Path(out)
    atomic_write(out, lambda tmp: meshio.write(tmp, mesh, file_format=_format_of(out)))
    return params


# --------------------------------------------------------------------------- summary (heartctl status)


def _reason_pattern(reason: str) -> str:
    return re.sub(r"[-+]?\d+(\.\d+)?([eE][-+]?\d+)?", "#", reason).strip()


def _percentiles(values: np.ndarray) -> dict | None:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return None
    p = np.percentile(values, [50, 90, 99])
    return {"p50": float(p[0]), "p90": float(p[1]), "p99": float(p[2]), "max": float(values.max()),
            "mean": float(values.mean())}


def summarize(location, storage_options: dict | None = None) -> dict:
    """Counts by status, failure reasons grouped, throughput of the latest run, per-phase time
    percentiles (s) and an ETA. A case whose status cannot be known (its shape's arrays are not what
    the schema implies, or its status code is out of range) counts as "unknown", and is named in
    "table_damage" ({"shape", "case" (None: every case of the shape), "reason"})."""
    reader = PairReader(location, storage_options)
    attrs = reader.attrs
    grid = attrs["grid"]
    n_shapes = int(grid["shapes"])
    K = reader.n_cases
    names = reader.stat_names
    col = {n: i for i, n in enumerate(names)}
    ready = set(reader.shape_ids())
    counts = {"done": 0, "failed": 0, "pending": 0, "unknown": 0}
    groups: dict[str, dict] = {}
    hosts: dict[str, int] = {}
    all_stats = []
    table_damage = []  # {"shape", "case" (None: every case), "reason"}: status unknown
    for s in range(n_shapes):
        if s not in ready:
            counts["pending"] += K
            continue
        damage = reader.table_damage(s)
        table_damage.extend({"shape": s, "case": k, "reason": why} for k, why in damage)
        if damage and damage[0][0] is None:
            counts["unknown"] += K
            continue
        status = reader.status_codes(s)
        counts["unknown"] += len(damage)
        stats = reader.stats(s)
        g = reader._shape(s)
        failures = g.attrs.get("failures", {})
        counts["done"] += int((status == DONE).sum())
        counts["failed"] += int((status == FAILED).sum())
        counts["pending"] += int((status == PENDING).sum())
        for k in np.flatnonzero(status == FAILED):
            reason = failures.get(str(k), "unknown")
            pat = _reason_pattern(reason)
            entry = groups.setdefault(pat, {"reason": pat, "count": 0, "example": reason, "cases": []})
            entry["count"] += 1
            if len(entry["cases"]) < 5:
                entry["cases"].append([s, int(k)])
        for k, host in g.attrs.get("hosts", {}).items():
            if status[int(k)] == DONE:
                hosts[host] = hosts.get(host, 0) + 1
        all_stats.append(stats[status == DONE])
    done_stats = np.vstack(all_stats) if all_stats else np.zeros((0, len(names)))
    phases = {
        "inverse_s": done_stats[:, col["inverse_wall_s"]],
        "forward_s": done_stats[:, col["forward_wall_s"]],
        "task_solve_s": done_stats[:, col["task_wall_s"]],
        "queue_s": done_stats[:, col["started_at"]] - done_stats[:, col["submitted_at"]],
        "result_to_stored_s": done_stats[:, col["stored_at"]] - done_stats[:, col["finished_at"]],
    }
    runs = attrs.get("runs", [])
    throughput = None
    last_run = None
    if runs:
        idx = len(runs) - 1
        last = runs[idx]
        in_run = done_stats[done_stats[:, col["run"]] == idx]
        if len(in_run):
            span = float(np.nanmax(in_run[:, col["stored_at"]]) - last["started_at"])
            if span > 0:
                throughput = len(in_run) / span
        last_run = {"index": idx, "started": last.get("started"), "host": last.get("host"),
                    "ended": last.get("ended_at") is not None, "done_in_run": int(len(in_run)),
                    "cpus": last.get("cpus")}
    total = n_shapes * K
    eta = counts["pending"] / throughput if throughput and counts["pending"] else (0.0 if not counts["pending"] else None)
    mesh_failures = attrs.get("mesh_failures", {})
    return {
        **counts,
        "table_damage": table_damage,
        "total": total,
        "shapes": n_shapes,
        "shapes_ready": len(ready),
        "cases_per_shape": K,
        "fidelity": attrs.get("fidelity"),
        "seed": attrs.get("seed"),
        "mesh_nodes": attrs.get("mesh_nodes"),
        "grid": grid,
        "failure_reasons": sorted(groups.values(), key=lambda e: -e["count"]),
        "mesh_failures": mesh_failures,
        "throughput_cases_per_s": throughput,
        "throughput_cases_per_h": throughput * 3600 if throughput else None,
        "eta_s": eta,
        "phase_percentiles_s": {k: _percentiles(v) for k, v in phases.items()},
        "hosts": hosts,
        "runs": len(runs),
        "last_run": last_run,
        "writer": _writer(location),  # the driver writing it now ({host, pid, since}), or None
        "store_bytes": store_bytes(location),
    }


def _writer(location) -> dict | None:
    from .lock import holder  # storage.lock builds on this module

    return holder(location)


def store_bytes(location) -> int | None:
    if is_url(location):
        return None
    total = 0
    for root, _, files in os.walk(_local_path(location)):
        for f in files:
            try:
                total += os.path.getsize(os.path.join(root, f))
            except OSError:
                pass
    return total


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
                           compressors=_codecs())
        a[0] = np.asarray(x, dtype=COORD_DTYPE)
    chunks = sum(len(v.to_bytes()) for k, v in store._store_dict.items() if "/c/" in k)
    return chunks + 2 * SHARD_INDEX_BYTES_PER_CASE


def attrs_json(attrs: dict) -> str:
    return json.dumps(_jsonable(attrs), sort_keys=True)
