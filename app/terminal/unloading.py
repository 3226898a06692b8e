"""`heartctl unload` in the terminal: the method run, the unloaded mesh written, and what was done
printed in one line (with `--check`, the answer inflated again)."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import typer

from .console import failures, progress_of, say
from .inputs import solve_budget, write_mesh_file

if TYPE_CHECKING:
    from app.method_choice import MethodChoice


def print_auto_choice(choice: MethodChoice, tolerance_mm: float) -> None:
    """`--method auto`: the trade table's choice and the error it expects."""
    typer.echo(f"auto: {choice.label} (p95 {choice.p95_mm:.3f} mm, max {choice.max_mm:.3f} mm against the "
               f"converged solution on the trade table's {choice.nodes}-node held-out meshes, "
               f"{choice.time_mean_s:.2f} s per case there; asked ≤ {tolerance_mm:g} mm)")


def print_check(lv, unloaded, params, fidelity: str, base: str, fibres: str) -> None:
    """`--check`: the answer inflated again; its distance from the ED mesh estimates its error."""
    from solver.reinflate import reinflation_error

    chk = reinflation_error(lv, unloaded, params, fidelity, base, fibres)
    if not chk.ok:
        typer.echo(f"check: the answer could not be inflated again ({chk.failed}): do not trust it", err=True)
        return
    typer.echo(f"check: inflated again ({fidelity}, {chk.wall_s:.1f} s), the answer lands {chk.mean_mm:.3f} mm mean / "
               f"{chk.max_mm:.3f} mm max from the ED mesh: an estimate of its error against the {fidelity} model")


def unload_or_fail(lv, params, plan):
    """app.unload.unload_mesh: an inverse FE that fails exits 1, a network's refusal 2; the
    network's warnings as lines on stderr."""
    from app.unload import unload_mesh

    with failures(solve="inverse solve did not converge"):
        result = unload_mesh(lv, params, plan)
    for w in result.warnings:
        say(f"heartctl: warning: {w}", err=True)
    return result


def write_unloaded(out: Path, lv, result, units: str) -> None:
    """The unloaded mesh with point data `displacement` (ED − unloaded) and, for an ensemble of
    networks, `ensemble_spread` (a hybrid's answer is the FE's: no network spread to show); an adaptive
    solve's `estimated_error` (mm, per node)."""
    shift = lv.nodes - result.unloaded_nodes
    point_data, lengths = {"displacement": shift}, ["displacement"]
    if result.adaptive is not None and result.adaptive.steps[-1].estimate_p95_mm is not None:
        point_data["estimated_error"] = result.adaptive.estimated_error_mm
        lengths.append("estimated_error")
    if result.method == "gnn" and result.network.members > 1:
        point_data["ensemble_spread"] = result.network.spread_mm
        lengths.append("ensemble_spread")
    write_mesh_file(out, lv, result.unloaded_nodes, point_data=point_data, units=units, length_fields=tuple(lengths))


def print_unloaded(result, lv, params, plan, out: Path) -> None:
    """One line: how the mesh was unloaded (FE's updates and mismatch, the network's time, or the
    hybrid's both) and the ED − unloaded displacement."""
    d = np.linalg.norm(lv.nodes - result.unloaded_nodes, axis=1)
    moved = f"ED − unloaded mean {d.mean():.3f} / max {d.max():.3f} mm → {out}"
    inv, net = result.inverse, result.network
    if result.adaptive is not None:
        print_adaptive(result.adaptive, params, plan, moved)
    elif result.method == "fe":
        typer.echo(f"unloaded at {params.label()} ({plan.fidelity}, {plan.base} base): {inv.updates} updates, "
                   f"{inv.stats.newton_iterations} Newton iterations, {inv.stats.wall_s:.2f} s, "
                   f"mismatch {inv.mismatch_mm:.2e} mm; {moved}")
    elif result.method == "gnn":
        spread = (f"; the {net.members} networks disagree by {net.spread_mm.mean():.3f} mm mean / "
                  f"{net.spread_mm.max():.3f} mm max (RMS about their mean, point data ensemble_spread)"
                  if net.members > 1 else "")
        typer.echo(f"unloaded at {params.label()} by the network {net.run} in {net.network_ms:.1f} ms "
                   f"(first call with graph building{' and the linear FE response' if net.with_response else ''} "
                   f"{net.first_call_ms:.0f} ms); "
                   f"ED − unloaded mean {d.mean():.3f} / max {d.max():.3f} mm{spread} → {out}")
    else:
        dropped = ""
        if net.fallback:
            lost = net.guess_attempt_s
            dropped = ", guess unusable" + (f" after {lost:.1f} s of inverse FE from it" if lost is not None else "")
        budget = f", at most {plan.max_updates} updates" if plan.max_updates is not None else ""
        typer.echo(f"unloaded at {params.label()} (hybrid: network {net.network_ms:.1f} ms{dropped}"
                   f", then {plan.fidelity} inverse FE{budget}): {inv.updates} updates, "
                   f"{inv.stats.newton_iterations} Newton iterations, {inv.stats.wall_s:.2f} s, mismatch {inv.mismatch_mm:.2e} mm; "
                   f"network guess was {net.guess_error_mm:.3f} mm (max) from the FE answer; {moved}")


def print_adaptive(adaptive, params, plan, moved: str) -> None:
    """An adaptive unload: each mesh it solved on, and whether the estimate met the tolerance."""
    steps = "; ".join(f"{s.nodes:,} nodes" + (f" ({s.split_tets} of the ED tets split)" if s.split_tets else "")
                      + f" {s.wall_s:.1f} s" + (f", estimated p95 {s.estimate_p95_mm:.3f} mm"
                                                 if s.estimate_p95_mm is not None else "") for s in adaptive.steps)
    last = adaptive.steps[-1]
    typer.echo(f"unloaded at {params.label()} (adaptive, {plan.base} base): {steps}; tolerance "
               f"{plan.tolerance_mm:g} mm {'met' if adaptive.met else 'not met'}; {adaptive.stats.wall_s:.2f} s, "
               f"mismatch {adaptive.mismatch_mm:.2e} mm; {moved}")
    if not adaptive.met:
        say(f"heartctl: warning: the estimated p95 error {last.estimate_p95_mm:.3f} mm is above --tolerance-mm "
            f"{plan.tolerance_mm:g} after {len(adaptive.steps) - 1} refinements (the answer is the last one's); --fidelity "
            f"reference or a finer mesh goes further", err=True)


def unload_and_report(mesh_path: Path, lv, params, plan, choice: dict | None, request, out: Path, units: str) -> None:
    """Run a checked unload plan on the ED mesh `lv` (auto's choice said first; the solve's memory
    checked and its progress shown when it is long), write the unloaded mesh to `out` and say what was
    done; with the request's check, inflate the answer again and say how far it lands."""
    if choice is not None:
        print_auto_choice(choice, request.tolerance_mm)
    inverse = plan.method in ("fe", "hybrid")
    est = solve_budget(mesh_path, lv, plan.fidelity, inverse=inverse) if inverse or request.check else None
    with progress_of(est if inverse else None, str(mesh_path)):
        result = unload_or_fail(lv, params, plan)
    write_unloaded(out, lv, result, units)
    print_unloaded(result, lv, params, plan, out)
    if request.check and plan.method != "fe":
        print_check(lv, result.unloaded_nodes, params, plan.fidelity, plan.base, plan.fibres)
