"""The solver's commands in the terminal: `mesh`, `solve`, `verify`, and the solver benchmarks
(`bench solver`, `corners`, `convergence`, `trade`), each result as the lines and tables it prints."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from .console import json_line, machine_line

if TYPE_CHECKING:
    from bench.adaptive import AdaptiveBenchResult
    from bench.convergence import ConvergenceResult
    from bench.solver_speed import SolverTiming
    from bench.stability import CornerCase
    from bench.trade_table import TradeResult
    from solver.land_problems import Land1Result, Land2Result


def print_shape_mesh(result, out: Path) -> None:
    """`mesh`: the mesh written, its size and quality, and its shape descriptors."""
    from solver.descriptors import format_descriptors

    lv, shape_def = result.lv, result.shape_def
    typer.echo(f"shape {result.shape} (seed {result.seed}, shape model {result.shape_model}): {lv.n_nodes} nodes, "
               f"{len(lv.tets)} tets, EDV {result.cavity_volume_ml:.1f} mL, wall {shape_def.wall_thickness_mm:.1f} mm, "
               f"min scaled Jacobian {lv.info['min_scaled_jacobian']:.3f} → {out}")
    typer.echo(f"descriptors: {format_descriptors(result.descriptors)}")


def print_inflated(result, params, fidelity: str, base: str, out: Path) -> None:
    """`solve`: the forward solve's work and the displacement it found."""
    from app.meshing import displacement_summary_mm

    mean, largest = displacement_summary_mm(result.displacement)
    s = result.stats
    typer.echo(f"inflated to {params.label()} ({fidelity}, {base} base): "
               f"{s.load_steps} load steps, {s.newton_iterations} Newton iterations, {s.wall_s:.2f} s; "
               f"displacement mean {mean:.3f} / max {largest:.3f} mm → {out}")


def print_land(result: Land1Result | Land2Result, as_json: bool) -> None:
    """`verify`: one Land et al. (2015) problem against its published values."""
    r = result
    if as_json:
        typer.echo(json_line(r.as_dict()))
    elif r.problem == "land1":
        typer.echo(f"land1 ({r.fidelity}, {r.nodes} nodes, {r.dofs} dofs, {r.wall_s:.1f} s): "
                   f"deflection z {r.deflection_z_mm:.3f} mm vs reference {r.reference_mm:.3f} mm "
                   f"(error {r.error_mm:+.3f} mm)")
    else:
        typer.echo(f"land2 ({r.fidelity}, {r.nodes} nodes, {r.dofs} dofs, {r.wall_s:.1f} s): "
                   f"endo apex z {r.endo_apex_z_mm:.2f} mm (ref −26.61, {r.endo_apex_error_mm:+.2f}), "
                   f"epi apex z {r.epi_apex_z_mm:.2f} mm (ref −28.28, {r.epi_apex_error_mm:+.2f}), "
                   f"cavity {r.cavity_volume_mm3:.0f} mm³ (ref ≈10734)")


def print_solver_bench(rows: list["SolverTiming"], shape: int, nodes: int, threads: int, as_json: bool) -> None:
    """`bench solver`: a JSON line per row, or the timing table."""
    if as_json:
        for row in rows:
            typer.echo(json_line(row.as_dict()))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"heartctl bench solver — shape {shape}, ~{nodes} nodes, {threads} thread(s)")
    for col in ("preset", "case", "nodes", "dofs", "forward s", "asm/lin/other s", "Newton", "pair s",
                "pair asm/lin/other s", "pair Newton", "round trip mm"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(r.fidelity, r.case, str(r.nodes), str(r.dofs), f"{r.forward_s:.2f}",
                      f"{r.forward_assembly_s:.2f}/{r.forward_linear_s:.2f}/{r.forward_other_s:.2f}",
                      str(r.forward_newton), f"{r.pair_s:.2f}",
                      f"{r.pair_assembly_s:.2f}/{r.pair_linear_s:.2f}/{r.pair_other_s:.2f}",
                      str(r.pair_newton), f"{r.roundtrip_mm:.1e}")
    Console(width=200).print(table)


def report_header(title: str, details: str, threads: int = 1) -> str:
    """A report's Markdown header: the benchmark, the date and machine, its details, the command run."""
    return (f"# heartctl bench {title}\n\n{machine_line(threads)}{details}\n\n"
            f"Command: `heartctl {' '.join(sys.argv[1:])}`\n")


def print_corners(rows: list["CornerCase"], presets: list, out: Path | None, header: str) -> None:
    """`bench corners`: per box and preset, how many pairs converged and their extremes; with `out`,
    the region table and every row written there."""
    from bench.stability import region_table

    for box in sorted({r.box for r in rows}):
        for preset in presets:
            rs = [r for r in rows if r.box == box and r.preset == preset]
            ok = [r for r in rs if r.ok]
            bad = sum(1 for r in rs if r.finite is False)
            typer.echo(f"{box} box, {preset}: {len(ok)}/{len(rs)} converged, worst round trip "
                       f"{max((r.roundtrip_mm for r in ok), default=float('nan')):.1e} mm, min J "
                       f"{min((r.min_jacobian for r in ok), default=float('nan')):.3f}, max Q "
                       f"{max((r.q_max for r in ok), default=float('nan')):.1f}, {bad} non-finite answers, "
                       f"{sum(r.wall_s for r in rs):.0f} s")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "stability.md").write_text(header + "\n" + region_table(rows))
        (out / "stability.json").write_text(json.dumps([r.as_dict() for r in rows], indent=1))
        typer.echo(f"report: {out / 'stability.md'}")


def print_adaptive_bench(result: "AdaptiveBenchResult", paths: dict) -> None:
    """`bench adaptive`: per case, the indicator's ranking and each tolerance's error, estimate and time."""
    for r in result.rows:
        k = r.ranking
        typer.echo(f"{r.shape:>6} {r.case:>4} {r.nodes} nodes: indicator Spearman {k.spearman:.2f}, "
                   f"top 20 % holds {k.top_share:.0%} of the true error² (best {k.best_share:.0%}); accurate "
                   f"{r.accurate_error['mean_mm']:.3f} mm mean, {r.accurate_s:.1f} s; reference {r.reference_s:.1f} s")
        for a in r.adaptive:
            typer.echo(f"{'':>12} adaptive to {a.tolerance_mm:g} mm: {a.error['mean_mm']:.3f} mm mean / "
                       f"{a.error['p95_mm']:.3f} p95 (estimated p95 {a.estimate_p95_mm:.3f}, "
                       f"{'met' if a.met else 'not met'}), {a.wall_s:.1f} s = {a.time_vs_reference:.2f} × reference")
    typer.echo(f"report: {paths['markdown']}")


def print_convergence(result: "ConvergenceResult", paths: dict) -> None:
    """`bench convergence`: each hierarchy's level differences and order, each quadrature variant's error."""
    for o in result.orders:
        diffs = ", ".join(f"{d:.4f}" for d in o.level_diffs_mean_mm)
        order = (f"order {o.order_mean:.2f} (max-norm {o.order_max:.2f})" if len(o.level_diffs_mean_mm) >= 2
                 else f"with the deepest mesh's order {o.order_used:.2f}")
        typer.echo(f"{o.shape:>6} {o.case:>4} {o.hierarchy:>9} {o.preset:>8}: mean differences of levels "
                   f"{diffs} mm; {order}: finest level's error ≈ {o.finest_error_mean_mm:.4f} mm mean")
    for r in result.quadrature:
        if not r.failed:
            typer.echo(f"{r.shape:>6} {r.case:>4} {r.hierarchy:>9} {r.preset:>8} q{r.quad_degree} "
                       f"f{r.facet_quad_degree} level {r.level}: quadrature error "
                       f"{r.quadrature['mean_mm']:.4f} mm mean, {r.wall_s:.1f} s")
    typer.echo(f"report: {paths['markdown']}, {paths['plot']}")


def print_trade(result: "TradeResult", paths: dict) -> None:
    """`bench trade`: each method's error against the converged solution and time, the hybrid's goal and
    how well --check tracks the network's error."""
    for srow in result.summary:
        err = (f"mean {srow.mean_mm:.3f} / p95 {srow.p95_mm:.3f} / max {srow.max_mm:.3f} mm"
               if srow.mean_mm is not None else "no answer")
        typer.echo(f"{srow.resolution:>8} ({srow.nodes:>4} nodes) {srow.method:<22} {srow.ok}/{srow.cases} "
                   f"{err}, {srow.time_mean_s:.2f} s per case")
    goal = result.hybrid_goal
    if goal.cases:
        typer.echo(f"hybrid accurate to tolerance: {goal.time_ratio:.2f} × the cold accurate time (goal ≤ 0.30), "
                   f"answers within {goal.max_distance_mm:.1e} mm (goal ≤ 0.01)")
    track = result.check_network
    if track.answers:
        typer.echo(f"--check on the network's answers: Spearman {track.spearman_max:.2f} with the true max error "
                   f"(goal ≥ 0.8); true ≈ {track.true_over_estimate_median:.2f} × the check")
    typer.echo(f"report: {paths['markdown']}, {paths['plot']}, {paths['json']}")
