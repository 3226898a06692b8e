"""Read access to a store: only done cases are visible, each read back through its checksum, and a
damaged case is named alone (its shape, its case, what is wrong, and how to recompute it).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from .location import StoreError, open_group, read_error_words
from .schema import DONE, PARAM_NAMES, STATUS_NAMES, CaseCounts, inspect_store, shape_problem


RECOMPUTE_HINT = "reading the store with `verify` lists the damaged cases, generating with `retry_damaged` recomputes them"


def chunk_damage(group, k: int) -> tuple[tuple | None, str | None]:
    """((unloaded, loaded), None) of case k from a shape's group, or (None, the damage in words) when a
    chunk does not read back (checksum mismatch, or it does not decompress) or reads back absent or
    not finite."""
    try:
        pair = group["unloaded"][k], group["loaded"][k]
    except (TypeError, AttributeError, NameError):
        raise
    except Exception as exc:
        return None, read_error_words(exc)
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
                pair, why = chunk_damage(group, k)
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


def damaged_error(location: str, shape_id: int, k: int, damage: str) -> StoreError:
    where = f"store {location}: " if location else ""
    return StoreError(f"{where}shape {shape_id} case {k} is damaged: {damage}; {RECOMPUTE_HINT}")


def read_case_chunks(group, shape_id: int, k: int, location: str = "") -> tuple[np.ndarray, np.ndarray]:
    """(unloaded, loaded) of case k from a shape's group; StoreError naming the store and the case
    when a chunk is damaged."""
    arrays, damage = chunk_damage(group, k)
    if damage is not None:
        raise damaged_error(location, shape_id, k, damage)
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


def id_ranges(ids: list) -> str:
    """[0, 1, 2, 5, 7, 8] → "0–2, 5, 7–8" ("none" when empty)."""
    runs, start = [], None
    for i, v in enumerate(ids):
        if start is None:
            start = v
        if i + 1 == len(ids) or ids[i + 1] != v + 1:
            runs.append(f"{start}" if start == v else f"{start}–{v}")
            start = None
    return ", ".join(runs) or "none"


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
        self.root = open_group(location, "r", storage_options)
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

    def _ready_group(self, shape_id: int):
        """The group of a ready shape, unchecked, or None when the store has not meshed it."""
        shapes = self.root["shapes"]
        key = str(shape_id)
        return shapes[key] if key in shapes and shapes[key].attrs.get("ready", False) else None

    def _group(self, shape_id: int):
        """The group of a ready shape, unchecked; StoreError for one the store has not meshed."""
        group = self._ready_group(shape_id)
        if group is None:
            raise StoreError(f"shape {shape_id} is not meshed in this store (shapes with data: "
                             f"{id_ranges(self.shape_ids())})")
        return group

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
            return [(None, f"its array 'status' is damaged: {read_error_words(exc)}")]

    def shape_problem(self, shape_id: int) -> str | None:
        """Why a ready shape's arrays are not what the schema implies, or None (module shape_problem)."""
        return shape_problem(self._group(shape_id), self.attrs)

    def status_codes(self, shape_id: int) -> np.ndarray:
        """The shape's status array as stored, codes out of range included."""
        return self._shape(shape_id)["status"][...]

    def shape_counts(self, shape_id: int, damage: list | None = None) -> CaseCounts:
        """The cases of one shape by status (CaseCounts): all pending when it is not meshed, all
        unknown when its arrays are not what the schema implies. `damage`: its table_damage, when
        known already."""
        if self._ready_group(shape_id) is None:  # not meshed
            return CaseCounts(pending=self.n_cases)
        damage = self.table_damage(shape_id) if damage is None else damage
        if damage and damage[0][0] is None:
            return CaseCounts(unknown=self.n_cases, meshed=1)
        return CaseCounts.of_status(self.status_codes(shape_id))

    def counts(self, shapes: int | None = None) -> CaseCounts:
        """The cases of shapes 0 … shapes − 1 by status (default: the store's shape count), read from
        their status arrays alone."""
        shapes = int(self.attrs["grid"]["shapes"]) if shapes is None else shapes
        return sum((self.shape_counts(s) for s in range(shapes)), CaseCounts())

    def shape_arrays(self, shape_id: int) -> dict:
        if shape_id not in self._cache:
            g = self._shape(shape_id)
            self._cache[shape_id] = {name: g[name][...] for name in
                                     ("ed_reference", "tets", "endo", "epi", "base", "params", "coefficients")}
        return self._cache[shape_id]

    def mesh(self, shape_id: int):
        """The shape's ED mesh as a solver TetMesh (mm)."""
        from solver.mesh import TetMesh

        s = self.shape_arrays(shape_id)
        return TetMesh(s["ed_reference"].astype(float), s["tets"].astype(np.int64), s["endo"].astype(np.int64),
                       s["epi"].astype(np.int64), s["base"].astype(np.int64),
                       {"shape_id": shape_id, "coefficients": s["coefficients"].tolist()})

    def status(self, shape_id: int) -> np.ndarray:
        """The shape's status codes; StoreError naming the first that is out of range."""
        status = self.status_codes(shape_id)
        for k, why in status_damage(status)[:1]:
            raise damaged_error(self.location, shape_id, k, why)
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
            raise damaged_error(self.location, shape_id, k, why)
        s = self.shape_arrays(shape_id)
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
                    raise damaged_error(self.location, s, k, damage[k])
                yield self._case(s, k, *arrays[k], stats)


def read_done_cases(location, shape_ids=None, storage_options: dict | None = None):
    """Every done case of the store (optionally of some shapes), as Case records."""
    yield from PairReader(location, storage_options).iter_done(shape_ids)
