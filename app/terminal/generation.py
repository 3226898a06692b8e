"""`heartctl generate` in the terminal: the memory check of a local sweep, the sweep on Ray with its
refusals as one line, and the plan and report it prints."""
from __future__ import annotations

import os
from typing import TYPE_CHECKING

import typer

from . import console
from .console import fail, failures, json_line, size_text, stop_on_sigterm

if TYPE_CHECKING:
    from bench.sweep_speed import SweepBenchResult


def check_sweep_memory(sweep) -> None:
    """A local sweep whose workers' solves (solver.budget's estimate of one pair of a ~--nodes mesh at the
    sweep's preset, times the workers) need more memory than this machine has available: refused in one
    line (exit 2), naming how many workers would fit. User meshes (--meshes) are not estimated."""
    from solver.budget import estimate_for_nodes

    spec = sweep.spec
    if spec.meshes:
        return
    est = estimate_for_nodes(spec.fidelity, spec.nodes, inverse=True)
    workers = sweep.request.local_cpus or os.cpu_count() or 1
    available = console.available_memory()
    if est.peak_bytes * workers > available:
        fit = int(available // est.peak_bytes)
        instead = f"--num-cpus {fit}" if fit >= 1 else "a coarser --nodes or a cheaper --fidelity"
        fail(f"{workers} workers solving {spec.fidelity} pairs of ~{spec.nodes:,}-node meshes need about "
             f"{size_text(est.peak_bytes)} each, {size_text(est.peak_bytes * workers)} in all; {size_text(available)} are "
             f"available: use {instead}")


def warn_high_pressures(high: list[float], flag: str = "--pressures") -> None:
    """One warning line for pressures above end-diastolic ones (allowed: the solver decides)."""
    from solver.parameters import HIGHEST_ED_PRESSURE_MMHG

    if high:
        typer.echo(f"warning: {flag} {', '.join(f'{p:g}' for p in high)} mmHg: end-diastolic pressures are "
                   f"0–{HIGHEST_ED_PRESSURE_MMHG:g} mmHg; such cases may take long and fail", err=True)


def warn_high_pressure(pressure: float) -> None:
    """warn_high_pressures for the one --pressure of solve and unload."""
    from solver.parameters import HIGHEST_ED_PRESSURE_MMHG

    warn_high_pressures([pressure] if pressure > HIGHEST_ED_PRESSURE_MMHG else [], "--pressure")


def sweep_or_fail(sweep, where, warm_start: bool, retry_damaged: bool, progress: bool):
    """orchestrator.sweep.run_sweep within a ray_session: Ray that will not start and store errors
    exit 2, a full disk or a lost object store exits 1, Ctrl-C (or SIGTERM) 130, each in one line;
    done cases are kept."""
    from orchestrator.ray_session import ray_session, sweep_ray_options
    from orchestrator.sweep import run_sweep

    req = sweep.request
    with failures(interrupted="interrupted; done cases are kept, rerun the same command to resume"):
        with ray_session(where, **sweep_ray_options(req.num_cpus, req.local)):
            stop_on_sigterm()  # after ray.init, whose driver installs its own handler
            return run_sweep(sweep.spec, req.store, max_in_flight=req.max_in_flight, retry_failed=req.retry_failed,
                             progress=progress, warm_start=warm_start, retry_damaged=retry_damaged)


def print_nothing_to_run(sweep, as_json: bool) -> None:
    """A store that holds every case: the keys of a run's report with nothing submitted, or one line."""
    left, total = sweep.left, sweep.spec.n_cases
    if as_json:
        from orchestrator.sweep import SweepReport

        typer.echo(json_line(SweepReport(total=total, done_before=left["done"], failed_before=left["failed"]).as_dict()))
        return
    typer.echo(f"{sweep.request.store}: nothing to run — {left['done']} done, {left['failed']} failed of {total}"
               + (" (--retry-failed reruns the failed ones)" if left["failed"] else ""))


def print_sweep_report(report, store: str, retry_damaged: bool, as_json: bool) -> None:
    """The run's report: strict JSON, or the damaged cases recomputed and one summary line."""
    if as_json:
        typer.echo(json_line(report.as_dict()))
        return
    rate = report.throughput
    if retry_damaged:
        typer.echo(f"{len(report.damaged_reset)} damaged case(s) or shape(s) recomputed"
                   + (": " + ", ".join(f"shape {a} case {b}" if b is not None else f"shape {a} (meshed again, every case)"
                                       for a, b in report.damaged_reset[:10]) if report.damaged_reset else "")
                   + (" …" if len(report.damaged_reset) > 10 else ""))
    typer.echo(f"{store}: {report.done_before + report.done} done, {report.failed_now} failed "
               f"of {report.total} ({report.done} done and {report.failed} failed in this run, "
               f"{report.submitted} submitted); meshing {report.phase1_s:.1f} s, pairs {report.phase2_s:.1f} s "
               f"on {cpus_text(report)} ({rate:.2f} cases/s)"
               + (f"; {report.lost} cases lost with their workers are still pending (rerun to solve them)"
                  if report.lost else "") if report.submitted else
               f"{store}: nothing to run — {report.done_before} done, {report.failed_before} failed of {report.total}")


def cpus_text(report) -> str:
    """Where the pairs were solved: the CPUs whose workers solved them (and their nodes, if several),
    and the cluster's CPUs when it had more."""
    where = f"{report.cpus:g} CPU{'s' if report.cpus != 1 else ''}"
    if report.nodes > 1:
        where += f" of {report.nodes} nodes"
    if report.cluster_cpus > report.cpus:
        where += f" (the cluster had {report.cluster_cpus:g})"
    return where


def run_state_text(writer: dict | None, object_store: bool) -> str:
    """How an unfinished run stands: a local store's writer lock tells a running driver from a dead one."""
    if writer is not None:
        return f", running: pid {writer.get('pid')} on {writer.get('host')}"
    return ", running or interrupted" if object_store else ", interrupted"


def print_plan(plan, as_json: bool) -> None:
    """A dry run's plan (orchestrator.plan.SweepPlan): strict JSON, or the grid, counts, calibration,
    estimates and the paper's sweep."""
    if as_json:
        typer.echo(json_line(plan.as_dict()))
        return
    g = plan.grid
    axes = " × ".join(f"{len(g[a])} {n}" for a, n in (("pressure_mmhg", "P"), ("stiffness_pa", "C"),
                                                      ("helix_endo_deg", "θendo"), ("helix_epi_deg", "θepi")))
    how = ("new store" if not plan.resume else "resume" if plan.grows_from is None else
           f"resume, growing the store from {plan.grows_from} shapes")
    typer.echo(f"plan for {plan.store} ({how}): {plan.shapes} shapes × "
               f"{axes} = {plan.cases} cases; {plan.done} done, {plan.failed} failed, {plan.to_run} to run")
    typer.echo(f"fidelity {plan.fidelity}, seed {plan.seed}, ~{plan.mesh_nodes} nodes per mesh")
    if plan.cost is not None:
        _print_cost(plan.cost, plan.store_objects)


def _print_cost(cost, store_objects: int) -> None:
    cal, p = cost.calibration, cost.calibration["params"]
    status = "ok" if cal["ok"] else f"FAILED: {cal['reason']}"
    typer.echo(f"calibration: shape 0 ({cal['nodes']} nodes) meshed in {cal['mesh_s']:.1f} s; one pair at "
               f"P={p[0]:g} mmHg, C={p[1]:g} Pa, θ={p[2]:g}/{p[3]:g}° took {cal['cold_pair_s']:.2f} s on 1 core ({status})"
               + (f", the next pressure warm-started from it {cal['warm_pair_s']:.2f} s: "
                  f"{cal['pair_s']:.2f} s a pair over a pressure chain" if "warm_pair_s" in cal else ""))
    typer.echo(f"estimate: {cost.core_hours:.2f} core-hours"
               + (f", {cost.wall_hours_at_cores * 60:.1f} min wall on {cost.cores} cores" if cost.cores else "")
               + f"; store ≈ {cost.store_bytes_estimate / 1e6:.0f} MB ({cal['case_bytes'] / 1e3:.1f} kB per case), "
               f"{store_objects:,} objects")
    typer.echo(f"to finish in one hour: {cost.cores_for_one_hour:,} cores, e.g. "
               f"{cost.worker_nodes_for_one_hour:,} worker nodes of 32 vCPUs (cluster.yaml's c7i.8xlarge)")
    full = cost.paper_full_sweep_core_hours
    line = (f"full paper sweep (19,440 pairs) at this fidelity and mesh size: {full:.1f} core-hours, "
            f"{full * 60 / 64:.0f} min on 64 cores, store ≈ {cost.paper_full_sweep_store_bytes / 1e9:.2f} GB")
    if cost.fast_goal is not None:
        line += (f"; goal ≤ 8 core-hours (≤ 1.5 s a pair): "
                 f"{'met' if cost.fast_goal['meets'] else 'NOT met'} ({cal['pair_s']:.2f} s a pair)")
    typer.echo(line)


def print_sweep_bench(result: "SweepBenchResult", as_json: bool) -> None:
    """`bench sweep`: strict JSON, or the throughput table per CPU count and what its columns mean."""
    if as_json:
        typer.echo(json_line(result.as_dict()))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"heartctl bench sweep — {result.cases} fast pairs, {result.nodes} nodes; "
                        f"plain serial {result.plain_serial_s_per_case:.2f} s/pair cold, "
                        f"{result.chained_serial_s_per_case:.2f} s/pair in warm-started pressure chains")
    for col in ("CPUs", "pairs/s", "speedup", "efficiency", "solve s (p50)", "idle core s/task", "submit→start s",
                "result→stored s", "no-op round trip s", "overhead % of solve (idle / stored / no-op)"):
        table.add_column(col, justify="right")
    for r in result.rows:
        table.add_row(str(r.cpus), f"{r.throughput_cases_per_s:.3f}", f"{r.speedup_vs_1:.2f}",
                      f"{100 * r.parallel_efficiency:.0f} %", f"{r.solve_s_median:.2f}",
                      f"{r.idle_core_s_per_task:.3f}", f"{r.submit_to_start_s_median:.3f}",
                      f"{r.result_to_stored_s_median:.4f}", f"{r.noop_roundtrip_s_median:.4f}",
                      f"{r.overhead_idle_core_pct:.1f} / {r.overhead_result_to_stored_pct:.2f} / "
                      f"{r.overhead_noop_pct:.2f}")
    Console(width=200).print(table)
    typer.echo("Ray rows: one cold pair per task. submit→start includes queueing (2 tasks in flight per CPU); "
               "idle core s/task = (CPUs × wall − Σ solve) / pairs, everything that is not solving.")
