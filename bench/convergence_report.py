"""`bench convergence`'s report: convergence.md (errors against the reference, observed orders, the
quadrature study), convergence.png (error against time per case) and convergence.json."""
from __future__ import annotations

import json
import math
from pathlib import Path

from bench.convergence import APEX_FRACTION, CASES, ConvergenceResult, QuadratureRow


def _fmt(x: float, digits: int = 3) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def markdown_report(result: ConvergenceResult, header: str = "") -> str:
    """The report as Markdown: errors against the reference, observed orders, the reference's own error."""
    lines = [header] if header else []
    lines += ["## Nodal error of the unloaded geometry against the finest accurate answer (mm)", "",
              "Reference: `accurate` on the hierarchy's finest mesh, same polyhedral domain, compared at the "
              "base mesh's vertices. Time: one inverse solve from the ED geometry (what unloading by inverse FE does); the "
              "references (†) start from the level below's answer.", "",
              "| shape | case | mesh | preset | level | nodes | time s | mean | p95 | max | apex mean | base mean |",
              "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in result.rows:
        head = f"| {r.shape} | {r.case} | {r.hierarchy} | {r.preset} | {r.level} | {r.nodes} | {r.wall_s:.1f}"
        if r.failed:
            lines.append(f"{head} | failed: {r.failed} | | | | |")
            continue
        vals = ("reference", "", "", "", "") if r.is_reference else tuple(
            _fmt(r.error[k]) for k in ("mean_mm", "p95_mm", "max_mm", "apex_mean_mm", "base_mean_mm"))
        lines.append(f"{head}{' †' if r.warm else ''} | " + " | ".join(vals) + " |")
    lines += ["", "## Observed order and the finest answer's estimated own error", "",
              "p = log2(d(h, h/2) / d(h/2, h/4)) from the mean (and max) nodal differences of consecutive levels; "
              "the finest answer's error ≈ d_top / (2^p − 1) (mesh hierarchies with two levels use the order of "
              "the same shape, case and preset on the deeper hierarchy).", "",
              "| shape | case | mesh | preset | differences of levels, mean (max) mm | p (mean) | p (max) | finest error, mean (max) mm |",
              "| --- | --- | --- | --- | --- | ---: | ---: | --- |"]
    for o in result.orders:
        diffs = ", ".join(f"{a:.3f} ({b:.3f})" for a, b in zip(o.level_diffs_mean_mm, o.level_diffs_max_mm))
        lines.append(f"| {o.shape} | {o.case} | {o.hierarchy} | {o.preset} | {diffs} | "
                     f"{_fmt(o.order_mean, 2)} | {_fmt(o.order_max, 2)} | "
                     f"{_fmt(o.finest_error_mean_mm, 4)} ({_fmt(o.finest_error_max_mm, 4)}) |")
    if result.quadrature:
        lines += ["", *quadrature_markdown(result.quadrature)]
    return "\n".join(lines) + "\n"


def quadrature_markdown(rows: list[QuadratureRow]) -> list[str]:
    """The quadrature study as Markdown lines: per preset, degree and level, the quadrature error
    (against the highest cell degree on the same mesh) and the error against the converged answer."""
    lines = ["## Convergence in quadrature", "",
             "Each preset with its cell (q) and facet (f) quadrature degrees changed, on a mesh (level 0) and its "
             "uniform refinement (level 1). *Quadrature error*: against the same preset, mesh and level at the "
             "highest cell degree. *Against converged*: against the reference above (the finest `accurate` "
             "answer). Mean (max) nodal distance of the unloaded geometry, mm; apex: the lowest "
             f"{APEX_FRACTION:.0%} of the height. Preset's own degrees in bold; † started from level 0's answer.", "",
             "| shape | case | mesh | preset | q / f | level | nodes | time s | quadrature error | apex | against converged | apex |",
             "| --- | --- | --- | --- | --- | ---: | ---: | ---: | --- | ---: | --- | ---: |"]
    for r in rows:
        qf = f"{r.quad_degree} / {r.facet_quad_degree}"
        qf = f"**{qf}**" if r.is_preset else qf
        head = (f"| {r.shape} | {r.case} | {r.hierarchy} | {r.preset} | {qf} | {r.level} | "
                f"{r.nodes} | {r.wall_s:.1f}{' †' if r.warm else ''} | ")
        if r.failed:
            lines.append(head + f"failed: {r.failed} | | | |")
            continue
        q, c = r.quadrature, r.converged
        conv = ("reference", "") if c is None else (f"{_fmt(c['mean_mm'], 4)} ({_fmt(c['max_mm'], 3)})",
                                                    _fmt(c["apex_mean_mm"], 4))
        lines.append(head + f"{_fmt(q['mean_mm'], 4)} ({_fmt(q['max_mm'], 4)}) | {_fmt(q['apex_mean_mm'], 4)} | "
                     f"{conv[0]} | {conv[1]} |")
    return lines


def plot_report(result: ConvergenceResult, path: Path) -> None:
    """Log-log PNG: mean nodal error against the reference vs time per case, one panel per case;
    colour = preset, marker = mesh, line style = shape, the points of a line = refinement levels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    cases = list(dict.fromkeys(r.case for r in result.rows))
    fig, axes = plt.subplots(1, len(cases), figsize=(5.6 * len(cases) + 2.2, 4.6), squeeze=False)
    colours = {"fast": "tab:orange", "accurate": "tab:blue"}
    names = list(dict.fromkeys(r.hierarchy for r in result.rows))
    markers = dict(zip(names, "os^Dv<>"))
    shapes = list(dict.fromkeys(r.shape for r in result.rows))
    styles = dict(zip(shapes, ("-", "--", ":", "-.")))
    for ax, case in zip(axes[0], cases):
        groups: dict[tuple, list] = {}
        for r in result.rows:
            if r.case == case and not r.is_reference and not r.failed:
                groups.setdefault((r.shape, r.hierarchy, r.preset), []).append(r)
        for (shape, hier, preset), rs in groups.items():
            rs = sorted(rs, key=lambda r: r.level)
            ax.plot([r.wall_s for r in rs], [r.error["mean_mm"] for r in rs], styles.get(shape, "-"),
                    marker=markers.get(hier, "^"), color=colours.get(preset, "k"), alpha=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        params = CASES[case]
        ax.set_title(f"{case}: P {params.pressure_mmhg:g} mmHg, C {params.stiffness_pa:g} Pa")
        ax.set_xlabel("time per case, s (one inverse solve, one thread)")
        ax.set_ylabel("mean nodal error vs converged, mm")
        ax.grid(True, which="both", alpha=0.3)
    handles = ([Line2D([], [], color=c, lw=2, label=p) for p, c in colours.items()]
               + [Line2D([], [], color="grey", ls="", marker=markers[h], label=f"{h} mesh") for h in names]
               + [Line2D([], [], color="grey", ls=styles[s], label=f"{s} shape") for s in shapes])
    fig.legend(handles=handles, loc="center right", fontsize=8, title="points: refinement levels", title_fontsize=8)
    fig.tight_layout(rect=(0, 0, 1 - 2.0 / fig.get_figwidth(), 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(result: ConvergenceResult, out_dir: Path, header: str = "") -> dict:
    """convergence.md, convergence.png and convergence.json in out_dir; returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"markdown": out_dir / "convergence.md", "plot": out_dir / "convergence.png",
             "json": out_dir / "convergence.json"}
    paths["markdown"].write_text(markdown_report(result, header))
    plot_report(result, paths["plot"])
    paths["json"].write_text(json.dumps(result.as_dict(), indent=1, default=float))
    return paths
