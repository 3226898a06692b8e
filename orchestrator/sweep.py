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
from storage.location import object_store_problem
from storage.schema import DONE, FAILED, PENDING, inspect_store
from storage.writer import PairStore, stats_row

from .grid import MAX_CHAIN, SweepSpec, pressure_chains
from .pacing import HeldResults, InFlightLimit, SweepProgress, cpus_used, node_cpus

TASK_MAX_RETRIES = 3  # worker process crash / node loss
FLUSH_INTERVAL_S = 2.0


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
    from storage.reader import PairReader
    from storage.writer import remove_partial_files

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


def check_request(spec: SweepSpec, location: str, for_writing: bool = True, retry_damaged: bool = False,
                  reader=None) -> dict | None:
    """Validate the spec and the store it targets, read-only. Returns the store's attributes
    (None when the store is new). Raises ValueError / StoreError / SweepConflict (one line).
    `for_writing` (not for a dry run) also needs a writable store no other driver is writing.
    Damage that shows without reading the cases (a shape's arrays not what the schema implies, a
    status code out of range) is refused unless `retry_damaged`, which repairs it. `reader`: the
    store opened already (a PairReader), read instead of opening it again."""
    spec.validate()
    if for_writing and str(location).startswith("memory://"):
        raise ValueError(f"store {location}: a memory:// store vanishes when generate exits; give a folder or an "
                         f"object-store URL (s3://…)")
    attrs = reader.attrs if reader is not None else inspect_store(location)
    if for_writing:
        _check_writable(location)
    if attrs is not None and for_writing:
        check_free(location)  # another driver is writing it
    if attrs is not None:
        conflicts = spec.conflicts(attrs)
        if conflicts:
            raise _conflict(location, conflicts)
        from storage.reader import PairReader

        reader = reader or PairReader(location)
        _check_table_damage(reader, location, retry_damaged)
        _check_shape_tables(reader, location, np.asarray(attrs["case_params"], dtype=float))
    return attrs


def _check_table_damage(reader, location: str, retry_damaged: bool) -> None:
    """StoreError naming the first damage of a shape's arrays or status codes, unless retry_damaged."""
    from storage.location import StoreError

    if retry_damaged:
        return
    for s in reader.shape_ids():
        for k, why in reader.table_damage(s)[:1]:
            where = f"shape {s}" if k is None else f"shape {s} case {k}"
            raise StoreError(f"store {location}: {where} is damaged: {why}; generating with `retry_damaged` "
                             f"{'meshes the shape again and recomputes its cases' if k is None else 'recomputes it'}")


def _conflict(location: str, conflicts: list[str]) -> SweepConflict:
    return SweepConflict(f"store {location} was made with another setup: {'; '.join(conflicts)}; "
                         f"use the store's settings to resume, or a new `store`")


def _check_shape_tables(reader, location: str, case_params: np.ndarray) -> None:
    """SweepConflict when a shape's own parameter table (what readers label its cases with) differs
    from the store's case_params (what the driver solves): resuming would store mislabelled data."""
    for s in reader.shape_ids():
        if reader.shape_problem(s) is None and not np.array_equal(reader.case_params(s), case_params):
            raise SweepConflict(f"store {location}: shape {s}'s parameter table differs from the store's case_params "
                                f"(edited by hand?); it cannot be resumed")


def _check_writable(location: str) -> None:
    """ValueError when a local store (or the folder it would be made in) cannot be written, found
    before Ray starts; object stores are left to their own permissions."""
    from storage.location import is_url, local_path

    if is_url(location):
        return
    path = local_path(location).absolute()
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


def remaining_cases(spec: SweepSpec, location: str, retry_failed: bool = False, reader=None) -> dict:
    """Read-only counts of a store for this spec: done, failed, and to_run (cases a run would submit,
    counting every case of a shape not meshed yet or damaged, and every status code out of range).
    `reader`: the store opened already (a PairReader)."""
    from storage.reader import PairReader

    if reader is None and inspect_store(location) is None:
        return {"done": 0, "failed": 0, "to_run": spec.n_cases}
    counts = (reader or PairReader(location)).counts(spec.shapes)
    return {"done": counts.done, "failed": counts.failed, "to_run": counts.to_run(retry_failed)}


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
    from storage.location import is_url, local_path

    attrs = check_request(spec, location, retry_damaged=retry_damaged)
    folder = None if is_url(location) else local_path(location)
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
    """run_sweep's body, with the store open and its writer lock held: phase 1 meshes the shapes not
    meshed yet, phase 2 solves the pending cases' pressure chains."""
    import ray

    cpus = float(ray.cluster_resources().get("CPU", 1.0))
    limit = InFlightLimit(max_in_flight, lambda: float(ray.cluster_resources().get("CPU", 0.0)))
    report = _begin_run(spec, store, cpus, limit, warm_start)
    mesh_remote, chain_remote = _remotes()
    kept_failed = 0 if retry_failed else report.failed_before
    report.retried_failed = report.failed_before - kept_failed
    bar = SweepProgress(progress, spec.n_cases, report.done_before + kept_failed, kept_failed, console)
    try:
        with bar:
            _mesh_phase(spec, store, mesh_remote, report, bar)
            chains = _pending_chains(spec, store, retry_failed, chain_length)
            _pair_phase(spec, store, chains, _ChainTask(chain_remote, spec, warm_start), limit, report, bar, on_event)
            report.cluster_cpus = max(report.cpus, limit.cpus_seen)
            report.cpus, report.nodes = cpus_used(report.workers, node_cpus()) if report.workers else (report.cluster_cpus, 0)
    finally:
        store.flush()
        report.wall_s = time.perf_counter() - t_start
        try:
            store.end_run(report.run, {"done": report.done, "failed": report.failed, "submitted": report.submitted,
                                       "lost": report.lost, "cpus_used": report.cpus, "nodes": report.nodes,
                                       "wall_s": report.wall_s, "phase1_s": report.phase1_s,
                                       "phase2_s": report.phase2_s})
        except Exception:
            pass
    return report


def _begin_run(spec: SweepSpec, store: PairStore, cpus: float, limit: InFlightLimit, warm_start: bool) -> SweepReport:
    """The run's report with the store's counts before it, and the run recorded in the store's audit
    trail (growing the store first when the spec has more shapes)."""
    counts_before = store.counts(spec.shapes)
    report = SweepReport(total=spec.n_cases, done_before=counts_before.done, failed_before=counts_before.failed,
                         cpus=cpus)
    grows_from = spec.grows(store.attrs)
    report.run = store.begin_run({"host": socket.gethostname(), "pid": os.getpid(), "cpus": cpus,
                                  "solver_version": solver_version(), "argv": sys.argv[:], "max_in_flight": limit.value,
                                  "done_before": report.done_before, "failed_before": report.failed_before,
                                  "warm_start": warm_start, "shapes": spec.shapes,
                                  **({"shapes_before": grows_from} if grows_from is not None else {})})
    if grows_from is not None:  # the added shapes are pending: phase 1 meshes them, phase 2 solves them
        store.grow_shapes(spec.shapes)
    return report


def _mesh_phase(spec: SweepSpec, store: PairStore, mesh_remote, report: SweepReport, bar: SweepProgress) -> None:
    """Phase 1: every shape not meshed yet meshed by a task and written with its case arrays; a shape
    that will not mesh is noted in the store, its cases left pending."""
    import ray

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
        except Exception as exc:
            store.record_mesh_failure(s, _error_line(exc))
            report.mesh_failures += 1
            continue
        m = out["mesh"]
        store.write_shape(s, m.nodes, m.tets, m.endo, m.epi, m.base, out["coefficients"], out["info"])
        report.meshed_shapes += 1
    report.phase1_s = time.perf_counter() - t1


def _pending_chains(spec: SweepSpec, store: PairStore, retry_failed: bool, chain_length: int) -> deque:
    """(shape, pressure chain of case indices) of every case to solve: pending ones, and failed ones
    when they are retried."""
    todo = deque()
    for s in range(spec.shapes):
        if not store.shape_ready(s):
            continue
        status = store.status(s)
        wanted = (status == PENDING) | ((status == FAILED) if retry_failed else False)
        todo.extend((s, chain) for chain in pressure_chains(store.params, np.flatnonzero(wanted), chain_length))
    return todo


@dataclass
class _ChainTask:
    """Submits one pressure chain of a shape as a task, the shape's mesh put in Ray's object store once."""

    remote: object
    spec: SweepSpec
    warm_start: bool
    meshes: dict = field(default_factory=dict)

    def submit(self, store: PairStore, s: int, chain: list):
        import ray

        if s not in self.meshes:
            self.meshes[s] = ray.put(_tet_mesh(store, s))
        return self.remote.remote(self.meshes[s], [tuple(store.params[k]) for k in chain], self.spec.fidelity,
                                  self.spec.base, fibres=self.spec.fibres, warm_start=self.warm_start)


def _pair_phase(spec: SweepSpec, store: PairStore, todo: deque, task: _ChainTask, limit: InFlightLimit,
                report: SweepReport, bar: SweepProgress, on_event) -> None:
    """Phase 2: the chains run as tasks, at most limit.current() in flight; returned cases are held
    (HeldResults) and recorded shape by shape; a task lost with its worker leaves its cases pending."""
    import ray

    t2 = time.perf_counter()
    held = HeldResults(store.sharded, lambda s: int((store.table(s).status == DONE).sum()))
    for s, _ in todo:
        held.expect(s)
    bar.phase(f"solving {sum(len(chain) for _, chain in todo)} pairs ({len(todo)} pressure chains) on "
              f"{report.cpus:g} CPUs")
    inflight: dict = {}
    while todo or inflight:
        while todo and len(inflight) < limit.current():
            s, chain = todo.popleft()
            inflight[task.submit(store, s, chain)] = (s, chain, time.time())
            report.submitted += len(chain)
        ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)
        for ref in ready:
            s, chain, submitted_at = inflight.pop(ref)
            held.add(s, _returned(store, s, chain, ref, submitted_at, report))
        for s in held.due():
            _store_shape(store, s, held.take(s), report, bar, on_event)
        store.flush(FLUSH_INTERVAL_S)
    report.phase2_s = time.perf_counter() - t2


def _returned(store: PairStore, s: int, chain: list, ref, submitted_at: float, report: SweepReport) -> list:
    """A returned task's (k, result, submitted_at) per case to record; a case lost with its worker
    (None) is left out and stays pending for the next run."""
    import ray

    try:
        results = ray.get(ref)
    except Exception as exc:
        results = _failed_task_results(store, s, chain, exc)
        report.lost += sum(r is None for r in results)
    for result in results:
        if result is not None and result.get("pid") is not None:
            report.workers.add((result.get("node") or result.get("host"), result["pid"]))
    return [(k, r, submitted_at) for k, r in zip(chain, results) if r is not None]


def _store_shape(store: PairStore, s: int, items: list, report: SweepReport, bar: SweepProgress, on_event) -> None:
    """Record a shape's held cases (_record) and count each in the report and the progress bar."""
    t_w = time.perf_counter()
    recorded = _record(store, s, items, report.run)
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


def _tet_mesh(store: PairStore, s: int):
    from solver.mesh import TetMesh

    a = store.mesh_arrays(s)
    return TetMesh(a["ed_reference"].astype(float), a["tets"].astype(np.int64), a["endo"].astype(np.int64),
                   a["epi"].astype(np.int64), a["base"].astype(np.int64), {"shape_id": s})


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


