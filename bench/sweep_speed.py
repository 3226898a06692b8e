"""`heartctl bench sweep`: sweep throughput on 1, 2, … CPUs, parallel efficiency, and Ray's
overhead per task against a `fast` pair's solve time (one cold pair per task), and the serial time
per pair with and without the pressure chains' warm start."""
from __future__ import annotations

import statistics
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from storage.reader import PairReader
from storage.schema import DONE, STAT_NAMES

from orchestrator.grid import SweepSpec, pressure_chains
from orchestrator.ray_session import RayAddress, ray_session, sweep_ray_options
from orchestrator.sweep import run_sweep
from orchestrator.tasks import mesh_shape, run_case, run_chain


@dataclass(frozen=True, kw_only=True)
class CpuRun:
    """The sweep on one CPU count: pairs done and failed of `cases`, phase-2 wall time (s) and
    throughput (pairs/s); medians of a pair's solve, submit→start and result→stored times and the mean
    solve (s); the driver's store time and the idle core time per pair (s); a no-op Ray round trip (s);
    and against the first CPU count and the plain serial loop: speedup, parallel efficiency, throughput
    per CPU over the plain loop's, and each overhead as a percentage of the median solve."""

    cpus: int
    cases: int
    done: int
    failed: int
    phase2_s: float
    throughput_cases_per_s: float
    solve_s_median: float
    solve_s_mean: float
    submit_to_start_s_median: float
    result_to_stored_s_median: float
    driver_store_s_per_case: float
    idle_core_s_per_task: float
    noop_roundtrip_s_median: float
    speedup_vs_1: float = float("nan")
    parallel_efficiency: float = float("nan")
    throughput_vs_plain: float = float("nan")
    overhead_submit_to_start_pct: float = float("nan")
    overhead_result_to_stored_pct: float = float("nan")
    overhead_noop_pct: float = float("nan")
    overhead_idle_core_pct: float = float("nan")

    def compared(self, first: "CpuRun", plain_per_s: float) -> "CpuRun":
        """This run with its figures against the first CPU count's run and the plain loop's pairs/s."""
        s = self.solve_s_median
        per_cpu_first = first.throughput_cases_per_s / first.cpus
        return replace(self, speedup_vs_1=self.throughput_cases_per_s / first.throughput_cases_per_s * first.cpus,
                       parallel_efficiency=self.throughput_cases_per_s / (self.cpus * per_cpu_first),
                       throughput_vs_plain=self.throughput_cases_per_s / plain_per_s / self.cpus,
                       overhead_submit_to_start_pct=100 * self.submit_to_start_s_median / s,
                       overhead_result_to_stored_pct=100 * self.result_to_stored_s_median / s,
                       overhead_noop_pct=100 * self.noop_roundtrip_s_median / s,
                       overhead_idle_core_pct=100 * self.idle_core_s_per_task / s)


@dataclass(frozen=True, kw_only=True)
class SweepBenchResult:
    """`bench sweep`'s result: the mesh's nodes, the pairs per run, the plain serial loop's time per pair
    cold and in warm-started pressure chains (s) and its median solve (s), and a CpuRun per CPU count."""

    nodes: int
    cases: int
    plain_serial_s_per_case: float
    chained_serial_s_per_case: float
    plain_solve_s_median: float
    rows: list[CpuRun]

    def as_dict(self) -> dict:
        return asdict(self)


def bench_spec(cases: int, nodes: int) -> SweepSpec:
    pressures = tuple(float(p) for p in np.linspace(6.0, 12.0, max(1, cases // 2)))
    stiffness = (100.0, 200.0) if cases >= 2 else (150.0,)
    return SweepSpec(shapes=1, pressure_mmhg=pressures, stiffness_pa=stiffness, helix_endo_deg=(60.0,),
                     helix_epi_deg=(-60.0,), fidelity="fast", seed=0, nodes=nodes)


def _noop():
    return time.time()


def _ray_run(spec: SweepSpec, cpus: int, workdir: Path) -> CpuRun:
    import ray

    from orchestrator.tasks import warm_up

    with ray_session(RayAddress(), **sweep_ray_options(cpus, local=True)):
        # warm the worker pool (process start + solver import are one-off costs, not per task)
        ray.get([ray.remote(num_cpus=1)(warm_up).remote(0.5) for _ in range(cpus)])
        noop = ray.remote(num_cpus=1)(_noop)
        lat = []
        for _ in range(30):
            t = time.time()
            ray.get(noop.remote())
            lat.append(time.time() - t)
        store = workdir / f"bench-{cpus}cpu.zarr"
        # one pair per task, cold: Ray's per-task overhead against one pair's solve (the chains'
        # warm start is measured serially in run_sweep_benchmark)
        report = run_sweep(spec, str(store), progress=False, warm_start=False, chain_length=1)
    reader = PairReader(str(store))
    st = reader.stats(0)[reader.status(0) == DONE]
    col = {n: i for i, n in enumerate(STAT_NAMES)}
    solve = st[:, col["task_wall_s"]]
    queue = st[:, col["started_at"]] - st[:, col["submitted_at"]]
    stored = st[:, col["stored_at"]] - st[:, col["finished_at"]]
    n = report.done + report.failed
    idle_core_s = cpus * report.phase2_s - float(solve.sum())
    return CpuRun(
        cpus=cpus, cases=n, done=report.done, failed=report.failed, phase2_s=report.phase2_s,
        throughput_cases_per_s=n / report.phase2_s, solve_s_median=float(np.median(solve)),
        solve_s_mean=float(solve.mean()), submit_to_start_s_median=float(np.median(queue)),
        result_to_stored_s_median=float(np.median(stored)),
        driver_store_s_per_case=report.driver_store_s / max(n, 1),
        idle_core_s_per_task=idle_core_s / max(n, 1), noop_roundtrip_s_median=statistics.median(lat))


def parse_cpu_counts(text: str) -> list[int]:
    """'1,2' (commas and/or spaces) → [1, 2]; ValueError (one line, naming --cpus) unless they are integers ≥ 1."""
    try:
        counts = [int(c) for c in text.replace(",", " ").split()]
    except ValueError:
        raise ValueError(f"`cpus` must be comma-separated integers, got {text!r}") from None
    if not counts or min(counts) < 1:
        raise ValueError("`cpus` needs counts ≥ 1")
    return counts


def run_sweep_benchmark(cases: int = 8, nodes: int = 200, cpus=(1, 2)) -> SweepBenchResult:
    """The benchmark's figures for `cases` fast pairs of one shape meshed to about `nodes` nodes, on
    each CPU count of `cpus`; ValueError (one line) for a count of cases or nodes out of range."""
    from solver.meshing import check_node_target

    if cases < 1 or nodes < 50:
        raise ValueError("`cases` must be ≥ 1 and `nodes` ≥ 50")
    check_node_target(nodes)
    spec = bench_spec(cases, nodes).validate()
    # in-process reference: the same cases, serially, no Ray
    m = mesh_shape(0, spec.seed, spec.nodes)["mesh"]
    run_case(m, spec.case_params()[0], "fast")  # warm imports / caches
    t = time.perf_counter()
    plain = [run_case(m, p, "fast")["task_wall_s"] for p in spec.case_params()]
    plain_wall = time.perf_counter() - t
    params = spec.case_params()
    t = time.perf_counter()
    for chain in pressure_chains(params, range(len(params))):
        run_chain(m, [params[k] for k in chain], "fast")
    chained_wall = time.perf_counter() - t
    with tempfile.TemporaryDirectory(prefix="heartctl-bench-") as tmp:
        runs = [_ray_run(spec, int(k), Path(tmp)) for k in cpus]
    plain_per_s = len(plain) / plain_wall
    return SweepBenchResult(nodes=int(m.n_nodes), cases=spec.n_cases, plain_serial_s_per_case=plain_wall / len(plain),
                            chained_serial_s_per_case=chained_wall / len(plain),
                            plain_solve_s_median=float(np.median(plain)),
                            rows=[r.compared(runs[0], plain_per_s) for r in runs])
