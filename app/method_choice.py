"""`heartctl unload --method auto`: the cheapest unloading method that met a tolerance on a run's trade
table (written by `heartctl bench trade`, bench.trade)."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from trainer.errors import TrainerError

TRADE_FILE = "trade.json"


@dataclass(frozen=True)
class Method:
    """An unloading method as the trade table names it: `method` fe | gnn | hybrid; `preset` the FE
    preset (None for gnn); `updates` a hybrid's inverse-update budget (None: to the tolerance);
    `ensemble` whether a gnn row averages several networks; `tolerance_mm` the adaptive preset's."""

    method: str
    preset: str | None = None
    updates: int | None = None
    ensemble: bool = False
    tolerance_mm: float | None = None


def parse_method(name: str) -> Method:
    """'hybrid accurate +2' → Method("hybrid", "accurate", updates=2); 'fe adaptive 0.05' →
    Method("fe", "adaptive", tolerance_mm=0.05); 'gnn ensemble' → Method("gnn", ensemble=True)."""
    parts = name.split()
    if parts[0] == "gnn":
        return Method("gnn", ensemble=len(parts) > 1)
    if parts[0] == "fe":
        return Method("fe", parts[1], tolerance_mm=float(parts[2]) if len(parts) > 2 else None)
    return Method("hybrid", parts[1], updates=None if parts[2] == "to" else int(parts[2].lstrip("+")))


@dataclass(frozen=True)
class MethodChoice:
    """The trade table's choice for `--method auto`: the row's name (`label`), what it runs, and what
    it measured there: p95 and largest nodal error against the converged solution (mm), mean time
    per case (s), on meshes of `nodes` nodes."""

    label: str
    run: Method
    p95_mm: float
    max_mm: float
    time_mean_s: float
    nodes: int


def load_trade(run_dir: Path | str, table: Path | None = None) -> dict:
    """The trade table of a run (RUN/trade/trade.json by default); TrainerError when there is none."""
    path = Path(table) if table is not None else Path(run_dir) / "trade" / TRADE_FILE
    if not path.is_file():
        raise TrainerError(f"no trade table at {path}: run heartctl bench trade run={run_dir} first")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise TrainerError(f"trade table {path} is not readable JSON ({exc})") from None


def choose_method(trade: dict, tolerance_mm: float, n_nodes: int, with_ensemble: bool) -> MethodChoice:
    """The cheapest method (mean time per case) whose p95 nodal error met `tolerance_mm` on every case
    of the table (bench.trade's JSON), at the table's resolution nearest to `n_nodes`; TrainerError
    (one line) when no method met it."""
    if not (math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise TrainerError(f"`tolerance_mm` must be a finite number > 0, got {tolerance_mm}")
    summary = trade.get("summary") or []
    if not summary:
        raise TrainerError("the trade table has no rows")
    nodes = {s["resolution"]: s["nodes"] for s in summary}
    res = min(nodes, key=lambda r: abs(math.log(max(nodes[r], 1) / max(n_nodes, 1))))
    rows = [s for s in summary if s["resolution"] == res and s["ok"] == s["cases"] and "p95_mm" in s
            and (with_ensemble or s["method"] != "gnn ensemble")]
    meets = [s for s in rows if s["p95_mm"] <= tolerance_mm]
    if not meets:
        best = min(rows, key=lambda s: s["p95_mm"], default=None)
        hint = f"; the closest, {best['method']}, reached {best['p95_mm']:.3f} mm" if best else ""
        raise TrainerError(f"no method met {tolerance_mm:g} mm (p95 nodal error against the converged solution) on "
                           f"the trade table's {nodes[res]}-node meshes{hint}")
    best = min(meets, key=lambda s: s["time_mean_s"])
    return MethodChoice(label=best["method"], run=parse_method(best["method"]), p95_mm=float(best["p95_mm"]),
                        max_mm=float(best["max_mm"]), time_mean_s=float(best["time_mean_s"]), nodes=int(best["nodes"]))
