"""The speed–accuracy trade of unloading, measured against the converged solution.

Held-out ED meshes (shapes of the run's shape model the run never saw, at the training resolution and
at the size users bring) are unloaded by every method: inverse FE with each preset from the ED
geometry; the network alone; the network's guess refined by k inverse updates and to tolerance. Each
answer is scored node for node against the `reference` preset's answer on the same ED mesh (the
`accurate` preset on the mesh refined once, near the converged solution of the same model: same law,
base condition and fibre rule). Network answers and budgeted hybrids also get the a-posteriori check
(`solver.reinflate`): how far they land from the ED mesh when inflated again, to see how well it
tracks their true error.

The result is the run's trade table (`bench.trade_table.TradeResult`, written as `trade.json` in the report
folder): `app.method_choice` reads it to pick the cheapest method that met a tolerance (`heartctl unload
--method auto`)."""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from bench.convergence import LevelSolve, SolveCache
from bench.trade_table import TradeResult, TradeRow, check_tracking, hybrid_goal, summarise
from solver.adaptive import adaptive_unload
from solver.forward import SolveError
from solver.lv import inverse_solve
from solver.mesh import MeshError, TetMesh, check_geometry
from solver.parameters import CaseParameters
from solver.reinflate import reinflation_error

from trainer.errors import TrainerError

FE_PRESETS_COMPARED = ("fast", "accurate")
AXES = ("pressure_mmhg", "stiffness_pa", "helix_endo_deg", "helix_epi_deg")


@dataclass(frozen=True)
class TradeSpec:
    """What `bench trade` measures. shapes: held-out shapes (ids after the run's last); cases: the mid
    of the run's parameter box, then its corners, hardest first; user_nodes: the second mesh size
    (0: the training resolution only); hybrid_updates: the budgets of the network-guess hybrids;
    check_preset: the preset of the a-posteriori re-inflation; network_only: score the network (and
    its ensemble) alone, no FE or hybrid methods; first_shape: the first held-out shape id (None: the
    one after the run's last; runs trained on different stores are then scored on the same shapes); seed:
    the held-out shapes' shape-model seed (None: the run's store's; another seed holds no training shape);
    shape_model: their shape model's version (None: the run's store's; another version, like another seed,
    holds no training shape);
    adaptive_tolerance_mm: the target of the adaptive FE row (`unload --fidelity adaptive --tolerance-mm`)."""

    runs: tuple[str, ...]
    shapes: int = 2
    cases: int = 3
    user_nodes: int = 800
    hybrid_updates: tuple[int, ...] = (1, 2, 4)
    check_preset: str = "accurate"
    network_only: bool = False
    first_shape: int | None = None
    seed: int | None = None  # the held-out shapes' seed (None: the run's store's)
    shape_model: int | None = None  # the held-out shapes' shape model version (None: the run's store's)
    adaptive_tolerance_mm: float = 0.05

    def validate(self) -> "TradeSpec":
        if not self.runs:
            raise ValueError("bench trade needs `run` DIR (a trained network)")
        if not 1 <= self.shapes <= 20:
            raise ValueError(f"`shapes` must be 1–20, got {self.shapes}")
        if not 1 <= self.cases <= 5:
            raise ValueError(f"`cases` must be 1–5 (the mid case and up to 4 corners), got {self.cases}")
        if self.user_nodes and not 150 <= self.user_nodes <= 5000:
            raise ValueError(f"`user_nodes` must be 0 or 150–5000, got {self.user_nodes}")
        if self.first_shape is not None and self.first_shape < 0:
            raise ValueError(f"`first_shape` must be ≥ 0, got {self.first_shape}")
        if self.shape_model is not None:
            from solver.shape_model import check_version

            check_version(self.shape_model)
        if not (math.isfinite(self.adaptive_tolerance_mm) and self.adaptive_tolerance_mm > 0):
            raise ValueError(f"`adaptive_tolerance_mm` must be a number > 0, got {self.adaptive_tolerance_mm}")
        if any(k < 1 for k in self.hybrid_updates):
            raise ValueError("hybrid update budgets must be ≥ 1")
        return self


@dataclass(frozen=True)
class HeldOutCase:
    shape_id: int
    seed: int
    target_nodes: int
    resolution: str  # "training" | "user"
    name: str  # "mid" | "corner …"
    params: CaseParameters
    version: int  # the shape model's

    @property
    def key(self) -> str:
        p = self.params
        return (f"s{self.shape_id}_seed{self.seed}_v{self.version}_n{self.target_nodes}_P{p.pressure_mmhg:g}"
                f"_C{p.stiffness_pa:g}_e{p.helix_endo_deg:g}_p{p.helix_epi_deg:g}")


def box_cases(grid: dict, n: int) -> list[tuple[str, CaseParameters]]:
    """The mid of the run's parameter box (each axis at its midpoint, values the network did not see),
    then its pressure × stiffness corners, hardest first (highest pressure on the softest wall, then
    the lowest on the stiffest, then the other two), the hardest with the steepest helix angles."""
    lo = {a: float(min(grid[a])) for a in AXES}
    hi = {a: float(max(grid[a])) for a in AXES}
    mid = CaseParameters(*((lo[a] + hi[a]) / 2 for a in AXES))
    steep = (hi["helix_endo_deg"], lo["helix_epi_deg"])
    mild = (lo["helix_endo_deg"], hi["helix_epi_deg"])
    corners = [(hi["pressure_mmhg"], lo["stiffness_pa"], steep), (lo["pressure_mmhg"], hi["stiffness_pa"], mild),
               (hi["pressure_mmhg"], hi["stiffness_pa"], mild), (lo["pressure_mmhg"], lo["stiffness_pa"], steep)]
    out = [("mid", mid)]
    for p, c, (endo, epi) in corners:
        params = CaseParameters(p, c, endo, epi)
        if params not in [q for _, q in out]:
            out.append((f"P{p:g} C{c:g}", params))
    return out[:n]


def held_out_cases(fingerprint: dict, spec: TradeSpec) -> list[HeldOutCase]:
    """Shapes the run's store does not hold (ids after its last, same seed), each at the training
    resolution and at `user_nodes`, at the cases of `box_cases`."""
    grid = fingerprint.get("grid") or {}
    if not all(grid.get(a) for a in AXES):
        raise TrainerError("the run's checkpoint names no parameter grid: bench trade needs a run trained on a "
                           "store made by heartctl generate")
    seen = [int(s) for s in fingerprint.get("shape_nodes", {})] or [int(grid.get("shapes", 1)) - 1]
    first = max(max(seen) + 1, int(grid.get("shapes", 0)))
    store_seed = int(fingerprint.get("seed") or 0)
    seed = store_seed if spec.seed is None else int(spec.seed)
    store_version = int(fingerprint.get("shape_model_version") or 1)
    version = store_version if spec.shape_model is None else int(spec.shape_model)
    if seed != store_seed or version != store_version:  # no shape of another seed or model is a training shape
        first = 0 if spec.first_shape is None else spec.first_shape
    elif spec.first_shape is not None:
        if spec.first_shape < first:
            raise TrainerError(f"first_shape={spec.first_shape}: the run's store holds shapes 0–{first - 1} of this "
                               f"seed; held-out shapes start at {first} or later")
        first = spec.first_shape
    nodes = fingerprint.get("mesh_nodes") or int(np.mean(list(fingerprint["shape_nodes"].values())))
    sizes = [("training", int(nodes))] + ([("user", spec.user_nodes)] if spec.user_nodes else [])
    return [HeldOutCase(first + s, seed, n, res, name, params, version)
            for s in range(spec.shapes) for res, n in sizes for name, params in box_cases(grid, spec.cases)]


@dataclass
class Answer:
    """One method's unloaded geometry of one case, its cost, and where the cost went."""

    method: str
    unloaded: np.ndarray | None = field(repr=False)
    wall_s: float
    network_s: float = 0.0
    assembly_s: float = 0.0
    linear_s: float = 0.0
    updates: int | None = None
    mismatch_mm: float | None = None
    failed: str = ""


def _inverse_answer(method: str, ed: TetMesh, params: CaseParameters, preset: str, base: str, fibres: str,
                    guess: np.ndarray | None = None, max_updates: int | None = None,
                    network_s: float = 0.0) -> Answer:
    """A cold inverse (no guess), or a hybrid's from the network's guess as `unload --method hybrid` runs
    it: a rough first state, to HYBRID_TOL_MM (or for `max_updates` updates)."""
    from trainer.evaluation.predict import HYBRID_TOL_MM

    hybrid = method.startswith("hybrid")
    tol_mm = HYBRID_TOL_MM if hybrid else None
    return _timed_answer(method, lambda: inverse_solve(ed, params, preset, base, initial_unloaded=guess, tol_mm=tol_mm,
                                                       fibres=fibres, max_updates=max_updates,
                                                       rough_first_state=hybrid), network_s)


def _timed_answer(method: str, solve, network_s: float = 0.0) -> Answer:
    """`solve()` (an InverseResult or AdaptiveResult) timed and scored as an Answer; a solve that fails
    is an Answer with its reason. `network_s`: the network's time before it (hybrids)."""
    t0 = time.perf_counter()
    try:
        r = solve()
    except (SolveError, MeshError) as exc:
        return Answer(method, None, time.perf_counter() - t0 + network_s, network_s,
                      failed=str(exc).splitlines()[0][:160])
    wall = time.perf_counter() - t0
    return Answer(method, r.unloaded_nodes, wall + network_s, network_s, r.stats.assembly_s, r.stats.linear_s,
                  r.updates, r.mismatch_mm)


def method_names(spec: TradeSpec, ensemble: bool) -> list[str]:
    """Every method the table compares, cheapest family first."""
    names = ["gnn"] + (["gnn ensemble"] if ensemble else [])
    if spec.network_only:
        return names
    names += [f"fe {p}" for p in FE_PRESETS_COMPARED] + [adaptive_name(spec)]
    names += [f"hybrid {p} +{k}" for p in FE_PRESETS_COMPARED for k in spec.hybrid_updates]
    names += [f"hybrid {p} to tol" for p in FE_PRESETS_COMPARED]
    return names


def adaptive_name(spec: TradeSpec) -> str:
    return f"fe adaptive {spec.adaptive_tolerance_mm:g}"


def _network_guess(predictor, ed: TetMesh, params: CaseParameters) -> tuple[np.ndarray, float]:
    """The network's unloaded geometry of a new mesh and its cost (s): features, the linear FE response
    where the network takes it, and the forward pass, as a user pays them for one mesh."""
    from trainer.data.features import mesh_features

    values = np.array([params.pressure_mmhg, params.stiffness_pa, params.helix_endo_deg, params.helix_epi_deg])
    t0 = time.perf_counter()
    feat = mesh_features(ed)
    (disp,), _ = predictor.predict_many_with_spread([(feat, values, None)], 1)
    predictor.sync()
    return ed.nodes + disp, time.perf_counter() - t0


def solve_case(case: HeldOutCase, ed: TetMesh, predictors: dict, spec: TradeSpec, base: str, fibres: str) -> list[Answer]:
    """Every method's answer for one held-out case. predictors: {"gnn": first run, "gnn ensemble": all}."""
    answers = []
    guess = None
    for label, pred in predictors.items():
        unloaded, net_s = _network_guess(pred, ed, case.params)
        answers.append(Answer(label, unloaded, net_s, net_s))
        if label == "gnn":
            guess, guess_s = unloaded, net_s
    if spec.network_only:
        return answers
    try:
        check_geometry(guess, ed.tets)
        usable = guess
    except MeshError:
        usable = None  # hybrid starts from the ED mesh, as `unload --method hybrid` does
    for preset in FE_PRESETS_COMPARED:
        answers.append(_inverse_answer(f"fe {preset}", ed, case.params, preset, base, fibres))
        for k in spec.hybrid_updates:
            answers.append(_inverse_answer(f"hybrid {preset} +{k}", ed, case.params, preset, base, fibres,
                                           usable, k, guess_s))
        answers.append(_inverse_answer(f"hybrid {preset} to tol", ed, case.params, preset, base, fibres,
                                       usable, None, guess_s))
    # a tolerance not met is still an answer, scored like the others
    tolerance = spec.adaptive_tolerance_mm
    answers.append(_timed_answer(adaptive_name(spec), lambda: adaptive_unload(ed, case.params, tolerance, base, fibres)))
    return answers


def reference_answer(case: HeldOutCase, ed: TetMesh, base: str, fibres: str, cache: SolveCache,
                     progress=None) -> LevelSolve:
    """The `reference` preset's unloaded geometry of the case at ed's nodes (cached by solver digest)."""
    key = f"trade_{case.key}_{base}_{fibres}"
    hit = cache.get(key)
    if hit is not None:
        return hit
    if progress:
        progress(f"  reference solve: shape {case.shape_id}, {ed.n_nodes} nodes, {case.params.label()} …")
    t0 = time.perf_counter()
    try:
        r = inverse_solve(ed, case.params, "reference", base, fibres=fibres)
        solve = LevelSolve(1, ed.n_nodes, time.perf_counter() - t0, r.updates, r.stats.newton_iterations,
                           r.unloaded_nodes.copy())
    except SolveError as exc:
        solve = LevelSolve(1, ed.n_nodes, time.perf_counter() - t0, 0, 0, np.full_like(ed.nodes, np.nan),
                           str(exc).splitlines()[0][:160])
    cache.put(key, solve)
    return solve


def score(answer: Answer, reference: np.ndarray) -> dict:
    """Nodal distance to the reference (mm)."""
    if answer.failed or answer.unloaded is None:
        return {"failed": answer.failed or "no answer"}
    e = np.linalg.norm(answer.unloaded - reference, axis=1)
    return {"mean_mm": float(e.mean()), "p95_mm": float(np.percentile(e, 95)), "max_mm": float(e.max())}


def run_trade(spec: TradeSpec, cache_dir: Path | None = None, progress=None) -> TradeResult:
    """Every held-out case solved by every method and scored against its reference; the summary per
    (method, resolution), the a-posteriori check's tracking of the true error, and the hybrid goal."""
    from solver.meshing import mesh_lv
    from solver.shape_model import lv_shape

    from trainer.data.store_cases import fingerprint_value
    from trainer.evaluation.predict import Ensemble

    spec = spec.validate()
    predictors = {"gnn": Ensemble.from_runs(spec.runs[:1])}
    if len(spec.runs) > 1:
        predictors["gnn ensemble"] = Ensemble.from_runs(spec.runs)
    fingerprint = predictors["gnn"].state.get("fingerprint", {})
    base = fingerprint_value(fingerprint, "base") or "sliding"
    fibres = fingerprint_value(fingerprint, "fibres")
    cache = SolveCache(cache_dir)
    rows, meshes = [], {}
    for case in held_out_cases(fingerprint, spec):
        mkey = (case.shape_id, case.target_nodes)
        if mkey not in meshes:
            meshes[mkey] = mesh_lv(lv_shape(case.shape_id, case.seed, case.version), case.target_nodes)
        ed = meshes[mkey]
        ref = reference_answer(case, ed, base, fibres, cache, progress)
        if ref.failed:
            if progress:
                progress(f"  shape {case.shape_id} {case.name}: reference failed ({ref.failed}); case skipped")
            continue
        answers = {a.method: a for a in solve_case(case, ed, predictors, spec, base, fibres)}
        for ans in answers.values():
            rows.append(_scored_row(case, ed, ans, ref.unloaded, answers, spec.check_preset, base, fibres))
        if progress:
            done = [r for r in rows if r.shape == case.shape_id and r.nodes == ed.n_nodes and r.case == case.name]
            gnn = next(r for r in done if r.method == "gnn")
            progress(f"  shape {case.shape_id}, {ed.n_nodes} nodes, {case.name}: reference {ref.wall_s:.0f} s; "
                     f"gnn {gnn.mean_mm if gnn.scored else float('nan'):.3f} mm mean; "
                     + ", ".join(f"{r.method} {r.wall_s:.1f} s" for r in done if r.method.startswith("fe")))
    methods = method_names(spec, len(spec.runs) > 1)
    return TradeResult(spec={**asdict(spec), "runs": list(spec.runs)}, base=base, fibres=fibres,
                       reference="the reference preset (accurate on the ED mesh refined once), same law, base and fibres",
                       rows=rows, summary=summarise(rows, methods), hybrid_goal=hybrid_goal(rows),
                       check_network=check_tracking([r for r in rows if r.method == "gnn"]),
                       check_all=check_tracking(rows))


def _scored_row(case: HeldOutCase, ed: TetMesh, ans: Answer, reference: np.ndarray, answers: dict,
                check_preset: str, base: str, fibres: str) -> TradeRow:
    """One answer scored against the reference; network answers and budgeted hybrids inflated again (the
    check); the hybrid to tolerance measured against the cold accurate answer."""
    check = {}
    checked = ans.method.startswith("gnn") or (ans.method.startswith("hybrid") and "to tol" not in ans.method)
    if checked and ans.unloaded is not None:
        chk = reinflation_error(ed, ans.unloaded, case.params, check_preset, base, fibres)
        check = dict(check_mean_mm=chk.mean_mm, check_max_mm=chk.max_mm, check_s=chk.wall_s, check_failed=chk.failed)
    vs_cold = _distance(ans, answers["fe accurate"]) if ans.method == "hybrid accurate to tol" else None
    return TradeRow(shape=case.shape_id, nodes=ed.n_nodes, resolution=case.resolution, case=case.name,
                    params=asdict(case.params), method=ans.method, wall_s=ans.wall_s, network_s=ans.network_s,
                    assembly_s=ans.assembly_s, linear_s=ans.linear_s, updates=ans.updates,
                    mismatch_mm=ans.mismatch_mm, vs_cold_max_mm=vs_cold, **score(ans, reference), **check)


def _distance(a: Answer, b: Answer) -> float | None:
    """Max nodal distance between two answers (mm), None when either failed."""
    if a.unloaded is None or b.unloaded is None:
        return None
    return float(np.linalg.norm(a.unloaded - b.unloaded, axis=1).max())
