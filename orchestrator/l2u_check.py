"""`heartctl bench l2u`: forward-solve the original dataset's unloaded meshes with their own
parameters using our solver, and compare with their ED meshes (mm, and as a fraction of the mean
loading displacement), per parameter value and overall; or, in the inverse direction, unload their
ED meshes and compare with their unloaded meshes."""
from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import asdict, dataclass, replace

import numpy as np

from solver.fidelity import Fidelity, get_fidelity
from solver.forward import SolveError
from solver.lv import forward_solve, inverse_solve
from solver.parameters import SOLVE_DIRECTIONS, CaseParameters
from storage.location import StoreError
from storage.reader import PairReader
from storage.schema import PARAM_NAMES



@dataclass(frozen=True, kw_only=True)
class L2uFigures:
    """How our geometry compares with theirs: the nodal distance (mean, max mm), their and our mean
    loading displacement (mm), the mean distance over their loading (`relative`), and the same after the
    in-plane rigid alignment; None where nothing was solved."""

    mismatch_mean_mm: float | None = None
    mismatch_max_mm: float | None = None
    loading_mean_mm: float | None = None
    ours_loading_mean_mm: float | None = None
    relative: float | None = None
    aligned_mean_mm: float | None = None
    aligned_relative: float | None = None

    def as_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass(frozen=True, kw_only=True)
class L2uPairCheck(L2uFigures):
    """One of their pairs solved by us: shape and case, their parameters (their C), their mean loading
    displacement (mm, always there), whether our solve converged (`reason` when not), its time (s), and
    when it did the figures."""

    shape: int
    case: int
    pressure_mmhg: float
    stiffness_pa: float
    helix_endo_deg: float
    helix_epi_deg: float
    loading_mean_mm: float
    ok: bool
    wall_s: float
    reason: str | None = None


@dataclass(frozen=True, kw_only=True)
class L2uSummary(L2uFigures):
    """Means over `n` solved pairs of their figures (the largest mismatch: the max); None for none."""

    n: int


@dataclass(frozen=True, kw_only=True)
class L2uCheckResult:
    """`bench l2u`'s result: the direction and set-up (preset, base, C factor, fibre rule, cell quadrature
    degree), pairs tried and solved, every pair, their summary overall and per parameter value."""

    direction: str
    fidelity: str
    base: str
    stiffness_factor: float
    fibres: str
    quad_degree: int
    rows: list[L2uPairCheck]
    overall: L2uSummary
    by_parameter: dict[str, dict[float, L2uSummary]]

    @property
    def cases(self) -> int:
        return len(self.rows)

    @property
    def solved(self) -> int:
        return sum(r.ok for r in self.rows)

    @property
    def failed(self) -> list[L2uPairCheck]:
        return [r for r in self.rows if not r.ok]

    def as_dict(self, with_rows: bool = True) -> dict:
        """`--json`'s layout (without the rows when `with_rows` is False)."""
        d = {"direction": self.direction, "fidelity": self.fidelity, "base": self.base,
             "stiffness_factor": self.stiffness_factor, "fibres": self.fibres, "quad_degree": self.quad_degree,
             "cases": self.cases, "solved": self.solved, "failed": [r.as_dict() for r in self.failed],
             "overall": self.overall.as_dict(),
             "by_parameter": {name: {v: g.as_dict() for v, g in groups.items()} for name, groups in self.by_parameter.items()}}
        return {**d, "rows": [r.as_dict() for r in self.rows]} if with_rows else d



def check_case(reader: PairReader, shape_id: int, k: int, fidelity: Fidelity | str, base: str,
               stiffness_factor: float = 1.0, fibres: str = "laplace", direction: str = "forward") -> L2uPairCheck:
    """One pair; `stiffness_factor` multiplies their C (their heartFEM code writes W = C (e^Q − 1),
    ours W = C/2 (e^Q − 1): 2 makes the laws equal); `fibres` is the fibre rule. direction "forward":
    inflate their unloaded mesh, compare with their ED mesh; "inverse": unload their ED mesh (inverse
    FE), compare with their unloaded mesh. Either way `mismatch_*` is the nodal distance to their
    geometry and `ours_loading_mean_mm` the mean distance between our two geometries."""
    if direction not in SOLVE_DIRECTIONS:
        raise ValueError(f"direction must be forward or inverse, got {direction!r}")
    case = reader.case(shape_id, k)
    mesh = reader.mesh(shape_id)
    unloaded = case.unloaded.astype(float)
    ed = case.loaded.astype(float)
    p = case.params
    params = CaseParameters(p["pressure_mmhg"], p["stiffness_pa"] * stiffness_factor, p["helix_endo_deg"],
                            p["helix_epi_deg"])
    loading = np.linalg.norm(ed - unloaded, axis=1)
    row = dict(shape=shape_id, case=k, **case.params, loading_mean_mm=float(loading.mean()))
    t0 = time.perf_counter()
    try:
        if direction == "forward":
            ours, theirs, start = forward_solve(mesh.with_nodes(unloaded), params, fidelity, base,
                                                fibres=fibres).loaded_nodes, ed, unloaded
        else:
            ours, theirs, start = inverse_solve(mesh.with_nodes(ed), params, fidelity, base,
                                                fibres=fibres).unloaded_nodes, unloaded, ed
    except SolveError as exc:
        return L2uPairCheck(**row, ok=False, reason=str(exc), wall_s=time.perf_counter() - t0)
    gap = np.linalg.norm(ours - theirs, axis=1)
    aligned = np.linalg.norm(align_in_plane(ours, theirs) - theirs, axis=1)
    ours_disp = np.linalg.norm(ours - start, axis=1)
    return L2uPairCheck(**row, ok=True, wall_s=time.perf_counter() - t0, mismatch_mean_mm=float(gap.mean()),
                        mismatch_max_mm=float(gap.max()), ours_loading_mean_mm=float(ours_disp.mean()),
                        relative=float(gap.mean() / loading.mean()), aligned_mean_mm=float(aligned.mean()),
                        aligned_relative=float(aligned.mean() / loading.mean()))


def align_in_plane(x: np.ndarray, target: np.ndarray) -> np.ndarray:
    """x moved by the in-plane rigid motion (rotation about z, x/y translation) that best matches
    target: the gauge both pipelines leave free under a sliding base."""
    a, b = x[:, :2] - x[:, :2].mean(axis=0), target[:, :2] - target[:, :2].mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    rot = u @ np.diag([1.0, d]) @ vt
    out = x.copy()
    out[:, :2] = a @ rot + target[:, :2].mean(axis=0)
    return out


def run_l2u_check(location: str, fidelity: str, base: str, limit: int | None = None,
                  stiffness_factor: float = 1.0, fibres: str = "laplace", quad_degree: int | None = None,
                  direction: str = "forward") -> L2uCheckResult:
    """`quad_degree` 1–6 overrides the preset's cell quadrature (heartFEM integrates, and places its
    fibres, at degree 4; 0 or None: the preset's). `limit` N ≥ 1: the first N done pairs (None: all).
    `stiffness_factor` > 0 multiplies their C. ValueError (one line) for a bad setting; StoreError for a
    store that import-l2u did not write: its pairs are ours, and "their" geometry would be our own labels."""
    from solver.fibres import check_fibre_rule

    if not (stiffness_factor > 0):
        raise ValueError(f"`stiffness_factor` must be > 0, got {stiffness_factor}")
    check_fibre_rule(fibres)
    if quad_degree is not None and not 0 <= quad_degree <= 6:
        raise ValueError(f"`quad_degree` must be 1–6 (0: the preset's), got {quad_degree}")
    quad_degree = quad_degree or None
    if limit is not None and limit < 1:
        raise ValueError(f"`limit` must be ≥ 1 (leave it out for every pair), got {limit}")
    reader = PairReader(location)
    if reader.attrs.get("shape_source") != "imported" or reader.attrs.get("fidelity") != "imported":
        raise StoreError(f"{location} was not imported from the original paper's dataset (it holds "
                         f"{reader.attrs.get('fidelity')} pairs of heartctl's own): bench l2u compares with their "
                         f"pipeline's geometry; import it with heartctl's import-l2u")
    keys = reader.done_cases()[:limit] if limit is not None else reader.done_cases()
    fid = get_fidelity(fidelity)
    if quad_degree is not None:
        fid = replace(fid, quad_degree=quad_degree)
    rows = [check_case(reader, s, k, fid, base, stiffness_factor, fibres, direction) for s, k in keys]
    ok = [r for r in rows if r.ok]
    by_param = {}
    for name in PARAM_NAMES:
        groups = defaultdict(list)
        for r in ok:
            groups[getattr(r, name)].append(r)
        by_param[name] = {v: _summary(g) for v, g in sorted(groups.items())}
    return L2uCheckResult(direction=direction, fidelity=fidelity, base=base, stiffness_factor=stiffness_factor,
                          fibres=fibres, quad_degree=fid.quad_degree, rows=rows, overall=_summary(ok),
                          by_parameter=by_param)


def _summary(rows: list[L2uPairCheck]) -> L2uSummary:
    if not rows:
        return L2uSummary(n=0)
    mean = {name: float(np.mean([getattr(r, name) for r in rows]))
            for name in ("mismatch_mean_mm", "loading_mean_mm", "ours_loading_mean_mm", "relative", "aligned_mean_mm",
                         "aligned_relative")}
    return L2uSummary(n=len(rows), mismatch_max_mm=float(np.max([r.mismatch_max_mm for r in rows])), **mean)
