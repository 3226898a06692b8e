"""`heartctl bench sweep`: sweep throughput on 1, 2, … CPUs, parallel efficiency, and Ray's
overhead per task against a `fast` pair's solve time (one cold pair per task), and the serial time
per pair with and without the pressure chains' warm start."""
from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from storage.reader import PairReader
from storage.schema import DONE, STAT_NAMES

from orchestrator.grid import SweepSpec, pressure_chains
from orchestrator.ray_session import RayAddress, ray_session, sweep_ray_options
from orchestrator.sweep import run_sweep
from orchestrator.tasks import mesh_shape, run_case, run_chain


def bench_spec(cases: int, nodes: int) -> SweepSpec:
    pressures = tuple(float(p) for p in np.linspace(6.0, 12.0, max(1, cases // 2)))
    stiffness = (100.0, 200.0) if cases >= 2 else (150.0,)
    return SweepSpec(shapes=1, pressure_mmhg=pressures, stiffness_pa=stiffness, helix_endo_deg=(60.0,),
                     helix_epi_deg=(-60.0,), fidelity="fast", seed=0, nodes=nodes)


def _noop():
    return time.time()


def _ray_run(spec: SweepSpec, cpus: int, workdir: Path) -> dict:
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
    return {
        "cpus": cpus, "cases": n, "done": report.done, "failed": report.failed, "phase2_s": report.phase2_s,
        "throughput_cases_per_s": n / report.phase2_s, "solve_s_median": float(np.median(solve)),
        "solve_s_mean": float(solve.mean()),
        "submit_to_start_s_median": float(np.median(queue)),
        "result_to_stored_s_median": float(np.median(stored)),
        "driver_store_s_per_case": report.driver_store_s / max(n, 1),
        "idle_core_s_per_task": idle_core_s / max(n, 1),
        "noop_roundtrip_s_median": statistics.median(lat),
    }


def parse_cpu_counts(text: str) -> list[int]:
    """'1,2' (commas and/or spaces) → [1, 2]; ValueError (one line, naming --cpus) unless they are integers ≥ 1."""
    try:
        counts = [int(c) for c in text.replace(",", " ").split()]
    except ValueError:
        raise ValueError(f"`cpus` must be comma-separated integers, got {text!r}") from None
    if not counts or min(counts) < 1:
        raise ValueError("`cpus` needs counts ≥ 1")
    return counts


def run_sweep_benchmark(cases: int = 8, nodes: int = 200, cpus=(1, 2)) -> dict:
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
    rows = []
    with tempfile.TemporaryDirectory(prefix="heartctl-bench-") as tmp:
        for k in cpus:
            rows.append(_ray_run(spec, int(k), Path(tmp)))
    base = rows[0]
    for r in rows:
        r["speedup_vs_1"] = r["throughput_cases_per_s"] / base["throughput_cases_per_s"] * base["cpus"]
        r["parallel_efficiency"] = r["throughput_cases_per_s"] / (r["cpus"] * base["throughput_cases_per_s"] / base["cpus"])
        r["throughput_vs_plain"] = r["throughput_cases_per_s"] / (len(plain) / plain_wall) / r["cpus"]
        s = r["solve_s_median"]
        r["overhead_submit_to_start_pct"] = 100 * r["submit_to_start_s_median"] / s
        r["overhead_result_to_stored_pct"] = 100 * r["result_to_stored_s_median"] / s
        r["overhead_noop_pct"] = 100 * r["noop_roundtrip_s_median"] / s
        r["overhead_idle_core_pct"] = 100 * r["idle_core_s_per_task"] / s
    return {"nodes": int(m.n_nodes), "cases": spec.n_cases, "plain_serial_s_per_case": plain_wall / len(plain),
            "chained_serial_s_per_case": chained_wall / len(plain),
            "plain_solve_s_median": float(np.median(plain)), "rows": rows}
