"""A store's progress as `heartctl status` reports it: counts by status, failure reasons, throughput
and ETA (summarize), and on request every damaged case: a shape whose arrays are not what the schema
implies, a status code out of range, a done case whose data are missing, short, unreadable or not
finite (store_status)."""
from __future__ import annotations

import os
import re
from dataclasses import asdict, dataclass

import numpy as np

from .location import StoreError, is_url, local_path, reading_store
from .lock import holder
from .reader import PairReader
from .schema import DONE, FAILED, CaseCounts, inspect_store


def _reason_pattern(reason: str) -> str:
    return re.sub(r"[-+]?\d+(\.\d+)?([eE][-+]?\d+)?", "#", reason).strip()


def _percentiles(values: np.ndarray) -> dict | None:
    values = values[np.isfinite(values)]
    if values.size == 0:
        return None
    p = np.percentile(values, [50, 90, 99])
    return {"p50": float(p[0]), "p90": float(p[1]), "p99": float(p[2]), "max": float(values.max()),
            "mean": float(values.mean())}


@dataclass
class StoreSummary:
    """A store's progress (summarize). Counts are cases; a case whose status cannot be known (its
    shape's arrays are not what the schema implies, or its status code is out of range) counts as
    `unknown` and is named in `table_damage` ({"shape", "case" (None: every case of the shape),
    "reason"}). Times in s; `writer`: the driver writing the store now ({host, pid, since}) or None;
    `damaged`: every damaged case, when the done cases were read back (store_status with verify)."""

    done: int
    failed: int
    pending: int
    unknown: int
    table_damage: list
    total: int
    shapes: int
    shapes_ready: int
    cases_per_shape: int
    fidelity: str | None
    seed: int | None
    mesh_nodes: int | None
    grid: dict
    failure_reasons: list  # {"reason" (numbers as #), "count", "example", "cases"}, most frequent first
    mesh_failures: dict
    throughput_cases_per_s: float | None
    throughput_cases_per_h: float | None
    eta_s: float | None
    phase_percentiles_s: dict
    hosts: dict
    runs: int
    last_run: dict | None
    writer: dict | None
    store_bytes: int | None
    damaged: list | None = None

    def as_dict(self) -> dict:
        """The summary as a JSON object (`damaged` only when the cases were read back)."""
        d = asdict(self)
        if self.damaged is None:
            del d["damaged"]
        return d


def summarize(location, storage_options: dict | None = None) -> StoreSummary:
    """Counts by status, failure reasons grouped, throughput of the latest run, per-phase time
    percentiles (s) and an ETA (StoreSummary)."""
    reader = PairReader(location, storage_options)
    attrs, n_shapes = reader.attrs, int(reader.attrs["grid"]["shapes"])
    counts = CaseCounts()
    failures: dict[str, dict] = {}
    hosts: dict[str, int] = {}
    done_stats = [np.zeros((0, len(reader.stat_names)))]
    table_damage = []  # {"shape", "case" (None: every case), "reason"}: status unknown
    ready = set(reader.shape_ids())
    for s in range(n_shapes):
        damage = reader.table_damage(s) if s in ready else []
        table_damage.extend({"shape": s, "case": k, "reason": why} for k, why in damage)
        counts += reader.shape_counts(s, damage)
        if s not in ready or (damage and damage[0][0] is None):
            continue
        status, group = reader.status_codes(s), reader._shape(s)
        _group_failures(failures, s, status, group.attrs.get("failures", {}))
        for k, host in group.attrs.get("hosts", {}).items():
            if status[int(k)] == DONE:
                hosts[host] = hosts.get(host, 0) + 1
        done_stats.append(reader.stats(s)[status == DONE])
    done_stats = np.vstack(done_stats)
    col = {n: i for i, n in enumerate(reader.stat_names)}
    runs = attrs.get("runs", [])
    throughput, last_run = _last_run(runs, done_stats, col)
    pending = counts.pending
    return StoreSummary(
        done=counts.done, failed=counts.failed, pending=pending, unknown=counts.unknown, table_damage=table_damage,
        total=n_shapes * reader.n_cases, shapes=n_shapes, shapes_ready=len(ready), cases_per_shape=reader.n_cases,
        fidelity=attrs.get("fidelity"), seed=attrs.get("seed"), mesh_nodes=attrs.get("mesh_nodes"), grid=attrs["grid"],
        failure_reasons=sorted(failures.values(), key=lambda e: -e["count"]),
        mesh_failures=attrs.get("mesh_failures", {}), throughput_cases_per_s=throughput,
        throughput_cases_per_h=throughput * 3600 if throughput else None,
        eta_s=pending / throughput if throughput and pending else (0.0 if not pending else None),
        phase_percentiles_s={k: _percentiles(v) for k, v in _phase_times(done_stats, col).items()},
        hosts=hosts, runs=len(runs), last_run=last_run, writer=holder(location), store_bytes=store_bytes(location))


def _group_failures(groups: dict, shape_id: int, status: np.ndarray, reasons: dict) -> None:
    """Add a shape's failed cases to `groups`, keyed by their reason with the numbers taken out."""
    for k in np.flatnonzero(status == FAILED):
        reason = reasons.get(str(k), "unknown")
        pattern = _reason_pattern(reason)
        entry = groups.setdefault(pattern, {"reason": pattern, "count": 0, "example": reason, "cases": []})
        entry["count"] += 1
        if len(entry["cases"]) < 5:
            entry["cases"].append([shape_id, int(k)])


def _phase_times(done_stats: np.ndarray, col: dict) -> dict:
    """Seconds each done case spent in each phase, from its stats row."""
    return {
        "inverse_s": done_stats[:, col["inverse_wall_s"]],
        "forward_s": done_stats[:, col["forward_wall_s"]],
        "task_solve_s": done_stats[:, col["task_wall_s"]],
        "queue_s": done_stats[:, col["started_at"]] - done_stats[:, col["submitted_at"]],
        "result_to_stored_s": done_stats[:, col["stored_at"]] - done_stats[:, col["finished_at"]],
    }


def _last_run(runs: list, done_stats: np.ndarray, col: dict) -> tuple[float | None, dict | None]:
    """(cases stored per second by the latest run, what the latest run is), or (None, None) before
    the first run."""
    if not runs:
        return None, None
    index, last = len(runs) - 1, runs[-1]
    in_run = done_stats[done_stats[:, col["run"]] == index]
    throughput = None
    if len(in_run):
        span = float(np.nanmax(in_run[:, col["stored_at"]]) - last["started_at"])
        throughput = len(in_run) / span if span > 0 else None
    return throughput, {"index": index, "started": last.get("started"), "host": last.get("host"),
                        "ended": last.get("ended_at") is not None, "done_in_run": int(len(in_run)),
                        "cpus": last.get("cpus")}


def store_bytes(location) -> int | None:
    if is_url(location):
        return None
    total = 0
    for root, _, files in os.walk(local_path(location)):
        for f in files:
            try:
                total += os.path.getsize(os.path.join(root, f))
            except OSError:
                pass
    return total


def store_status(location: str, verify: bool = False) -> StoreSummary:
    """summarize(location), with `damaged` ({"shape", "case", "reason"} per damaged case, case None
    for every case of a shape; PairReader.damaged) when `verify`, which reads every done case.
    StoreError (one line) when there is no heartctl store at `location` or it cannot be read."""
    with reading_store(location):
        if inspect_store(location) is None:
            raise StoreError(f"no heartctl store at {location}")
        status = summarize(location)
        if verify:
            status.damaged = [{"shape": s, "case": k, "reason": r} for s, k, r in PairReader(location).damaged()]
    return status
