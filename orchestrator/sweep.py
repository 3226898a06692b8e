"""The sweep driver: phase 1 meshes the shapes (Ray tasks) and writes them with every case array;
phase 2 runs the pairs as Ray tasks, one pressure chain per task (bounded in flight with `ray.wait`);
tasks return arrays and the driver — the store's only writer — validates, writes and marks each case.
In a sharded store the driver holds a shape's returned cases and writes them together (HeldResults),
so that a shape's shard is rewritten a few times, not once per chain.

Failures: a lost worker or node is retried by Ray (`max_retries`), after which the task's cases stay
pending for the next run (failed once that has happened to a case in MAX_LOSSES runs); a solver failure (or any exception a case's solve raises) is retried once
inside the task with a more robust setting, then recorded as failed with its reason. The
sweep never stops for one case. Resume: cases already done (or failed, unless retry_failed) are
never resubmitted. A resume with more shapes than the store's grows it: the count is raised in the
store's attributes, and the added shapes are meshed and solved like any pending shape.
"""
from __future__ import annotations

import os
import socket
import sys
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from storage.disk import is_disk_full
from storage.lock import LOCK_NAME, WriterLock, check_free
from storage.store import DONE, FAILED, PENDING, PairStore, inspect_store, object_store_problem, stats_row

from .grid import MAX_CHAIN, SweepSpec, pressure_chains

TASK_MAX_RETRIES = 3  # worker process crash / node loss
FLUSH_INTERVAL_S = 2.0
WRITE_HOLD_S = 30.0  # the longest a returned case waits to be written into its shape's shard


class SweepConflict(ValueError):
    """The request conflicts with the store it would resume."""


class StoreFullError(RuntimeError):
    """The store's disk (or quota) filled up during a sweep. Cases marked done before are intact (a
    case is marked only after its chunks were written and read back; local writes are atomic), so
    rerunning the same command after freeing space resumes. The message is one line."""

    def __init__(self, location: str, written: int | None):
        self.location, self.written = location, written
        cases = f"the {written} cases written are intact" if written is not None else "the cases marked done are intact"
        super().__init__(f"disk full writing {location}; {cases}, free space and rerun the same command to resume")


class StoreLostError(RuntimeError):
    """The object store (s3://) stopped answering, or refused a write, during a sweep. Cases marked
    done before are intact (a case is marked only after its chunks were written and read back, and
    every object is put whole), so rerunning the same command once the store answers resumes. The
    message is one line, naming the store and what its server said."""

    def __init__(self, location: str, problem: str):
        self.location, self.problem = location, problem
        super().__init__(f"lost the object store while writing {location}: {problem}; the cases marked done are "
                         f"intact, rerun the same command to resume once it answers")


def _cases_on_disk(location: str) -> int | None:
    """Done cases as the store on disk records them (what a rerun finds), or None if it cannot be read."""
    from storage.store import PairReader, remove_partial_files

    try:
        remove_partial_files(location)  # a write cut short leaves its temporary file: give the space back
        return len(PairReader(location).done_cases())
    except Exception:
        return None


@dataclass
class SweepReport:
    total: int
    done_before: int
    failed_before: int
    submitted: int = 0
    done: int = 0
    failed: int = 0
    meshed_shapes: int = 0
    mesh_failures: int = 0
    lost: int = 0  # cases of tasks lost to the infrastructure (worker or node died after retries): left pending
    retried_failed: int = 0  # of failed_before, the cases --retry-failed submitted again
    damaged_reset: list = field(default_factory=list)  # (shape, case) found damaged and recomputed (--retry-damaged)
    phase1_s: float = 0.0
    phase2_s: float = 0.0
    wall_s: float = 0.0
    cpus: float = 0.0  # CPUs that solved this run's cases (cpus_used), else the cluster's
    nodes: int = 0  # nodes whose workers solved this run's cases
    cluster_cpus: float = 0.0  # the most CPUs the cluster had during the run
    run: int = -1
    driver_store_s: float = 0.0  # driver time spent validating + writing results
    records: list = field(default_factory=list, repr=False)  # per finished task: (shape, k, status)
    workers: set = field(default_factory=set, repr=False)  # (node or host, pid) of the workers that solved cases

    @property
    def failed_now(self) -> int:
        """Failed cases in the store after the run: those not retried, and this run's failures."""
        return self.failed_before - self.retried_failed + self.failed

    @property
    def throughput(self) -> float:
        return (self.done + self.failed) / self.phase2_s if self.phase2_s > 0 else float("nan")

    def as_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k not in ("records", "workers")}
        d["throughput_cases_per_s"] = self.throughput
        return d


# --------------------------------------------------------------------------- request checks (no Ray, no writes)


def check_request(spec: SweepSpec, location: str, for_writing: bool = True, retry_damaged: bool = False) -> dict | None:
    """Validate the spec and the store it targets, read-only. Returns the store's attributes
    (None when the store is new). Raises ValueError / StoreError / SweepConflict (one line).
    `for_writing` (not for a dry run) also needs a writable store no other driver is writing.
    Damage that shows without reading the cases (a shape's arrays not what the schema implies, a
    status code out of range) is refused unless `retry_damaged`, which repairs it."""
    spec.validate()
    if for_writing and str(location).startswith("memory://"):
        raise ValueError(f"store {location}: a memory:// store vanishes when generate exits; give a folder or an "
                         f"object-store URL (s3://…)")
    attrs = inspect_store(location)
    if for_writing:
        _check_writable(location)
    if attrs is not None and for_writing:
        check_free(location)  # another driver is writing it
    if attrs is not None:
        conflicts = spec.conflicts(attrs)
        if conflicts:
            raise _conflict(location, conflicts)
        _check_table_damage(location, retry_damaged)
        _check_shape_tables(location, np.asarray(attrs["case_params"], dtype=float))
    return attrs


def _check_table_damage(location: str, retry_damaged: bool) -> None:
    """StoreError naming the first damage of a shape's arrays or status codes, unless retry_damaged."""
    from storage.store import PairReader, StoreError

    if retry_damaged:
        return
    reader = PairReader(location)
    for s in reader.shape_ids():
        for k, why in reader.table_damage(s)[:1]:
            where = f"shape {s}" if k is None else f"shape {s} case {k}"
            raise StoreError(f"store {location}: {where} is damaged: {why}; `heartctl generate --retry-damaged` "
                             f"{'meshes the shape again and recomputes its cases' if k is None else 'recomputes it'}")


def _conflict(location: str, conflicts: list[str]) -> SweepConflict:
    return SweepConflict(f"store {location} was made with another setup: {'; '.join(conflicts)}; "
                         f"use the store's settings to resume, or a new --store")


def _check_shape_tables(location: str, case_params: np.ndarray) -> None:
    """SweepConflict when a shape's own parameter table (what readers label its cases with) differs
    from the store's case_params (what the driver solves): resuming would store mislabelled data."""
    from storage.store import PairReader

    reader = PairReader(location)
    for s in reader.shape_ids():
        if reader.shape_problem(s) is None and not np.array_equal(reader.case_params(s), case_params):
            raise SweepConflict(f"store {location}: shape {s}'s parameter table differs from the store's case_params "
                                f"(edited by hand?); it cannot be resumed")


def _check_writable(location: str) -> None:
    """ValueError when a local store (or the folder it would be made in) cannot be written, found
    before Ray starts; object stores are left to their own permissions."""
    from storage.store import _local_path, is_url

    if is_url(location):
        return
    path = _local_path(location).absolute()
    folder = path if path.is_dir() else path.parent
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"store {location}: {'it' if folder == path else f'the folder {folder}'} is not writable")
    if not path.is_dir():
        return
    # what a resumed run writes: the lock, the root attributes, and the folders of every shape and array
    shapes = path / "shapes"
    parts = [path / LOCK_NAME, path / "zarr.json", shapes, shapes / "zarr.json"]
    if shapes.is_dir():
        parts += [p for shape in shapes.iterdir() if shape.is_dir() for p in (shape, *shape.iterdir())]
    for p in parts:
        if p.exists() and not os.access(p, os.W_OK | (os.X_OK if p.is_dir() else 0)):
            raise ValueError(f"store {location}: {p.relative_to(path)} is not writable by this user")


def remaining_cases(spec: SweepSpec, location: str, retry_failed: bool = False) -> dict:
    """Read-only counts of a store for this spec: done, failed, and to_run (cases a run would submit,
    counting every case of a shape not meshed yet or damaged, and every status code out of range)."""
    from storage.store import PairReader

    counts = {"done": 0, "failed": 0, "to_run": spec.n_cases}
    if inspect_store(location) is None:
        return counts
    reader = PairReader(location)
    ready = set(reader.shape_ids())
    to_run = 0
    for s in range(spec.shapes):
        damage = reader.table_damage(s) if s in ready else [(None, "not meshed")]
        if damage and damage[0][0] is None:
            to_run += spec.cases_per_shape
            continue
        st = reader.status_codes(s)
        to_run += len(damage)
        counts["done"] += int((st == DONE).sum())
        counts["failed"] += int((st == FAILED).sum())
        to_run += int((st == PENDING).sum()) + (int((st == FAILED).sum()) if retry_failed else 0)
    counts["to_run"] = to_run
    return counts


# --------------------------------------------------------------------------- Ray tasks


def _remotes():
    import ray

    from . import tasks

    mesh_remote = ray.remote(num_cpus=1, max_retries=TASK_MAX_RETRIES)(tasks.mesh_shape)
    chain_remote = ray.remote(num_cpus=1, max_retries=TASK_MAX_RETRIES, retry_exceptions=False)(tasks.run_chain)
    return mesh_remote, chain_remote


def solver_version() -> str:
    try:
        from importlib.metadata import version

        v = version("heartctl")
    except Exception:
        v = "unknown"
    from solver.version import solver_digest

    return f"heartctl {v} (solver sha256:{solver_digest()})"


# --------------------------------------------------------------------------- the sweep


def open_or_create(spec: SweepSpec, location: str, retry_damaged: bool = False) -> tuple[PairStore, WriterLock]:
    """The store to write (created when new) and its writer lock, taken before the store is opened
    (opening clears a killed writer's temporary files, which must not be another live driver's)."""
    from storage.store import _local_path, is_url

    attrs = check_request(spec, location, retry_damaged=retry_damaged)
    folder = None if is_url(location) else _local_path(location)
    made = attrs is None and folder is not None and not folder.exists()
    if made:  # the lock lives in the store's folder: two drivers starting a new store meet there
        folder.mkdir(exist_ok=True)
    try:
        lock = WriterLock(location).acquire()
    except BaseException:
        _remove_if_only_lock(folder if made else None)
        raise
    try:
        # a store that looked new may have been made (and finished) by another driver before this one
        # got the lock: check again under it
        if attrs is None and check_request(spec, location, for_writing=False, retry_damaged=retry_damaged) is None:
            return PairStore.create(location, {**spec.store_attrs(), "solver_version": solver_version()}), lock
        store = PairStore.open(location)
        conflicts = spec.conflicts(store.attrs)  # again under the lock: another driver may have grown it since
        if conflicts:
            raise _conflict(location, conflicts)
        return store, lock
    except BaseException:
        lock.release()
        _remove_if_only_lock(folder if made else None)
        raise


def _remove_if_only_lock(folder) -> None:
    """Remove a store folder this driver made when it holds nothing but the writer lock's file."""
    if folder is None or not folder.is_dir() or any(p.name != LOCK_NAME for p in folder.iterdir()):
        return
    (folder / LOCK_NAME).unlink(missing_ok=True)
    try:
        folder.rmdir()
    except OSError:
        pass


def run_sweep(spec: SweepSpec, location: str, *, max_in_flight: int | None = None, retry_failed: bool = False,
              progress: bool = True, on_event=None, console=None, warm_start: bool = True,
              chain_length: int = MAX_CHAIN, retry_damaged: bool = False) -> SweepReport:
    """Run (or resume) the sweep into the store at `location`. Ray must be initialised
    (orchestrator.ray_session). `on_event(dict)` is called after every recorded case (tests use it).

    Each task solves one pressure chain (`grid.pressure_chains`: the cases of a shape that differ only
    in pressure); with `warm_start` each inverse in it starts from the unloaded geometry extrapolated
    from the chain's lower pressures; `chain_length` 1 makes every pair its own task.
    `max_in_flight` counts tasks (default: InFlightLimit, twice the cluster's CPUs as nodes join).
    `retry_damaged`: first read every done case back and mark the damaged ones pending, so that they
    are recomputed (PairStore.reset_damaged: data missing, short, unreadable or not finite, a status
    code out of range; a shape whose arrays are not what the schema implies is meshed again). A full disk (ENOSPC, EDQUOT) while
    writing the store raises StoreFullError, an object store that stops answering or refuses a write
    StoreLostError (one line each; the cases already written are intact)."""
    import ray

    if not ray.is_initialized():
        raise RuntimeError("run_sweep needs Ray: start it with orchestrator.ray_session first")
    t_start = time.perf_counter()
    try:
        store, lock = open_or_create(spec, location, retry_damaged)
        try:
            damaged = store.reset_damaged([s for s in range(spec.shapes) if store.shape_ready(s)]) if retry_damaged else []
            report = _run(spec, store, max_in_flight, retry_failed, progress, on_event, console, warm_start,
                          chain_length, t_start)
            report.damaged_reset = [(s, k) for s, k, _ in damaged]
            return report
        finally:
            lock.release()
    except Exception as exc:
        problem = object_store_problem(location, exc)
        if problem is not None:
            raise StoreLostError(str(location), problem) from None
        if not is_disk_full(exc):
            raise
        raise StoreFullError(str(location), _cases_on_disk(location)) from None


def _run(spec: SweepSpec, store: PairStore, max_in_flight, retry_failed, progress, on_event, console, warm_start,
         chain_length, t_start) -> SweepReport:
    """run_sweep's body, with the store open and its writer lock held."""
    import ray

    cpus = float(ray.cluster_resources().get("CPU", 1.0))
    limit = InFlightLimit(max_in_flight, lambda: float(ray.cluster_resources().get("CPU", 0.0)))
    K = store.n_cases
    counts_before = _count(store, spec.shapes)
    report = SweepReport(total=spec.n_cases, done_before=counts_before[DONE], failed_before=counts_before[FAILED],
                         cpus=cpus)
    grows_from = spec.grows(store.attrs)
    run = store.begin_run({"host": socket.gethostname(), "pid": os.getpid(), "cpus": cpus,
                           "solver_version": solver_version(), "argv": sys.argv[:], "max_in_flight": limit.value,
                           "done_before": report.done_before, "failed_before": report.failed_before,
                           "warm_start": warm_start, "shapes": spec.shapes,
                           **({"shapes_before": grows_from} if grows_from is not None else {})})
    if grows_from is not None:  # the added shapes are pending: phase 1 meshes them, phase 2 solves them
        store.grow_shapes(spec.shapes)
    report.run = run
    mesh_remote, chain_remote = _remotes()
    kept_failed = 0 if retry_failed else report.failed_before
    report.retried_failed = report.failed_before - kept_failed
    bar = _Progress(progress, spec.n_cases, report.done_before + kept_failed, kept_failed, console)
    try:
        with bar:
            # ---- phase 1: meshes
            t1 = time.perf_counter()
            missing = [s for s in range(spec.shapes) if not store.shape_ready(s)]
            bar.phase(f"meshing {len(missing)} shapes" if missing else "meshes ready")
            refs = {mesh_remote.remote(s, spec.seed, spec.nodes, *spec.mesh_source(s),
                                       shape_model_version=spec.shape_model_version): s for s in missing}
            while refs:
                ready, _ = ray.wait(list(refs), num_returns=1)
                s = refs.pop(ready[0])
                try:
                    out = ray.get(ready[0])
                except Exception as exc:  # a shape that will not mesh: its cases stay pending, noted
                    store.record_mesh_failure(s, _error_line(exc))
                    report.mesh_failures += 1
                    continue
                m = out["mesh"]
                store.write_shape(s, m.nodes, m.tets, m.endo, m.epi, m.base, out["coefficients"], out["info"])
                report.meshed_shapes += 1
            report.phase1_s = time.perf_counter() - t1

            # ---- phase 2: pairs
            t2 = time.perf_counter()
            todo = deque()
            mesh_refs = {}
            for s in range(spec.shapes):
                if not store.shape_ready(s):
                    continue
                status = store.status(s)
                wanted = (status == PENDING) | ((status == FAILED) if retry_failed else False)
                ks = np.flatnonzero(wanted)
                todo.extend((s, chain) for chain in pressure_chains(store.params, ks, chain_length))
            n_pairs = sum(len(chain) for _, chain in todo)
            held = HeldResults(store.sharded, lambda s: int((store.table(s).status == DONE).sum()))
            for s, _ in todo:
                held.expect(s)
            bar.phase(f"solving {n_pairs} pairs ({len(todo)} pressure chains) on {cpus:g} CPUs")
            inflight: dict = {}
            while todo or inflight:
                while todo and len(inflight) < limit.current():
                    s, chain = todo.popleft()
                    if s not in mesh_refs:
                        mesh_refs[s] = ray.put(_tet_mesh(store, s))
                    ref = chain_remote.remote(mesh_refs[s], [tuple(store.params[k]) for k in chain], spec.fidelity,
                                              spec.base, fibres=spec.fibres, warm_start=warm_start)
                    inflight[ref] = (s, chain, time.time())
                    report.submitted += len(chain)
                ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)
                for ref in ready:
                    s, chain, submitted_at = inflight.pop(ref)
                    try:
                        results = ray.get(ref)
                    except Exception as exc:
                        results = _failed_task_results(store, s, chain, exc)
                        report.lost += sum(r is None for r in results)
                    for result in results:
                        if result is not None and result.get("pid") is not None:
                            report.workers.add((result.get("node") or result.get("host"), result["pid"]))
                    # a case lost with its worker (None) stays pending for the next run
                    held.add(s, [(k, r, submitted_at) for k, r in zip(chain, results) if r is not None])
                for s in held.due():
                    t_w = time.perf_counter()
                    recorded = _record(store, s, held.take(s), run)
                    report.driver_store_s += time.perf_counter() - t_w
                    for k, status in recorded:
                        if status == DONE:
                            report.done += 1
                        else:
                            report.failed += 1
                        report.records.append((s, k, status))
                        bar.advance(status == FAILED)
                        if on_event is not None:
                            on_event({"shape": s, "case": k, "status": status, "report": report})
                store.flush(FLUSH_INTERVAL_S)
            report.phase2_s = time.perf_counter() - t2
            report.cluster_cpus = max(report.cpus, limit.cpus_seen)
            report.cpus, report.nodes = cpus_used(report.workers, _node_cpus()) if report.workers else (report.cluster_cpus, 0)
    finally:
        store.flush()
        report.wall_s = time.perf_counter() - t_start
        try:
            store.end_run(run, {"done": report.done, "failed": report.failed, "submitted": report.submitted,
                                "lost": report.lost, "cpus_used": report.cpus, "nodes": report.nodes,
                                "wall_s": report.wall_s, "phase1_s": report.phase1_s, "phase2_s": report.phase2_s})
        except Exception:
            pass
    return report


def cpus_used(workers, node_cpus: dict) -> tuple[float, int]:
    """(CPUs, nodes) that solved cases: each worker process runs one task (one CPU) at a time, so a
    node used as many CPUs as it had distinct workers, at most its CPU count (Ray may replace a
    worker). workers: {(node id or host, pid)}; node_cpus: {node id: CPUs} (ray.nodes())."""
    from collections import Counter

    per_node = Counter(node for node, _ in workers)
    return float(sum(min(n, node_cpus.get(node, n)) for node, n in per_node.items())), len(per_node)


def _node_cpus() -> dict:
    """{node id: CPUs} of every node Ray knows, alive or gone."""
    import ray

    try:
        return {n["NodeID"]: float(n.get("Resources", {}).get("CPU", 0.0)) for n in ray.nodes()}
    except Exception:
        return {}


class InFlightLimit:
    """How many tasks the driver keeps submitted: `fixed` when given, else twice the cluster's CPUs,
    read again every `every_s` seconds. On an autoscaling cluster (a head with no CPUs, workers
    added on demand) the waiting tasks are the demand the autoscaler sees, so the limit must grow
    with the nodes that join: 2 × CPUs keeps one CPU's worth of tasks queued per CPU running."""

    def __init__(self, fixed: int | None, cluster_cpus, every_s: float = 5.0, clock=time.monotonic):
        self.fixed, self._cpus, self.every_s, self._clock = fixed, cluster_cpus, every_s, clock
        self.cpus_seen = 0.0
        self._next = -float("inf")
        self.value = fixed if fixed is not None else 2
        self.current()

    def current(self) -> int:
        if self.fixed is None and self._clock() >= self._next:
            cpus = self._cpus()
            self.cpus_seen = max(self.cpus_seen, cpus)
            self.value = max(2, int(2 * cpus))
            self._next = self._clock() + self.every_s
        return self.value


def _tet_mesh(store: PairStore, s: int):
    from solver.mesh import TetMesh

    a = store.mesh_arrays(s)
    return TetMesh(a["ed_reference"].astype(float), a["tets"].astype(np.int64), a["endo"].astype(np.int64),
                   a["epi"].astype(np.int64), a["base"].astype(np.int64), {"shape_id": s})


class HeldResults:
    """The returned cases the driver has not written yet, per shape. Each object of a sharded store
    is a whole shape's shard, rewritten whole by every write into it, so a shape's cases are written
    together: when none of its chains is waiting or in flight any more, when they are at least as
    many as the cases its shard already holds (each write doubles the shard: about log2(chains) + 1
    writes while the chains return close together), or when the oldest has waited WRITE_HOLD_S. A version 1
    store (an object per case) writes each task's cases at once. Held cases are pending: a driver
    killed while it holds them leaves them to the next run.

    stored(shape): how many cases the shape's shard holds (its done cases)."""

    def __init__(self, hold: bool, stored, clock=time.monotonic):
        from collections import Counter

        self.hold, self._stored, self._clock = hold, stored, clock
        self._outstanding = Counter()  # shape → its chains waiting or in flight
        self._held: dict[int, tuple[float, list]] = {}  # shape → (since, [(k, result, submitted_at)])

    def expect(self, shape: int) -> None:
        """A chain of the shape is to be submitted."""
        self._outstanding[shape] += 1

    def add(self, shape: int, items: list) -> None:
        """A chain of the shape returned: its (k, result, submitted_at) of the cases to record."""
        self._outstanding[shape] -= 1
        if items:
            self._held.setdefault(shape, (self._clock(), []))[1].extend(items)

    def due(self) -> list[int]:
        """The shapes whose held cases are to be written now."""
        now = self._clock()
        return [s for s, (since, items) in list(self._held.items())
                if not self.hold or self._outstanding[s] <= 0 or len(items) >= self._stored(s)
                or now - since >= WRITE_HOLD_S]

    def take(self, shape: int) -> list:
        return self._held.pop(shape)[1]


def _record(store: PairStore, s: int, items: list, run: int) -> list[tuple[int, int]]:
    """Write the returned cases (k, result, submitted_at) of shape s in one write_pairs (its shard
    rewritten once) and mark each done or failed; returns (k, status) in the order given."""
    values = {}
    for k, result, submitted_at in items:
        values[k] = dict(result.get("stats") or {})
        values[k].update({"solve_attempts": result.get("attempts"), "task_wall_s": result.get("task_wall_s"),
                          "submitted_at": submitted_at, "started_at": result.get("started_at"),
                          "finished_at": result.get("finished_at"), "worker_pid": result.get("pid"), "run": run})
    solved = {k: (r["unloaded"], r["loaded"], values[k]) for k, r, _ in items if r.get("ok")}
    written = store.write_pairs(s, solved) if solved else {}
    out = []
    for k, result, _ in items:
        reason = written[k] if k in solved else result.get("reason")
        values[k]["stored_at"] = time.time()
        status = DONE if reason is None else FAILED
        store.set_case(s, k, status, stats_row(values[k]), result.get("host"), reason)
        out.append((k, status))
    return out


MAX_LOSSES = 3  # a case whose task was lost with its worker this many times (over runs) is failed


def _failed_task_results(store: PairStore, s: int, chain: list, exc: BaseException) -> list:
    """One result per case of a chain whose task raised: its own error fails every case, with the
    reason; a task lost with its worker or node (or out of memory) leaves each case pending (None)
    until that has happened MAX_LOSSES times to it, so a case that always kills its worker (a
    crash in native code, a mesh too large for the nodes) ends as failed instead of looping."""
    line = _error_line(exc)
    if not _lost_to_infrastructure(exc):
        return [{"ok": False, "reason": f"task error: {line}", "attempts": 0}] * len(chain)
    out = []
    for k in chain:
        n = store.note_loss(s, k)
        out.append(None if n < MAX_LOSSES else
                   {"ok": False, "reason": f"lost with its worker in {n} runs (last: {line})", "attempts": 0})
    return out


def _lost_to_infrastructure(exc: BaseException) -> bool:
    """A task that failed for want of a machine, not for its cases: its worker or node died after
    Ray's retries, or its process ran out of memory (`run_case` re-raises MemoryError)."""
    import ray

    if isinstance(exc, ray.exceptions.RayTaskError):
        return isinstance(getattr(exc, "cause", None), MemoryError)
    return True


def _error_line(exc: BaseException) -> str:
    import ray

    if isinstance(exc, ray.exceptions.RayTaskError):
        cause = exc.cause if getattr(exc, "cause", None) is not None else exc
        text = str(cause).strip().splitlines()
        return f"{type(cause).__name__}: {text[-1] if text else ''}".strip()
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".strip()


def _count(store: PairStore, shapes: int) -> dict:
    counts = {PENDING: 0, DONE: 0, FAILED: 0}
    for s in range(shapes):
        if store.shape_ready(s):
            st = store.status(s)
            for code in counts:
                counts[code] += int((st == code).sum())
        else:
            counts[PENDING] += store.n_cases
    return counts


class _Progress:
    """A rich progress bar: done / failed / rate / ETA (silent when disabled)."""

    def __init__(self, enabled: bool, total: int, completed: int, failed: int, console=None):
        self.enabled = enabled
        self.failed = failed
        self.total, self.completed = total, completed
        self._progress = None
        if enabled:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, \
                TimeRemainingColumn

            self._progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                      TextColumn("done {task.fields[done]} · failed {task.fields[failed]}"),
                                      TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TextColumn("ETA"),
                                      TimeRemainingColumn(), console=console or Console(stderr=True),
                                      transient=False)
            self._task = self._progress.add_task("starting", total=total, completed=completed, failed=failed,
                                                 done=completed - failed, rate="")
        self._t0 = time.perf_counter()
        self._n = 0

    def __enter__(self):
        if self._progress:
            self._progress.__enter__()
        return self

    def __exit__(self, *exc):
        if self._progress:
            self._progress.__exit__(*exc)

    def phase(self, text: str) -> None:
        if self._progress:
            self._progress.update(self._task, description=text)
            if text.startswith("solving"):
                self._t0 = time.perf_counter()

    def advance(self, failed: bool) -> None:
        self._n += 1
        self.completed += 1
        self.failed += int(failed)
        if self._progress:
            rate = self._n / max(time.perf_counter() - self._t0, 1e-9)
            self._progress.update(self._task, advance=1, failed=self.failed, done=self.completed - self.failed,
                                  rate=f"{rate * 3600:.0f}/h" if rate < 1 else f"{rate:.2f}/s")
