"""The speed–accuracy trade of unloading, measured against the converged solution.

Held-out ED meshes (shapes of the run's shape model the run never saw, at the training resolution and
at the size users bring) are unloaded by every method: inverse FE with each preset from the ED
geometry; the network alone; the network's guess refined by k inverse updates and to tolerance. Each
answer is scored node for node against the `reference` preset's answer on the same ED mesh (the
`accurate` preset on the mesh refined once, near the converged solution of the same model: same law,
base condition and fibre rule). Network answers and budgeted hybrids also get the a-posteriori check
(`solver.reinflate`): how far they land from the ED mesh when inflated again, to see how well it
tracks their true error.

The result is the run's trade table (`trade.json` in the report folder): `app.method_choice` reads it
to pick the cheapest method that met a tolerance (`heartctl unload --method auto`)."""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from bench.convergence import LevelSolve, SolveCache
from solver.adaptive import adaptive_unload
from solver.forward import SolveError
from solver.lv import inverse_solve
from solver.mesh import MeshError, TetMesh, check_geometry
from solver.parameters import CaseParameters
from solver.reinflate import reinflation_error

from app.method_choice import TRADE_FILE
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

    @property
    def key(self) -> str:
        p = self.params
        return (f"s{self.shape_id}_seed{self.seed}_n{self.target_nodes}_P{p.pressure_mmhg:g}_C{p.stiffness_pa:g}"
                f"_e{p.helix_endo_deg:g}_p{p.helix_epi_deg:g}")


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
    if seed != store_seed:  # no shape of another seed is a training shape
        first = 0 if spec.first_shape is None else spec.first_shape
    elif spec.first_shape is not None:
        if spec.first_shape < first:
            raise TrainerError(f"first_shape={spec.first_shape}: the run's store holds shapes 0–{first - 1} of this "
                               f"seed; held-out shapes start at {first} or later")
        first = spec.first_shape
    nodes = fingerprint.get("mesh_nodes") or int(np.mean(list(fingerprint["shape_nodes"].values())))
    sizes = [("training", int(nodes))] + ([("user", spec.user_nodes)] if spec.user_nodes else [])
    return [HeldOutCase(first + s, seed, n, res, name, params)
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
    return _timed_answer(method, lambda: inverse_solve(ed, params, preset, base, initial_unloaded=guess,
                                                       fibres=fibres, max_updates=max_updates), network_s)


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


def spearman(a: list, b: list) -> float:
    """Spearman rank correlation of two equal-length samples (nan for fewer than 3 pairs)."""
    if len(a) < 3:
        return float("nan")
    from scipy.stats import spearmanr

    return float(spearmanr(a, b).statistic)


def run_trade(spec: TradeSpec, cache_dir: Path | None = None, progress=None) -> dict:
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
    version = int(fingerprint.get("shape_model_version") or 1)  # held-out shapes come from the store's model
    cache = SolveCache(cache_dir)
    rows, meshes = [], {}
    for case in held_out_cases(fingerprint, spec):
        mkey = (case.shape_id, case.target_nodes)
        if mkey not in meshes:
            meshes[mkey] = mesh_lv(lv_shape(case.shape_id, case.seed, version), case.target_nodes)
        ed = meshes[mkey]
        ref = reference_answer(case, ed, base, fibres, cache, progress)
        if ref.failed:
            if progress:
                progress(f"  shape {case.shape_id} {case.name}: reference failed ({ref.failed}); case skipped")
            continue
        answers = {a.method: a for a in solve_case(case, ed, predictors, spec, base, fibres)}
        for ans in answers.values():
            row = {"shape": case.shape_id, "nodes": ed.n_nodes, "resolution": case.resolution, "case": case.name,
                   "params": asdict(case.params), "method": ans.method, "wall_s": ans.wall_s,
                   "network_s": ans.network_s, "assembly_s": ans.assembly_s, "linear_s": ans.linear_s,
                   "updates": ans.updates, "mismatch_mm": ans.mismatch_mm, **score(ans, ref.unloaded)}
            checked = ans.method.startswith("gnn") or (ans.method.startswith("hybrid") and "to tol" not in ans.method)
            if checked and ans.unloaded is not None:
                chk = reinflation_error(ed, ans.unloaded, case.params, spec.check_preset, base, fibres)
                row.update(check_mean_mm=chk.mean_mm, check_max_mm=chk.max_mm, check_s=chk.wall_s,
                           check_failed=chk.failed)
            if ans.method == "hybrid accurate to tol":
                row["vs_cold_max_mm"] = _distance(ans, answers["fe accurate"])
            rows.append(row)
        if progress:
            done = [r for r in rows if r["shape"] == case.shape_id and r["nodes"] == ed.n_nodes and r["case"] == case.name]
            gnn = next(r for r in done if r["method"] == "gnn")
            progress(f"  shape {case.shape_id}, {ed.n_nodes} nodes, {case.name}: reference {ref.wall_s:.0f} s; "
                     f"gnn {gnn.get('mean_mm', float('nan')):.3f} mm mean; "
                     + ", ".join(f"{r['method']} {r['wall_s']:.1f} s" for r in done if r["method"].startswith("fe")))
    methods = method_names(spec, len(spec.runs) > 1)
    return {"spec": {**asdict(spec), "runs": list(spec.runs)}, "base": base, "fibres": fibres,
            "reference": "the reference preset (accurate on the ED mesh refined once), same law, base and fibres",
            "rows": rows, "summary": summarise(rows, methods), "check": check_tracking(rows),
            "hybrid_goal": hybrid_goal(rows)}


def _distance(a: Answer, b: Answer) -> float | None:
    """Max nodal distance between two answers (mm), None when either failed."""
    if a.unloaded is None or b.unloaded is None:
        return None
    return float(np.linalg.norm(a.unloaded - b.unloaded, axis=1).max())


def _p95(values: list) -> float:
    return float(np.percentile(values, 95)) if values else float("nan")


def summarise(rows: list, methods: list) -> list[dict]:
    """Per (resolution, method): cases answered, error (mean of case means; p95 and max over the cases'
    p95 and max), time per case (mean, p95) and its split (network, assembly, linear solves, other)."""
    out = []
    for res in ("training", "user"):
        mine = [r for r in rows if r["resolution"] == res]
        if not mine:
            continue
        for m in methods:
            rs = [r for r in mine if r["method"] == m]
            if not rs:
                continue
            ok = [r for r in rs if "mean_mm" in r]
            wall = [r["wall_s"] for r in rs]
            s = {"resolution": res, "method": m, "nodes": int(np.median([r["nodes"] for r in rs])),
                 "cases": len(rs), "ok": len(ok), "time_mean_s": float(np.mean(wall)), "time_p95_s": _p95(wall)}
            if ok:
                s.update(mean_mm=float(np.mean([r["mean_mm"] for r in ok])), p95_mm=_p95([r["p95_mm"] for r in ok]),
                         max_mm=float(max(r["max_mm"] for r in ok)))
            for part in ("network_s", "assembly_s", "linear_s"):
                s[part] = float(np.mean([r[part] for r in rs]))
            s["other_s"] = max(0.0, s["time_mean_s"] - s["network_s"] - s["assembly_s"] - s["linear_s"])
            out.append(s)
    return out


def check_tracking(rows: list) -> dict:
    """How well the re-inflation distance ranks the true error (Spearman over the checked answers, max
    nodal), and the median factor true / estimate: for the network alone and for every checked answer."""
    def track(rs):
        rs = [r for r in rs if "mean_mm" in r and not r.get("check_failed") and "check_max_mm" in r]
        if not rs:
            return {"answers": 0}
        true = [r["max_mm"] for r in rs]
        est = [r["check_max_mm"] for r in rs]
        ratio = [t / e for t, e in zip(true, est) if e > 0]
        return {"answers": len(rs), "spearman_max": spearman(est, true),
                "spearman_mean": spearman([r["check_mean_mm"] for r in rs], [r["mean_mm"] for r in rs]),
                "true_over_estimate_median": float(np.median(ratio)) if ratio else float("nan"),
                "check_s_mean": float(np.mean([r["check_s"] for r in rs]))}

    return {"gnn": track([r for r in rows if r["method"] == "gnn"]),
            "all": track([r for r in rows if "check_max_mm" in r])}


def hybrid_goal(rows: list) -> dict:
    """Network guess + accurate inverse to tolerance against the accurate preset from the ED mesh:
    mean time ratio (goal ≤ 0.3) and the largest max nodal distance between their answers (≤ 0.01 mm)."""
    hyb = [r for r in rows if r["method"] == "hybrid accurate to tol" and r.get("vs_cold_max_mm") is not None]
    if not hyb:
        return {"cases": 0}
    cold = {(r["shape"], r["nodes"], r["case"]): r["wall_s"] for r in rows if r["method"] == "fe accurate"}
    t_h = float(np.mean([r["wall_s"] for r in hyb]))
    t_c = float(np.mean([cold[(r["shape"], r["nodes"], r["case"])] for r in hyb]))
    return {"cases": len(hyb), "hybrid_s_mean": t_h, "cold_s_mean": t_c, "time_ratio": t_h / t_c,
            "max_distance_mm": float(max(r["vs_cold_max_mm"] for r in hyb))}


# ---- report

def _f(x, digits: int = 3) -> str:
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{digits}f}"


def markdown_report(result: dict, header: str = "") -> str:
    lines = [header, "", "## Error against the converged solution and time per case", "",
             f"Reference: {result['reference']} ({result['base']} base, {result['fibres']} fibres); held-out "
             "shapes; error = nodal distance of the unloaded geometry (mm); time = one case on one core, "
             "split into network (features, linear response, forward pass), FE assembly, sparse solves and other.",
             "",
             "| mesh | method | ok | mean | p95 | max | time mean s | time p95 s | network | assembly | linear | other |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for s in result["summary"]:
        lines.append(f"| {s['resolution']} ({s['nodes']}) | {s['method']} | {s['ok']}/{s['cases']} | {_f(s.get('mean_mm'))} "
                     f"| {_f(s.get('p95_mm'))} | {_f(s.get('max_mm'))} | {_f(s['time_mean_s'], 2)} | "
                     f"{_f(s['time_p95_s'], 2)} | {_f(s['network_s'], 2)} | {_f(s['assembly_s'], 2)} | "
                     f"{_f(s['linear_s'], 2)} | {_f(s['other_s'], 2)} |")
    g = result["hybrid_goal"]
    if g.get("cases"):
        lines += ["", "## Hybrid against the accurate preset from the ED mesh", "",
                  f"Network guess + accurate inverse to tolerance: {_f(g['hybrid_s_mean'], 2)} s against "
                  f"{_f(g['cold_s_mean'], 2)} s cold (ratio {_f(g['time_ratio'], 2)}, goal ≤ 0.30); answers within "
                  f"{g['max_distance_mm']:.1e} mm (max nodal, goal ≤ 0.01 mm) over {g['cases']} cases."]
    c = result["check"]
    lines += ["", "## The a-posteriori check (inflating the answer again, as unload's check does) against the true error", ""]
    for label, t in (("network alone", c["gnn"]), ("every checked answer", c["all"])):
        if t.get("answers"):
            lines.append(f"- {label}, {t['answers']} answers: Spearman {_f(t['spearman_max'], 2)} (max nodal), "
                         f"{_f(t['spearman_mean'], 2)} (mean); true error ≈ {_f(t['true_over_estimate_median'], 2)} × "
                         f"the re-inflation distance (median); {_f(t['check_s_mean'], 2)} s per check.")
    failed = [r for r in result["rows"] if "failed" in r]
    if failed:
        lines += ["", "## Failures", ""] + [f"- shape {r['shape']}, {r['nodes']} nodes, {r['case']}, {r['method']}: "
                                            f"{r['failed']}" for r in failed]
    return "\n".join(lines) + "\n"


def plot_report(result: dict, path: Path) -> None:
    """Pareto plot: time per case (log) against p95 nodal error (log), one marker per method and mesh."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    colours = {"gnn": "tab:purple", "fe": "tab:blue", "hybrid": "tab:orange"}
    markers = {"training": "o", "user": "s"}
    for s in result["summary"]:
        if "p95_mm" not in s:
            continue
        family = s["method"].split()[0]
        ax.scatter(s["time_mean_s"], s["p95_mm"], c=colours[family], marker=markers[s["resolution"]], s=36)
        ax.annotate(s["method"], (s["time_mean_s"], s["p95_mm"]), fontsize=6, xytext=(3, 2), textcoords="offset points")
    for res, m in markers.items():
        ax.scatter([], [], c="grey", marker=m, label=f"{res} meshes")
    for fam, col in colours.items():
        ax.scatter([], [], c=col, marker="o", label=fam)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per case, s (one CPU core)")
    ax.set_ylabel("p95 nodal error against the converged solution, mm")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def write_report(result: dict, out_dir: Path, header: str = "") -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    md, png, js = out_dir / "trade.md", out_dir / "trade.png", out_dir / TRADE_FILE
    md.write_text(markdown_report(result, header))
    plot_report(result, png)
    tmp = js.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1, default=float))
    tmp.replace(js)
    return {"markdown": md, "plot": png, "json": js}
