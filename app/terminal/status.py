"""`heartctl status` in the terminal: a store's progress, times, failures and damage."""
from __future__ import annotations

import typer

from .console import seconds_text
from .generation import run_state_text


def print_status(s, store: str, verify: bool) -> None:
    """A store's status as lines and tables: counts, throughput and ETA, per-phase times, failure
    reasons, shapes that did not mesh, hosts, and with --verify the damaged cases."""
    from rich.console import Console
    from rich.table import Table

    from storage.location import is_url

    con = Console(width=160)
    made = ", ".join(part for part in (s.fidelity, None if s.seed is None else f"seed {s.seed}",
                                       None if s.mesh_nodes is None else f"~{s.mesh_nodes} nodes") if part)
    con.print(f"[bold]{store}[/bold]: {s.shapes} shapes × {s.cases_per_shape} cases = {s.total} "
              f"({made}{'; ' if made else ''}{s.shapes_ready} shapes meshed)")
    pct = lambda n: f"{100 * n / s.total:.1f} %" if s.total else "—"  # noqa: E731
    con.print(f"done {s.done} ({pct(s.done)}), failed {s.failed} ({pct(s.failed)}), "
              f"pending {s.pending} ({pct(s.pending)})"
              + (f", status unknown {s.unknown} ({pct(s.unknown)})" if s.unknown else ""))
    thr = s.throughput_cases_per_s
    lr = s.last_run or {}
    con.print(f"throughput (run {lr.get('index', '—')}, {lr.get('done_in_run', 0)} done"
              f"{'' if not lr else ', finished' if lr.get('ended') else run_state_text(s.writer, is_url(store))}"
              f"{'; over its whole wall time, meshing included' if lr else ''}): "
              + (f"{thr:.3f} cases/s ({thr * 3600:.0f}/h)" if thr else "—")
              + f"; ETA {seconds_text(s.eta_s)}"
              + (f"; store {s.store_bytes / 1e6:.1f} MB" if s.store_bytes is not None else ""))
    table = Table(title="per-case times, done cases (s)")
    for col in ("phase", "p50", "p90", "p99", "max", "mean"):
        table.add_column(col, justify="right")
    for name, p in s.phase_percentiles_s.items():
        if p is None:
            table.add_row(name, *["—"] * 5)
        else:
            table.add_row(name, *(f"{p[k]:.3f}" for k in ("p50", "p90", "p99", "max", "mean")))
    con.print(table)
    if s.failure_reasons:
        ft = Table(title="failure reasons")
        ft.add_column("cases", justify="right")
        ft.add_column("reason (numbers as #)")
        ft.add_column("e.g. (shape, case)")
        for f in s.failure_reasons:
            ft.add_row(str(f["count"]), f["reason"], ", ".join(f"({a}, {b})" for a, b in f["cases"]))
        con.print(ft)
    if s.mesh_failures:
        con.print(f"shapes that did not mesh: {s.mesh_failures}")
    if s.hosts:
        con.print("done by host: " + ", ".join(f"{h} {n}" for h, n in sorted(s.hosts.items())))
    damaged = s.damaged if verify else s.table_damage
    if verify and not damaged:
        con.print(f"verified: all {s.done} done cases read back intact (checksums match, data present and "
                  f"finite, arrays as the schema says)")
    for d in damaged:
        where = "every case" if d["case"] is None else f"case {d['case']}"
        typer.echo(f"damaged: shape {d['shape']} {where}: {d['reason']}")
    if damaged:
        typer.echo(f"{damage_count_text(damaged, s.cases_per_shape)}; `heartctl generate --store {store} "
                   f"--retry-damaged` recomputes them" + ("" if verify else "; `--verify` reads every done case"))


def damage_count_text(damaged: list, cases_per_shape: int) -> str:
    """"2 damaged cases", "1 damaged shape (4 cases)", or both: the damage status found, in words."""
    cases = sum(d["case"] is not None for d in damaged)
    shapes = len(damaged) - cases
    parts = ([f"{cases} damaged case{'s' if cases != 1 else ''}"] if cases else []) + \
            ([f"{shapes} damaged shape{'s' if shapes != 1 else ''} ({shapes * cases_per_shape} cases)"] if shapes else [])
    return " and ".join(parts)


def print_exported(shape: int, case: int, params: dict, out) -> None:
    """`export`: the case written and its parameters."""
    typer.echo(f"shape {shape}, case {case} (P={params['pressure_mmhg']:g} mmHg, C={params['stiffness_pa']:g} Pa, "
               f"θ={params['helix_endo_deg']:g}/{params['helix_epi_deg']:g}°) → {out}")
