"""The trade table that `bench trade` returns and writes: each scored answer (`TradeRow`), each method's
summary per mesh size (`MethodSummary`), how well the a-posteriori check tracks the true error
(`CheckTracking`), the hybrid's goal (`HybridGoal`), all in a `TradeResult`; and its report (trade.md,
trade.png, and trade.json, which `app.method_choice` reads for `unload --method auto`)."""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from app.method_choice import TRADE_FILE


def _set_fields(obj) -> dict:
    """A record's fields that hold a value (None left out), as JSON writes it."""
    return {k: v for k, v in asdict(obj).items() if v is not None}


@dataclass(frozen=True, kw_only=True)
class TradeRow:
    """One method's answer to one held-out case: the case (shape id, mesh nodes, resolution "training" |
    "user", case name, CaseParameters as a dict), the method, its time (s: wall, and the network's,
    assembly's and sparse solves' shares), its inverse updates and final mismatch (mm) where it ran
    inverse FE; its nodal distance to the reference (mean, p95, max, mm) or why it failed; for network
    answers and budgeted hybrids the re-inflation check (mean, max mm, s, or why it failed); for the
    hybrid to tolerance its largest distance from the cold accurate answer (mm)."""

    shape: int
    nodes: int
    resolution: str
    case: str
    params: dict
    method: str
    wall_s: float
    network_s: float
    assembly_s: float
    linear_s: float
    updates: int | None = None
    mismatch_mm: float | None = None
    mean_mm: float | None = None
    p95_mm: float | None = None
    max_mm: float | None = None
    failed: str | None = None
    check_mean_mm: float | None = None
    check_max_mm: float | None = None
    check_s: float | None = None
    check_failed: str | None = None
    vs_cold_max_mm: float | None = None

    @property
    def scored(self) -> bool:
        return self.mean_mm is not None

    @property
    def checked(self) -> bool:
        return self.check_max_mm is not None and not self.check_failed

    def as_dict(self) -> dict:
        return _set_fields(self)


@dataclass(frozen=True, kw_only=True)
class MethodSummary:
    """One method at one mesh size: cases answered of those asked, error against the reference (mean of
    the cases' means; p95 and max over the cases' p95 and max, mm; None when none answered), time per
    case (mean, p95, s) and its split into network, assembly, sparse solves and other (mean, s)."""

    resolution: str
    method: str
    nodes: int
    cases: int
    ok: int
    time_mean_s: float
    time_p95_s: float
    network_s: float
    assembly_s: float
    linear_s: float
    other_s: float
    mean_mm: float | None = None
    p95_mm: float | None = None
    max_mm: float | None = None

    def as_dict(self) -> dict:
        return _set_fields(self)


@dataclass(frozen=True, kw_only=True)
class CheckTracking:
    """How well the re-inflation distance ranks the true error over `answers` checked answers: Spearman
    with the true max and mean nodal error, the median of true / estimated max error, the mean check
    time (s). None when nothing was checked."""

    answers: int
    spearman_max: float | None = None
    spearman_mean: float | None = None
    true_over_estimate_median: float | None = None
    check_s_mean: float | None = None

    def as_dict(self) -> dict:
        return _set_fields(self)


@dataclass(frozen=True, kw_only=True)
class HybridGoal:
    """The network's guess + accurate inverse to tolerance against accurate from the ED mesh, over
    `cases`: mean times (s), their ratio (goal ≤ 0.30), the largest max nodal distance between the two
    answers (mm, goal ≤ 0.01). None when no case had both."""

    cases: int
    hybrid_s_mean: float | None = None
    cold_s_mean: float | None = None
    time_ratio: float | None = None
    max_distance_mm: float | None = None

    def as_dict(self) -> dict:
        return _set_fields(self)


@dataclass(frozen=True, kw_only=True)
class TradeResult:
    """`bench trade`'s result: what was asked (`spec`, TradeSpec's fields), the model (base condition,
    fibre rule), what the reference is, every scored answer, the summaries, the check's tracking for
    the network alone and for every checked answer, and the hybrid's goal."""

    spec: dict
    base: str
    fibres: str
    reference: str
    rows: list[TradeRow]
    summary: list[MethodSummary]
    check_network: CheckTracking
    check_all: CheckTracking
    hybrid_goal: HybridGoal

    def as_dict(self) -> dict:
        """trade.json's layout (what `app.method_choice.choose_method` reads)."""
        return {"spec": self.spec, "base": self.base, "fibres": self.fibres, "reference": self.reference,
                "rows": [r.as_dict() for r in self.rows], "summary": [s.as_dict() for s in self.summary],
                "check": {"gnn": self.check_network.as_dict(), "all": self.check_all.as_dict()},
                "hybrid_goal": self.hybrid_goal.as_dict()}


def _p95(values: list) -> float:
    return float(np.percentile(values, 95)) if values else float("nan")


def summarise(rows: list[TradeRow], methods: list[str]) -> list[MethodSummary]:
    """Per (resolution, method), in the order of `methods`: a MethodSummary."""
    out = []
    for res in ("training", "user"):
        mine = [r for r in rows if r.resolution == res]
        for m in methods:
            rs = [r for r in mine if r.method == m]
            if not rs:
                continue
            ok = [r for r in rs if r.scored]
            wall = [r.wall_s for r in rs]
            wall_mean = float(np.mean(wall))
            parts = {part: float(np.mean([getattr(r, part) for r in rs])) for part in ("network_s", "assembly_s", "linear_s")}
            error = (dict(mean_mm=float(np.mean([r.mean_mm for r in ok])), p95_mm=_p95([r.p95_mm for r in ok]),
                          max_mm=float(max(r.max_mm for r in ok))) if ok else {})
            out.append(MethodSummary(resolution=res, method=m, nodes=int(np.median([r.nodes for r in rs])),
                                     cases=len(rs), ok=len(ok), time_mean_s=wall_mean, time_p95_s=_p95(wall),
                                     other_s=max(0.0, wall_mean - sum(parts.values())), **parts, **error))
    return out


def spearman(a: list, b: list) -> float:
    """Spearman rank correlation of two equal-length samples (nan for fewer than 3 pairs)."""
    if len(a) < 3:
        return float("nan")
    from scipy.stats import spearmanr

    return float(spearmanr(a, b).statistic)


def check_tracking(rows: list[TradeRow]) -> CheckTracking:
    """How well the re-inflation distance ranks the true error over the scored, checked rows."""
    rs = [r for r in rows if r.scored and r.checked]
    if not rs:
        return CheckTracking(answers=0)
    true = [r.max_mm for r in rs]
    est = [r.check_max_mm for r in rs]
    ratio = [t / e for t, e in zip(true, est) if e > 0]
    return CheckTracking(answers=len(rs), spearman_max=spearman(est, true),
                         spearman_mean=spearman([r.check_mean_mm for r in rs], [r.mean_mm for r in rs]),
                         true_over_estimate_median=float(np.median(ratio)) if ratio else float("nan"),
                         check_s_mean=float(np.mean([r.check_s for r in rs])))


def hybrid_goal(rows: list[TradeRow]) -> HybridGoal:
    """Network guess + accurate inverse to tolerance against the accurate preset from the ED mesh."""
    hyb = [r for r in rows if r.method == "hybrid accurate to tol" and r.vs_cold_max_mm is not None]
    if not hyb:
        return HybridGoal(cases=0)
    cold = {(r.shape, r.nodes, r.case): r.wall_s for r in rows if r.method == "fe accurate"}
    t_h = float(np.mean([r.wall_s for r in hyb]))
    t_c = float(np.mean([cold[(r.shape, r.nodes, r.case)] for r in hyb]))
    return HybridGoal(cases=len(hyb), hybrid_s_mean=t_h, cold_s_mean=t_c, time_ratio=t_h / t_c,
                      max_distance_mm=float(max(r.vs_cold_max_mm for r in hyb)))


# ---- report

def _f(x, digits: int = 3) -> str:
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{digits}f}"


def markdown_report(result: TradeResult, header: str = "") -> str:
    lines = [header, "", "## Error against the converged solution and time per case", "",
             f"Reference: {result.reference} ({result.base} base, {result.fibres} fibres); held-out "
             "shapes; error = nodal distance of the unloaded geometry (mm); time = one case on one core, "
             "split into network (features, linear response, forward pass), FE assembly, sparse solves and other.",
             "",
             "| mesh | method | ok | mean | p95 | max | time mean s | time p95 s | network | assembly | linear | other |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for s in result.summary:
        lines.append(f"| {s.resolution} ({s.nodes}) | {s.method} | {s.ok}/{s.cases} | {_f(s.mean_mm)} "
                     f"| {_f(s.p95_mm)} | {_f(s.max_mm)} | {_f(s.time_mean_s, 2)} | {_f(s.time_p95_s, 2)} | "
                     f"{_f(s.network_s, 2)} | {_f(s.assembly_s, 2)} | {_f(s.linear_s, 2)} | {_f(s.other_s, 2)} |")
    g = result.hybrid_goal
    if g.cases:
        lines += ["", "## Hybrid against the accurate preset from the ED mesh", "",
                  f"Network guess + accurate inverse to tolerance: {_f(g.hybrid_s_mean, 2)} s against "
                  f"{_f(g.cold_s_mean, 2)} s cold (ratio {_f(g.time_ratio, 2)}, goal ≤ 0.30); answers within "
                  f"{g.max_distance_mm:.1e} mm (max nodal, goal ≤ 0.01 mm) over {g.cases} cases."]
    lines += ["", "## The a-posteriori check (inflating the answer again, as unload's check does) against the true error", ""]
    for label, t in (("network alone", result.check_network), ("every checked answer", result.check_all)):
        if t.answers:
            lines.append(f"- {label}, {t.answers} answers: Spearman {_f(t.spearman_max, 2)} (max nodal), "
                         f"{_f(t.spearman_mean, 2)} (mean); true error ≈ {_f(t.true_over_estimate_median, 2)} × "
                         f"the re-inflation distance (median); {_f(t.check_s_mean, 2)} s per check.")
    failed = [r for r in result.rows if r.failed]
    if failed:
        lines += ["", "## Failures", ""] + [f"- shape {r.shape}, {r.nodes} nodes, {r.case}, {r.method}: {r.failed}"
                                            for r in failed]
    return "\n".join(lines) + "\n"


def plot_report(result: TradeResult, path: Path) -> None:
    """Pareto plot: time per case (log) against p95 nodal error (log), one marker per method and mesh."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    colours = {"gnn": "tab:purple", "fe": "tab:blue", "hybrid": "tab:orange"}
    markers = {"training": "o", "user": "s"}
    for s in result.summary:
        if s.p95_mm is None:
            continue
        family = s.method.split()[0]
        ax.scatter(s.time_mean_s, s.p95_mm, c=colours[family], marker=markers[s.resolution], s=36)
        ax.annotate(s.method, (s.time_mean_s, s.p95_mm), fontsize=6, xytext=(3, 2), textcoords="offset points")
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


def write_report(result: TradeResult, out_dir: Path, header: str = "") -> dict:
    """trade.md, trade.png and trade.json (written to a temporary file and renamed) in `out_dir`; their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    md, png, js = out_dir / "trade.md", out_dir / "trade.png", out_dir / TRADE_FILE
    md.write_text(markdown_report(result, header))
    plot_report(result, png)
    tmp = js.with_suffix(".tmp")
    tmp.write_text(json.dumps(result.as_dict(), indent=1, default=float))
    tmp.replace(js)
    return {"markdown": md, "plot": png, "json": js}
