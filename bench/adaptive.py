"""How well adaptive unloading works: the error indicator's ranking of the true local error, and the
adaptive answer's error and cost against the converged solution.

Per shape and case, on one gmsh mesh: `accurate` on the mesh (the adaptive loop's first solve) and
on its uniform refinement (`reference`, the converged answer here, started from accurate's answer as
the preset does); the adaptive unload at each tolerance. Scored at the ED mesh's vertices against the
reference; times are wall seconds of each whole unload (reference: its accurate start included).

Ranking: the true local error of tet K is ‖∇u_ref − ∇u_h‖ over K, with the reference's gradient
(on K's 8 children) and accurate's (K's own P2 field) compared at the children's quadrature points,
each on its own unloaded configuration. Reported: the Spearman rank correlation of η_K with it, and
the share of Σ(true error²) in the top 20 % of tets by η against the share in the true top 20 %."""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bench.convergence import CASES, convergence_shape, nodal_error
from solver.adaptive import adaptive_unload
from solver.elements import build_dofmap, cell_quadrature, simplex_shape, tet_geometry
from solver.error_indicator import INDICATOR_QUAD_DEGREE, gradient_indicator
from solver.local_refine import refine_marked
from solver.lv import displacement_at_dofs, inverse_solve
from solver.refine import refined_unloaded
from solver.meshing import mesh_lv
from solver.mesh import TetMesh
from solver.parameters import CaseParameters
from solver.version import solver_digest

TOP_SHARE = 0.2


@dataclass(frozen=True)
class AdaptiveSpec:
    """shapes: convergence shapes (mean | minus2 | plus2); cases: mid | hard; nodes: the gmsh mesh's
    size; tolerances: the adaptive loop's targets (p95, mm)."""

    shapes: tuple[str, ...] = ("mean",)
    cases: tuple[str, ...] = ("mid", "hard")
    nodes: int = 350
    tolerances: tuple[float, ...] = (0.05,)
    base: str = "sliding"
    fibres: str = "laplace"

    def validate(self) -> "AdaptiveSpec":
        for s in self.shapes:
            convergence_shape(s)
        unknown = [c for c in self.cases if c not in CASES]
        if unknown or not self.cases:
            raise ValueError(f"`cases` must be among {', '.join(CASES)}, got {', '.join(unknown) or 'none'}")
        if not 150 <= self.nodes <= 2000:
            raise ValueError(f"`nodes` must be 150–2000, got {self.nodes}")
        if not self.tolerances or not all(np.isfinite(t) and t > 0 for t in self.tolerances):
            raise ValueError("`tolerances` must be numbers > 0, mm")
        return self


def parse_tolerances(items: tuple[str, ...]) -> tuple[float, ...]:
    """Tolerances (mm) from their texts; a text that is no number > 0 raises ValueError naming it."""
    out = []
    for text in items:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"`tolerance` must be numbers > 0 (mm), got {text!r}")
        out.append(value)
    return tuple(out)


def true_local_error(ed_mesh: TetMesh, coarse_X: np.ndarray, coarse_u: np.ndarray, fine_mesh: TetMesh,
                     fine_X: np.ndarray, fine_u: np.ndarray, parent: np.ndarray, fine_ids: np.ndarray) -> np.ndarray:
    """‖∇u_fine − ∇u_coarse‖_{L²(K)} [n_tets] for each tet K of `ed_mesh`: the coarse P2 field (on the
    unloaded `coarse_X`) and the fine one (on `fine_X`, the mesh refined in full by `refine_marked`,
    `parent` and `fine_ids` its maps) at the fine tets' quadrature points, placed in K by barycentric
    coordinates (a child's vertex is a vertex or an edge midpoint of K)."""
    n = ed_mesh.n_nodes
    coarse_map = build_dofmap(ed_mesh.nodes, ed_mesh.tets, 2)
    edge_ends = coarse_map.edge_vertices
    # each fine vertex's barycentric coordinates in its child's parent tet
    parents = ed_mesh.tets[parent]  # [mf, 4]
    ids = fine_ids[fine_mesh.tets]  # [mf, 4] uniform numbering
    bary = np.zeros(fine_mesh.tets.shape + (4,))
    for corner in range(4):
        f = ids[:, corner]
        is_vertex = f < n
        ends = np.where(is_vertex[:, None], f[:, None], edge_ends[np.where(is_vertex, 0, f - n)])
        for end in range(2):
            bary[:, corner] += 0.5 * (parents == ends[:, end:end + 1])
    q = cell_quadrature(fine_X, fine_mesh.tets, 2, INDICATOR_QUAD_DEGREE)
    fine_map = build_dofmap(fine_X, fine_mesh.tets, 2)
    grad_fine = np.einsum("ebi,eqbj->eqij", fine_u[fine_map.cell_dofs], q.grads)
    lam_parent = np.einsum("eca,cq->eqa", bary, q.lam)  # [mf, nq, 4]
    _, g = tet_geometry(coarse_X, ed_mesh.tets)
    nq = lam_parent.shape[1]
    grad_coarse = np.empty_like(grad_fine)
    ue = coarse_u[coarse_map.cell_dofs][parent]  # [mf, 10, 3]
    for k in range(nq):
        _, dl = simplex_shape(2, lam_parent[:, k].T)  # [10, 4, mf]
        grads = np.einsum("blm,mlj->mbj", dl, g[parent])
        grad_coarse[:, k] = np.einsum("mbi,mbj->mij", ue, grads)
    diff2 = np.einsum("eqij,eqij,eq->e", grad_fine - grad_coarse, grad_fine - grad_coarse, q.dV)
    return np.sqrt(np.bincount(parent, weights=diff2, minlength=len(ed_mesh.tets)))


@dataclass(frozen=True, kw_only=True)
class IndicatorRanking:
    """How η ranks the true local error: Spearman, the share of Σ true² in η's top TOP_SHARE of tets, and
    the best possible share (the true top TOP_SHARE's)."""

    spearman: float
    top_share: float
    best_share: float


@dataclass(frozen=True, kw_only=True)
class ToleranceRun:
    """The adaptive unload at one tolerance (p95, mm): its error against the reference (`nodal_error`'s
    fields, mm), its time (s) and that time over the reference's, whether it met the tolerance, its own
    estimate of the p95 error and estimate / true, and each refinement step (AdaptiveStep's fields)."""

    tolerance_mm: float
    error: dict
    wall_s: float
    time_vs_reference: float
    met: bool
    estimate_p95_mm: float
    effectivity: float
    steps: list[dict]


@dataclass(frozen=True, kw_only=True)
class AdaptiveCase:
    """One shape × case: the mesh's nodes, the reference's nodes and time (s), the indicator's ranking,
    `accurate`'s error against the reference (mm) and time (s), and the adaptive unload at each tolerance."""

    shape: str
    case: str
    nodes: int
    reference_s: float
    reference_nodes: int
    ranking: IndicatorRanking
    accurate_error: dict
    accurate_s: float
    adaptive: list[ToleranceRun]

    def as_dict(self) -> dict:
        """adaptive.json's row layout: the errors flattened beside their times."""
        return {"shape": self.shape, "case": self.case, "nodes": self.nodes, "reference_s": self.reference_s,
                "reference_nodes": self.reference_nodes, "ranking": asdict(self.ranking),
                "accurate": {**self.accurate_error, "wall_s": self.accurate_s},
                "adaptive": [{"tolerance_mm": a.tolerance_mm, **a.error, "wall_s": a.wall_s,
                              "time_vs_reference": a.time_vs_reference, "met": a.met,
                              "estimate_p95_mm": a.estimate_p95_mm, "effectivity": a.effectivity, "steps": a.steps}
                             for a in self.adaptive]}


@dataclass(frozen=True, kw_only=True)
class AdaptiveBenchResult:
    """`bench adaptive`'s result: the spec (AdaptiveSpec's fields), the solver digest, every case."""

    spec: dict
    solver: str
    rows: list[AdaptiveCase]

    def as_dict(self) -> dict:
        return {"spec": self.spec, "solver": self.solver, "rows": [r.as_dict() for r in self.rows]}


def ranking(indicator: np.ndarray, true: np.ndarray) -> IndicatorRanking:
    """Spearman correlation of η with the true local error, and the share of Σ true² in η's top
    TOP_SHARE of tets against the best possible share (the true top TOP_SHARE's)."""
    from scipy.stats import spearmanr

    k = max(1, int(round(TOP_SHARE * len(true))))
    total = float((true ** 2).sum())
    return IndicatorRanking(spearman=float(spearmanr(indicator, true).statistic),
                            top_share=float((true[np.argsort(-indicator)[:k]] ** 2).sum() / total),
                            best_share=float((np.sort(true)[::-1][:k] ** 2).sum() / total))


def _case(spec: AdaptiveSpec, shape: str, case: str, progress=None) -> AdaptiveCase:
    ed = mesh_lv(convergence_shape(shape), spec.nodes)
    params: CaseParameters = CASES[case]
    say = progress or (lambda text: None)
    say(f"  {shape} {case}: {ed.n_nodes} nodes, accurate …")
    t0 = time.perf_counter()
    accurate = inverse_solve(ed, params, "accurate", spec.base, fibres=spec.fibres)
    accurate_s = time.perf_counter() - t0
    say(f"  {shape} {case}: reference …")
    t0 = time.perf_counter()
    coarse = inverse_solve(ed, params, "accurate", spec.base, tol_mm=1e-2, fibres=spec.fibres)  # as `reference` starts
    whole = refine_marked(ed, np.ones(len(ed.tets), dtype=bool))
    start = refined_unloaded(ed, coarse.unloaded_nodes, displacement_at_dofs(coarse))[whole.fine_ids]
    fine = inverse_solve(whole.mesh, params, "accurate", spec.base, initial_unloaded=start, fibres=spec.fibres)
    reference_s = time.perf_counter() - t0
    reference = fine.unloaded_nodes[: ed.n_nodes]
    eta = gradient_indicator(accurate.unloaded_nodes, ed.tets, displacement_at_dofs(accurate))
    true = true_local_error(ed, accurate.unloaded_nodes, displacement_at_dofs(accurate), whole.mesh,
                            fine.unloaded_nodes, displacement_at_dofs(fine), whole.parent, whole.fine_ids)
    runs = []
    for tol in spec.tolerances:
        say(f"  {shape} {case}: adaptive to {tol:g} mm …")
        t0 = time.perf_counter()
        result = adaptive_unload(ed, params, tol, spec.base, spec.fibres)
        wall = time.perf_counter() - t0
        err = nodal_error(result.unloaded_nodes, reference, ed.nodes)
        estimate = result.steps[-1].estimate_p95_mm
        runs.append(ToleranceRun(tolerance_mm=tol, error=err, wall_s=wall, time_vs_reference=wall / reference_s,
                                 met=result.met, estimate_p95_mm=estimate,
                                 effectivity=estimate / err["p95_mm"] if err["p95_mm"] > 0 else float("nan"),
                                 steps=[asdict(s) for s in result.steps]))
    return AdaptiveCase(shape=shape, case=case, nodes=ed.n_nodes, reference_s=reference_s,
                        reference_nodes=whole.mesh.n_nodes, ranking=ranking(eta, true),
                        accurate_error=nodal_error(accurate.unloaded_nodes, reference, ed.nodes),
                        accurate_s=accurate_s, adaptive=runs)


def run_adaptive(spec: AdaptiveSpec, progress=None) -> AdaptiveBenchResult:
    """Every shape × case of the spec (module docstring)."""
    spec = spec.validate()
    rows = [_case(spec, shape, case, progress) for shape in spec.shapes for case in spec.cases]
    return AdaptiveBenchResult(spec=asdict(spec), solver=solver_digest(), rows=rows)


def _f(x, digits: int = 3) -> str:
    return "–" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{digits}f}"


def markdown_report(result: AdaptiveBenchResult, header: str = "") -> str:
    lines = [header, "", "Error against `reference` (the mesh refined once in full), mm at the ED mesh's vertices; "
             "time of the whole unload, s.", "",
             "| shape | case | nodes | accurate mean / p95, time | tolerance | adaptive mean / p95 | estimated p95 "
             "(estimate / true) | met | finest mesh (ED tets split) | time | × reference's time |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in result.rows:
        a = r.accurate_error
        for ad in r.adaptive:
            last = ad.steps[-1]
            lines.append(f"| {r.shape} | {r.case} | {r.nodes} | {_f(a['mean_mm'])} / {_f(a['p95_mm'])}, "
                         f"{r.accurate_s:.1f} | {ad.tolerance_mm:g} | {_f(ad.error['mean_mm'])} / {_f(ad.error['p95_mm'])} | "
                         f"{_f(ad.estimate_p95_mm)} ({_f(ad.effectivity, 2)}) | {'yes' if ad.met else 'no'} | "
                         f"{last['nodes']:,} ({last['split_tets']} of {ad.steps[0]['tets']}) | {ad.wall_s:.1f} | "
                         f"{_f(ad.time_vs_reference, 2)} |")
    references = ", ".join(f"{r.shape} {r.case} {r.reference_nodes:,} nodes {r.reference_s:.1f} s" for r in result.rows)
    lines += ["", f"Reference: {references}.",
              "", "Indicator ranking (η_K against ‖∇u_ref − ∇u_h‖ over K, accurate on the mesh):", "",
              f"| shape | case | Spearman | share of Σ true² in η's top {TOP_SHARE:.0%} | best possible share |",
              "| --- | --- | --- | --- | --- |"]
    for r in result.rows:
        k = r.ranking
        lines.append(f"| {r.shape} | {r.case} | {_f(k.spearman, 2)} | {_f(k.top_share, 2)} | {_f(k.best_share, 2)} |")
    return "\n".join(lines) + "\n"


def write_report(result: AdaptiveBenchResult, out_dir: Path, header: str = "") -> dict:
    """adaptive.md and adaptive.json in `out_dir`; returns their paths."""
    import json

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"markdown": out_dir / "adaptive.md", "json": out_dir / "adaptive.json"}
    paths["markdown"].write_text(markdown_report(result, header))
    paths["json"].write_text(json.dumps(result.as_dict(), indent=1))
    return paths
