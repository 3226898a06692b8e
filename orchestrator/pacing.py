"""How the sweep driver paces a sweep: tasks kept in flight as the cluster grows (InFlightLimit),
returned cases held so that a shape's shard is rewritten a few times (HeldResults), the CPUs that
solved cases (cpus_used), and the progress bar on stderr (SweepProgress)."""
from __future__ import annotations

import time

WRITE_HOLD_S = 30.0  # s, the longest a returned case waits to be written into its shape's shard


def cpus_used(workers, node_cpus: dict) -> tuple[float, int]:
    """(CPUs, nodes) that solved cases: each worker process runs one task (one CPU) at a time, so a
    node used as many CPUs as it had distinct workers, at most its CPU count (Ray may replace a
    worker). workers: {(node id or host, pid)}; node_cpus: {node id: CPUs} (ray.nodes())."""
    from collections import Counter

    per_node = Counter(node for node, _ in workers)
    return float(sum(min(n, node_cpus.get(node, n)) for node, n in per_node.items())), len(per_node)


def node_cpus() -> dict:
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


class SweepProgress:
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
