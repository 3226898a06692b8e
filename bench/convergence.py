"""Mesh convergence of unloading (inverse FE): each preset on a coarse and a default mesh of the same
ED shape and on their uniform refinements. Every answer is compared node for node, at the base
mesh's vertices, with the finest `accurate` answer on the same polyhedral domain (uniform refinement
keeps the domain and the vertices), so the figures are discretisation errors of one model: same law,
base condition and fibre rule. From three levels of one preset come its observed order p and a
Richardson estimate of the finest answer's own error, d_top / (2^p − 1), d_top being the mean nodal
difference between its two finest levels. No Ray, Zarr or torch here; `heartctl bench convergence`
prints and writes the report."""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from solver.fidelity import Fidelity, get_fidelity
from solver.forward import SolveError
from solver.lv import displacement_at_dofs, inverse_solve
from solver.refine import refined_unloaded
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


@dataclass(frozen=True, kw_only=True)
class LevelRow:
    """One unloading of the study scored against the reference: shape, case, mesh hierarchy, preset,
    refinement level, nodes, time (s), inverse updates, Newton iterations, why it failed (empty: it did
    not), whether it started from the level below (`warm`), whether it is the reference itself, and
    `nodal_error`'s figures against the reference (mm)."""

    shape: str
    case: str
    hierarchy: str
    preset: str
    level: int
    nodes: int
    wall_s: float
    updates: int
    newton: int
    failed: str
    warm: bool
    is_reference: bool
    error: dict

    def as_dict(self) -> dict:
        d = asdict(self)
        error = d.pop("error")
        return {**d, **error}


@dataclass(frozen=True, kw_only=True)
class ConvergenceOrder:
    """One preset's levels on one hierarchy: the mean and max nodal differences of consecutive levels
    (mm), the observed orders from the last three levels (nan with two), the order used for the estimate
    (the deepest hierarchy's for the same shape, case and preset), and the finest level's estimated own
    error, mean and max (mm)."""

    shape: str
    case: str
    hierarchy: str
    preset: str
    level_diffs_mean_mm: list[float]
    level_diffs_max_mm: list[float]
    order_mean: float
    order_max: float
    order_used: float
    finest_error_mean_mm: float
    finest_error_max_mm: float

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True, kw_only=True)
class QuadratureRow:
    """One preset at one quadrature variant (cell / facet degree; `is_preset`: its own) on level 0 or 1 of
    a mesh: nodes, time (s), `warm`, why it (or the highest-degree answer it is compared with) failed,
    its `nodal_error` against the highest cell degree on the same mesh (`quadrature`) and against the
    study's reference (`converged`, None for the reference itself); both None when it failed."""

    shape: str
    case: str
    hierarchy: str
    preset: str
    quad_degree: int
    facet_quad_degree: int
    is_preset: bool
    level: int
    nodes: int
    wall_s: float
    warm: bool
    failed: str
    quadrature: dict | None = None
    converged: dict | None = None

    def as_dict(self) -> dict:
        d = asdict(self)
        if self.failed:
            del d["quadrature"], d["converged"]
        return d


@dataclass(frozen=True, kw_only=True)
class ConvergenceResult:
    """`bench convergence`'s result: the spec (ConvergenceSpec's fields), the solver digest, every scored
    unloading, every preset's orders, and the quadrature study's rows (empty without one)."""

    spec: dict
    solver: str
    rows: list[LevelRow]
    orders: list[ConvergenceOrder]
    quadrature: list[QuadratureRow]

    def as_dict(self) -> dict:
        return {"spec": self.spec, "solver": self.solver, "rows": [r.as_dict() for r in self.rows],
                "orders": [o.as_dict() for o in self.orders], "quadrature": [q.as_dict() for q in self.quadrature]}


def run_convergence(spec: ConvergenceSpec, cache_dir: Path | None = None, progress=None) -> ConvergenceResult:
    """Every (shape, case, hierarchy, preset, level) unloaded and scored: a LevelRow per solve, a
    ConvergenceOrder per (shape, case, hierarchy, preset) (the accurate ones give the reference's own
    error), and with a quadrature study a QuadratureRow per preset, variant and level 0 or 1
    (`_quadrature_rows`)."""
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
                        rows.append(LevelRow(shape=shape_name, case=case, hierarchy=hierarchy.name, preset=preset,
                                             level=s.level, nodes=s.nodes, wall_s=s.wall_s, updates=s.updates,
                                             newton=s.newton, failed=s.failed, warm=s.warm,
                                             is_reference=s is reference, error=err))
                    diffs = [nodal_error(a.unloaded, b.unloaded, ed.nodes) for a, b in zip(levels[:-1], levels[1:])]
                    order_mean = order_max = float("nan")
                    if len(diffs) >= 2:
                        order_mean = observed_order(diffs[-2]["mean_mm"], diffs[-1]["mean_mm"])
                        order_max = observed_order(diffs[-2]["max_mm"], diffs[-1]["max_mm"])
                        order_of.setdefault((shape_name, case, preset), order_mean)
                    p = order_of.get((shape_name, case, preset), float("nan"))
                    orders.append(ConvergenceOrder(
                        shape=shape_name, case=case, hierarchy=hierarchy.name, preset=preset,
                        level_diffs_mean_mm=[d["mean_mm"] for d in diffs], level_diffs_max_mm=[d["max_mm"] for d in diffs],
                        order_mean=order_mean, order_max=order_max, order_used=p,
                        finest_error_mean_mm=richardson_error(diffs[-1]["mean_mm"], p),
                        finest_error_max_mm=richardson_error(diffs[-1]["max_mm"], p)))
                if spec.quad_degrees:
                    quadrature += _quadrature_rows(spec, cache, shape_name, case, hierarchy, ed, solves, progress)
    return ConvergenceResult(spec=_spec_dict(spec), solver=cache.digest, rows=rows, orders=orders,
                             quadrature=quadrature)


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
                     ed: TetMesh, solves: dict[str, list[LevelSolve]], progress) -> list[QuadratureRow]:
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
                failed = s.failed or top.failed
                scored = {} if failed else dict(
                    quadrature=nodal_error(s.unloaded, top.unloaded, ed.nodes),
                    converged=None if s is reference else nodal_error(s.unloaded, reference.unloaded, ed.nodes))
                rows.append(QuadratureRow(shape=shape_name, case=case, hierarchy=hierarchy.name, preset=preset,
                                          quad_degree=v.quad_degree, facet_quad_degree=v.facet_quad_degree,
                                          is_preset=v.is_preset, level=level, nodes=s.nodes, wall_s=s.wall_s,
                                          warm=s.warm, failed=failed, **scored))
    return rows


def _spec_dict(spec: ConvergenceSpec) -> dict:
    d = asdict(spec)
    d["hierarchies"] = [asdict(h) for h in spec.hierarchies]
    return d
