"""`heartctl bench l2u` in the terminal: the original paper's pairs against ours, pair by pair."""
from __future__ import annotations

from typing import TYPE_CHECKING

import typer

from .console import json_line

if TYPE_CHECKING:
    from orchestrator.l2u_check import L2uCheckResult


def print_l2u_check(result: "L2uCheckResult", direction: str, as_json: bool) -> None:
    """bench l2u's comparison: JSON without the rows, or a line per pair, per parameter value, overall."""
    if as_json:
        typer.echo(json_line(result.as_dict(with_rows=False)))
        return
    o = result.overall
    what = "ED meshes unloaded" if direction == "inverse" else "unloaded meshes inflated"
    typer.echo(f"{result.solved}/{result.cases} of their {what} ({result.fidelity}, base {result.base}, "
               f"C × {result.stiffness_factor:g}, {result.fibres} fibres, quadrature degree {result.quad_degree})")
    for r in result.rows:
        if r.ok:
            typer.echo(f"  shape {r.shape} case {r.case}: P={r.pressure_mmhg:g} C={r.stiffness_pa:g} "
                       f"θ={r.helix_endo_deg:g}/{r.helix_epi_deg:g}: mismatch mean {r.mismatch_mean_mm:.3f} / "
                       f"max {r.mismatch_max_mm:.3f} mm; their loading {r.loading_mean_mm:.2f} mm, ours "
                       f"{r.ours_loading_mean_mm:.2f} mm → {100 * r.relative:.1f} %, {100 * r.aligned_relative:.1f} % "
                       f"after in-plane rigid alignment ({r.wall_s:.1f} s)")
        else:
            typer.echo(f"  shape {r.shape} case {r.case}: FAILED {r.reason}")
    for name, groups in result.by_parameter.items():
        parts = ", ".join(f"{v:g}: {100 * g.relative:.1f} % ({100 * g.aligned_relative:.1f} % aligned)"
                          for v, g in groups.items())
        typer.echo(f"  by {name}: {parts}")
    if o.n:
        typer.echo(f"overall: mean mismatch {o.mismatch_mean_mm:.3f} mm (max {o.mismatch_max_mm:.3f} mm) = "
                   f"{100 * o.relative:.1f} % of the mean loading displacement {o.loading_mean_mm:.2f} mm "
                   f"(ours {o.ours_loading_mean_mm:.2f} mm); after in-plane rigid alignment {o.aligned_mean_mm:.3f} mm "
                   f"= {100 * o.aligned_relative:.1f} %; goal ≤ 10 %")
