"""Mesh convergence of unloading (inverse FE): each preset on a coarse and a default mesh of the same
ED shape and on their uniform refinements. Every answer is compared node for node, at the base
mesh's vertices, with the finest `accurate` answer on the same polyhedral domain (uniform refinement
keeps the domain and the vertices), so the figures are discretisation errors of one model: same law,
base condition and fibre rule. From three levels of one preset come its observed order p and a
Richardson estimate of the finest answer's own error, d_top / (2^p − 1), d_top being the mean nodal
difference between its two finest levels. No Ray, Zarr or torch here; `heartctl bench convergence`
prints and writes the report."""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from solver.fidelity import Fidelity, get_fidelity
from solver.forward import SolveError
from solver.lv import displacement_at_dofs, inverse_solve, refined_unloaded
from solver.meshing import mesh_lv
from solver.mesh import TetMesh
from solver.parameters import CaseParameters
from solver.refine import refine_uniform
from solver.shape_model import MODES, LVShape, extreme_shapes, shape_from_coefficients
from solver.version import solver_digest

CASES = {"mid": CaseParameters(8.0, 150.0, 60.0, -60.0),   # the middle of the paper's box
         "hard": CaseParameters(14.0, 50.0, 60.0, -60.0)}  # its hardest corner: highest load, softest wall
APEX_FRACTION = 0.3  # apical region: the lowest 30 % of the height
BASE_FRACTION = 0.4  # basal region: the top 40 %


def convergence_shape(name: str) -> LVShape:
    """"mean" (every mode 0), "minus2" (every mode −2 SD: small, spherical, thin) or "plus2" (+2 SD)."""
    if name == "mean":
        return shape_from_coefficients(np.zeros(len(MODES)), 0)
    if name == "minus2":
        return extreme_shapes()[0]
    if name == "plus2":
        return extreme_shapes()[1]
    raise ValueError(f"unknown convergence shape {name!r}; choose mean, minus2 or plus2")


@dataclass(frozen=True)
class Hierarchy:
    """A gmsh mesh of about `target_nodes` nodes and its `levels` uniform refinements."""

    target_nodes: int
    levels: int

    @property
    def name(self) -> str:
        return f"{self.target_nodes}-node"


def parse_hierarchies(text: str) -> tuple[Hierarchy, ...]:
    """"150:2,800:1" → meshes of ~150 nodes refined twice and ~800 refined once."""
    out = []
    for item in text.split(","):
        try:
            nodes, levels = (int(v) for v in item.split(":"))
        except ValueError:
            raise ValueError(f"`meshes` takes NODES:LEVELS items separated by commas, got {item!r}") from None
        out.append(Hierarchy(nodes, levels))
    return tuple(out)


def parse_quad_degrees(text: str) -> tuple[int, ...]:
    """"2,4,5,7" → (2, 4, 5, 7); "" → () (no quadrature study)."""
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"quadrature degrees are integers separated by commas, got {text!r}") from None


@dataclass(frozen=True)
class ConvergenceSpec:
    shapes: tuple[str, ...] = ("mean", "minus2", "plus2")
    cases: tuple[str, ...] = ("mid", "hard")
    # the 150-node mesh refined twice gives observed orders; 350 and 800 nodes are the sizes of the
    # training meshes and of the meshes users bring
    hierarchies: tuple[Hierarchy, ...] = (Hierarchy(150, 2), Hierarchy(350, 1), Hierarchy(800, 1))
    presets: tuple[str, ...] = ("fast", "accurate")
    base: str = "sliding"
    fibres: str = "laplace"
    # cell quadrature degrees of the quadrature study (each preset on levels 0 and 1 of every mesh);
    # empty: no study. Each preset's own degree joins the list, and one more row per level raises the
    # facet degree to the list's highest.
    quad_degrees: tuple[int, ...] = (2, 4, 5, 7)

    def validate(self) -> "ConvergenceSpec":
        for name in self.shapes:
            convergence_shape(name)
        for case in self.cases:
            if case not in CASES:
                raise ValueError(f"unknown case {case!r}; choose {' or '.join(CASES)}")
        if "accurate" not in self.presets:
            raise ValueError("the reference is the accurate preset's finest answer: presets must include accurate")
        for h in self.hierarchies:
            if h.levels < 1 or h.target_nodes < 50:
                raise ValueError(f"hierarchy {h.name}: needs ≥ 1 refinement level and ≥ 50 nodes")
        for q in self.quad_degrees:
            if not 1 <= q <= 8:
                raise ValueError(f"quadrature degree {q}: the tetrahedron rules go from 1 to 8")
        return self


@dataclass
class LevelSolve:
    """One unloading: `unloaded` [n0, 3] mm at the base mesh's vertices; wall time of the inverse."""

    level: int
    nodes: int
    wall_s: float
    updates: int
    newton: int
    unloaded: np.ndarray = field(repr=False)
    failed: str = ""
    warm: bool = False  # started from the level below's answer (the reference solves), not cold
    displacement: np.ndarray | None = field(repr=False, default=None)  # [dofs, 3] u = x − X of the solve's element


def unload_at_level(ed_mesh: TetMesh, params: CaseParameters, preset: str | Fidelity, level: int,
                    base: str = "sliding", fibres: str = "laplace", below: LevelSolve | None = None) -> LevelSolve:
    """Inverse FE on `ed_mesh` refined `level` times: cold, as `heartctl unload --method fe`, or, given
    the same preset's answer one level `below`, started from it interpolated onto this level's nodes
    (the same tolerance, fewer updates: used for the finest, most expensive solves)."""
    mesh = refine_uniform(ed_mesh, level)
    n0 = ed_mesh.n_nodes
    t0 = time.perf_counter()
    guess = None
    if below is not None and below.displacement is not None and not below.failed:
        mesh_below = refine_uniform(ed_mesh, level - 1)
        guess = refined_unloaded(mesh_below, mesh_below.nodes - below.displacement[: mesh_below.n_nodes],
                                 below.displacement)
    try:
        result = inverse_solve(mesh, params, preset, base, initial_unloaded=guess, fibres=fibres)
    except SolveError as exc:
        return LevelSolve(level, mesh.n_nodes, time.perf_counter() - t0, 0, 0, np.full((n0, 3), np.nan), str(exc),
                          guess is not None)
    return LevelSolve(level, mesh.n_nodes, time.perf_counter() - t0, result.updates,
                      result.stats.newton_iterations, result.unloaded_nodes[:n0].copy(), "", guess is not None,
                      displacement_at_dofs(result))


def nodal_error(answer: np.ndarray, reference: np.ndarray, ed_nodes: np.ndarray) -> dict:
    """Nodal distance |answer − reference| (mm): mean, 95th percentile, max, and the means over the
    apical (lowest APEX_FRACTION of the height) and basal (top BASE_FRACTION) regions of the ED mesh."""
    e = np.linalg.norm(answer - reference, axis=1)
    z = ed_nodes[:, 2]
    depth = (z.max() - z) / max(float(np.ptp(z)), 1e-300)  # 0 at the base, 1 at the apex
    return {"mean_mm": float(e.mean()), "p95_mm": float(np.percentile(e, 95)), "max_mm": float(e.max()),
            "apex_mean_mm": float(e[depth > 1.0 - APEX_FRACTION].mean()),
            "base_mean_mm": float(e[depth < BASE_FRACTION].mean())}


def observed_order(coarse_diff: float, fine_diff: float) -> float:
    """p = log2(d(h, h/2) / d(h/2, h/4)); nan when either difference is not positive."""
    if not (coarse_diff > 0 and fine_diff > 0):
        return float("nan")
    return math.log2(coarse_diff / fine_diff)


def richardson_error(top_diff: float, order: float) -> float:
    """Estimated error of the finest answer, d_top / (2^p − 1); nan without a positive order."""
    if not (order > 0 and math.isfinite(order)):
        return float("nan")
    return top_diff / (2.0 ** order - 1.0)


class SolveCache:
    """Unloaded answers kept as .npz files in a folder, keyed by the solver's source digest and the
    run's inputs, so an interrupted benchmark resumes and a changed solver recomputes."""

    def __init__(self, folder: Path | None):
        self.folder = folder
        self.digest = solver_digest()
        if folder is not None:
            folder.mkdir(parents=True, exist_ok=True)

    def _path(self, key: str) -> Path:
        return self.folder / f"{self.digest}_{key}.npz"

    def get(self, key: str) -> LevelSolve | None:
        if self.folder is None or not self._path(key).exists():
            return None
        with np.load(self._path(key)) as z:
            return LevelSolve(int(z["level"]), int(z["nodes"]), float(z["wall_s"]), int(z["updates"]),
                              int(z["newton"]), z["unloaded"], str(z["failed"]), bool(z["warm"]), z["displacement"])

    def put(self, key: str, s: LevelSolve) -> None:
        if self.folder is None:
            return
        tmp = self._path(key).with_suffix(".tmp.npz")
        u = np.full_like(s.unloaded, np.nan) if s.displacement is None else s.displacement
        np.savez(tmp, level=s.level, nodes=s.nodes, wall_s=s.wall_s, updates=s.updates, newton=s.newton,
                 unloaded=s.unloaded, failed=s.failed, warm=s.warm, displacement=u)
        tmp.replace(self._path(key))


def run_convergence(spec: ConvergenceSpec, cache_dir: Path | None = None, progress=None) -> dict:
    """Every (shape, case, hierarchy, preset, level) unloaded and scored. Returns {"rows": per
    solve, "orders": per (shape, case, hierarchy, preset): the differences of its levels, the
    observed order (≥ 3 levels) and its finest level's estimated error; the accurate entries give
    the reference's own error, "quadrature": per preset, quadrature variant and level (levels 0 and
    1) its quadrature error and its error against the reference (`_quadrature_rows`)}."""
    spec.validate()
    cache = SolveCache(cache_dir)
    rows, orders, quadrature = [], [], []
    order_of = {}  # (shape, case, preset) → observed mean order, from the deepest hierarchy
    for shape_name in spec.shapes:
        shape = convergence_shape(shape_name)
        for hierarchy in sorted(spec.hierarchies, key=lambda h: -h.levels):
            ed = mesh_lv(shape, hierarchy.target_nodes)
            for case in spec.cases:
                params = CASES[case]
                solves: dict[str, list[LevelSolve]] = {}
                for preset in spec.presets:
                    solves[preset] = []
                    for level in range(hierarchy.levels + 1):
                        key = (f"{shape_name}_{case}_{hierarchy.name}{ed.n_nodes}_{preset}_L{level}_"
                               f"{spec.base}_{spec.fibres}")
                        s = cache.get(key)
                        if s is None:
                            top = preset == "accurate" and level == hierarchy.levels
                            below = solves[preset][-1] if top else None
                            s = unload_at_level(ed, params, preset, level, spec.base, spec.fibres, below)
                            cache.put(key, s)
                        solves[preset].append(s)
                        if progress:
                            progress(f"{shape_name:>6} {case:>4} {hierarchy.name:>9} {preset:>8} level {level}: "
                                     f"{s.nodes:>6} nodes, {s.wall_s:7.1f} s" + (f", FAILED {s.failed}" if s.failed else ""))
                reference = solves["accurate"][-1]
                for preset, levels in solves.items():
                    for s in levels:
                        err = nodal_error(s.unloaded, reference.unloaded, ed.nodes)
                        rows.append({"shape": shape_name, "case": case, "hierarchy": hierarchy.name,
                                     "preset": preset, "level": s.level, "nodes": s.nodes, "wall_s": s.wall_s,
                                     "updates": s.updates, "newton": s.newton, "failed": s.failed, "warm": s.warm,
                                     "is_reference": s is reference, **err})
                    diffs = [nodal_error(a.unloaded, b.unloaded, ed.nodes) for a, b in zip(levels[:-1], levels[1:])]
                    entry = {"shape": shape_name, "case": case, "hierarchy": hierarchy.name, "preset": preset,
                             "level_diffs_mean_mm": [d["mean_mm"] for d in diffs],
                             "level_diffs_max_mm": [d["max_mm"] for d in diffs]}
                    if len(diffs) >= 2:
                        entry["order_mean"] = observed_order(diffs[-2]["mean_mm"], diffs[-1]["mean_mm"])
                        entry["order_max"] = observed_order(diffs[-2]["max_mm"], diffs[-1]["max_mm"])
                        order_of.setdefault((shape_name, case, preset), entry["order_mean"])
                    else:
                        entry["order_mean"] = entry["order_max"] = float("nan")
                    p = order_of.get((shape_name, case, preset), float("nan"))
                    entry["order_used"] = p
                    entry["finest_error_mean_mm"] = richardson_error(diffs[-1]["mean_mm"], p)
                    entry["finest_error_max_mm"] = richardson_error(diffs[-1]["max_mm"], p)
                    orders.append(entry)
                if spec.quad_degrees:
                    quadrature += _quadrature_rows(spec, cache, shape_name, case, hierarchy, ed, solves, progress)
    return {"spec": _spec_dict(spec), "solver": cache.digest, "rows": rows, "orders": orders,
            "quadrature": quadrature}


@dataclass(frozen=True)
class QuadratureVariant:
    """A preset with its cell (and facet) quadrature degree replaced."""

    preset: str
    quad_degree: int
    facet_quad_degree: int

    @property
    def fidelity(self) -> Fidelity:
        return replace(get_fidelity(self.preset), quad_degree=self.quad_degree,
                       facet_quad_degree=self.facet_quad_degree)

    @property
    def is_preset(self) -> bool:
        fid = get_fidelity(self.preset)
        return (fid.quad_degree, fid.facet_quad_degree) == (self.quad_degree, self.facet_quad_degree)

    @property
    def name(self) -> str:
        return f"{self.preset}-q{self.quad_degree}f{self.facet_quad_degree}"


def quadrature_variants(preset: str, quad_degrees: tuple[int, ...]) -> list[QuadratureVariant]:
    """The preset at each cell degree of `quad_degrees` and its own (its facet degree kept), then
    its own cell degree with the facet degree raised to the highest listed; the last cell-degree
    variant (the highest) is the quadrature-converged answer the others are scored against."""
    fid = get_fidelity(preset)
    cells = sorted(set(quad_degrees) | {fid.quad_degree})
    out = [QuadratureVariant(preset, q, fid.facet_quad_degree) for q in cells]
    top_facet = max(max(quad_degrees), fid.facet_quad_degree)
    if top_facet != fid.facet_quad_degree:
        out.insert(0, QuadratureVariant(preset, fid.quad_degree, top_facet))
    return out


def _quadrature_rows(spec: ConvergenceSpec, cache: SolveCache, shape_name: str, case: str, hierarchy: Hierarchy,
                     ed: TetMesh, solves: dict[str, list[LevelSolve]], progress) -> list[dict]:
    """Each preset at each quadrature variant on levels 0 and 1 of one mesh. Per answer: its
    difference from the highest cell degree on the same mesh (the quadrature error alone) and from
    the convergence reference (the finest level of `accurate`: the error against an answer
    converged in h and, at the degree chosen for `accurate`, in quadrature). Level-1 variants start
    from the preset's own level-0 answer (†)."""
    params = CASES[case]
    reference = solves["accurate"][-1]
    rows = []
    for preset in spec.presets:
        variants = quadrature_variants(preset, spec.quad_degrees)
        for level in range(min(hierarchy.levels, 1) + 1):
            answers = {}
            for v in variants:
                if v.is_preset:
                    answers[v] = solves[preset][level]
                    continue
                key = (f"{shape_name}_{case}_{hierarchy.name}{ed.n_nodes}_{v.name}_L{level}_"
                       f"{spec.base}_{spec.fibres}")
                s = cache.get(key)
                if s is None:
                    below = solves[preset][0] if level else None
                    s = unload_at_level(ed, params, v.fidelity, level, spec.base, spec.fibres, below)
                    cache.put(key, s)
                    if progress:
                        progress(f"{shape_name:>6} {case:>4} {hierarchy.name:>9} {v.name:>14} level {level}: "
                                 f"{s.nodes:>6} nodes, {s.wall_s:7.1f} s" + (f", FAILED {s.failed}" if s.failed else ""))
                answers[v] = s
            top = answers[max((v for v in variants if v.facet_quad_degree == get_fidelity(preset).facet_quad_degree),
                              key=lambda v: v.quad_degree)]
            for v, s in answers.items():
                row = {"shape": shape_name, "case": case, "hierarchy": hierarchy.name, "preset": preset,
                       "quad_degree": v.quad_degree, "facet_quad_degree": v.facet_quad_degree,
                       "is_preset": v.is_preset, "level": level, "nodes": s.nodes, "wall_s": s.wall_s,
                       "warm": s.warm, "failed": s.failed or top.failed}
                if not row["failed"]:
                    row["quadrature"] = nodal_error(s.unloaded, top.unloaded, ed.nodes)
                    row["converged"] = (None if s is reference
                                        else nodal_error(s.unloaded, reference.unloaded, ed.nodes))
                rows.append(row)
    return rows


def _spec_dict(spec: ConvergenceSpec) -> dict:
    d = asdict(spec)
    d["hierarchies"] = [asdict(h) for h in spec.hierarchies]
    return d


def _fmt(x: float, digits: int = 3) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def markdown_report(result: dict, header: str = "") -> str:
    """The report as Markdown: errors against the reference, observed orders, the reference's own error."""
    lines = [header] if header else []
    lines += ["## Nodal error of the unloaded geometry against the finest accurate answer (mm)", "",
              "Reference: `accurate` on the hierarchy's finest mesh, same polyhedral domain, compared at the "
              "base mesh's vertices. Time: one inverse solve from the ED geometry (what unloading by inverse FE does); the "
              "references (†) start from the level below's answer.", "",
              "| shape | case | mesh | preset | level | nodes | time s | mean | p95 | max | apex mean | base mean |",
              "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in result["rows"]:
        if r["failed"]:
            lines.append(f"| {r['shape']} | {r['case']} | {r['hierarchy']} | {r['preset']} | {r['level']} | "
                         f"{r['nodes']} | {r['wall_s']:.1f} | failed: {r['failed']} | | | | |")
            continue
        vals = ("reference", "", "", "", "") if r["is_reference"] else tuple(
            _fmt(r[k]) for k in ("mean_mm", "p95_mm", "max_mm", "apex_mean_mm", "base_mean_mm"))
        lines.append(f"| {r['shape']} | {r['case']} | {r['hierarchy']} | {r['preset']} | {r['level']} | {r['nodes']} | "
                     f"{r['wall_s']:.1f}{' †' if r['warm'] else ''} | " + " | ".join(vals) + " |")
    lines += ["", "## Observed order and the finest answer's estimated own error", "",
              "p = log2(d(h, h/2) / d(h/2, h/4)) from the mean (and max) nodal differences of consecutive levels; "
              "the finest answer's error ≈ d_top / (2^p − 1) (mesh hierarchies with two levels use the order of "
              "the same shape, case and preset on the deeper hierarchy).", "",
              "| shape | case | mesh | preset | differences of levels, mean (max) mm | p (mean) | p (max) | finest error, mean (max) mm |",
              "| --- | --- | --- | --- | --- | ---: | ---: | --- |"]
    for o in result["orders"]:
        diffs = ", ".join(f"{a:.3f} ({b:.3f})" for a, b in zip(o["level_diffs_mean_mm"], o["level_diffs_max_mm"]))
        lines.append(f"| {o['shape']} | {o['case']} | {o['hierarchy']} | {o['preset']} | {diffs} | "
                     f"{_fmt(o['order_mean'], 2)} | {_fmt(o['order_max'], 2)} | "
                     f"{_fmt(o['finest_error_mean_mm'], 4)} ({_fmt(o['finest_error_max_mm'], 4)}) |")
    if result.get("quadrature"):
        lines += ["", *quadrature_markdown(result["quadrature"])]
    return "\n".join(lines) + "\n"


def quadrature_markdown(rows: list[dict]) -> list[str]:
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
        qf = f"{r['quad_degree']} / {r['facet_quad_degree']}"
        qf = f"**{qf}**" if r["is_preset"] else qf
        head = (f"| {r['shape']} | {r['case']} | {r['hierarchy']} | {r['preset']} | {qf} | {r['level']} | "
                f"{r['nodes']} | {r['wall_s']:.1f}{' †' if r['warm'] else ''} | ")
        if r["failed"]:
            lines.append(head + f"failed: {r['failed']} | | | |")
            continue
        q, c = r["quadrature"], r["converged"]
        conv = ("reference", "") if c is None else (f"{_fmt(c['mean_mm'], 4)} ({_fmt(c['max_mm'], 3)})",
                                                    _fmt(c["apex_mean_mm"], 4))
        lines.append(head + f"{_fmt(q['mean_mm'], 4)} ({_fmt(q['max_mm'], 4)}) | {_fmt(q['apex_mean_mm'], 4)} | "
                     f"{conv[0]} | {conv[1]} |")
    return lines


def plot_report(result: dict, path: Path) -> None:
    """Log-log PNG: mean nodal error against the reference vs time per case, one panel per case;
    colour = preset, marker = mesh, line style = shape, the points of a line = refinement levels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    cases = list(dict.fromkeys(r["case"] for r in result["rows"]))
    fig, axes = plt.subplots(1, len(cases), figsize=(5.6 * len(cases) + 2.2, 4.6), squeeze=False)
    colours = {"fast": "tab:orange", "accurate": "tab:blue"}
    names = list(dict.fromkeys(r["hierarchy"] for r in result["rows"]))
    markers = dict(zip(names, "os^Dv<>"))
    shapes = list(dict.fromkeys(r["shape"] for r in result["rows"]))
    styles = dict(zip(shapes, ("-", "--", ":", "-.")))
    for ax, case in zip(axes[0], cases):
        groups: dict[tuple, list] = {}
        for r in result["rows"]:
            if r["case"] == case and not r["is_reference"] and not r["failed"]:
                groups.setdefault((r["shape"], r["hierarchy"], r["preset"]), []).append(r)
        for (shape, hier, preset), rs in groups.items():
            rs = sorted(rs, key=lambda r: r["level"])
            ax.plot([r["wall_s"] for r in rs], [r["mean_mm"] for r in rs], styles.get(shape, "-"),
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


def write_report(result: dict, out_dir: Path, header: str = "") -> dict:
    """convergence.md, convergence.png and convergence.json in out_dir; returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"markdown": out_dir / "convergence.md", "plot": out_dir / "convergence.png",
             "json": out_dir / "convergence.json"}
    paths["markdown"].write_text(markdown_report(result, header))
    plot_report(result, paths["plot"])
    paths["json"].write_text(json.dumps(result, indent=1, default=float))
    return paths
