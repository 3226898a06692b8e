"""Unloading a user's ED mesh as `heartctl unload` asks: by inverse finite elements (fe), by the
trained network (gnn), by the network's guess refined by inverse FE (hybrid), or by the cheapest of
these that met a tolerance on the run's trade table (auto)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .method_choice import MethodChoice

METHODS = ("fe", "gnn", "hybrid", "auto")
ADAPTIVE = "adaptive"  # the `fidelity` of solver.adaptive: accurate, refined locally to a tolerance
SOLVER_OPTIONS = ("fidelity", "tol_mm")  # options of the inverse FE, which --method gnn does not run
TRAINED_CHOICES = ("base", "fibres")  # model choices a network is trained with, checked against the user's


@dataclass(frozen=True)
class UnloadRequest:
    """How to unload: `method`; the inverse FE's `fidelity` preset, `base` condition, `fibres` rule and
    mismatch `tol_mm` (None: the preset's); the network's `runs` (several: an ensemble) and
    `rotations` (test-time turns about the long axis); auto's `tolerance_mm` (p95 nodal error against
    the converged solution); `check` (inflate a network answer again); no `runs` with a network method:
    the network shipped with heartctl (trainer.shipped); `given`: the option names the
    user wrote (a default is no choice); `max_updates`: auto's inverse-update budget for hybrid."""

    method: str = "fe"
    fidelity: str = "accurate"
    base: str = "sliding"
    fibres: str = "laplace"
    tol_mm: float | None = None
    runs: tuple = ()
    rotations: int = 1
    tolerance_mm: float | None = None
    check: bool = False
    given: frozenset = frozenset()

    def __post_init__(self):
        from solver.fibres import check_fibre_rule

        if self.tol_mm is not None and not (math.isfinite(self.tol_mm) and self.tol_mm > 0):
            raise ValueError(f"`tol_mm` must be a finite number > 0, got {self.tol_mm}")
        check_fibre_rule(self.fibres)
        if self.rotations < 1 or (self.rotations > 1 and self.method == "fe"):
            raise ValueError(f"`rotations` must be ≥ 1 and applies to `method` gnn|hybrid, got {self.rotations}")
        adaptive = self.fidelity == ADAPTIVE
        if adaptive and self.method != "fe":
            raise ValueError(f"`fidelity` {ADAPTIVE} applies to `method` fe")
        if self.tolerance_mm is None and (self.method == "auto" or adaptive):
            raise ValueError("`method` auto needs `tolerance_mm` X" if self.method == "auto"
                             else f"`fidelity` {ADAPTIVE} needs `tolerance_mm` X")
        if self.tolerance_mm is not None and self.method != "auto" and not adaptive:
            raise ValueError(f"`tolerance_mm` applies to `method` auto or `fidelity` {ADAPTIVE} (use `tol_mm` for the "
                             f"inverse FE's mismatch)")
        if self.tolerance_mm is not None and not (math.isfinite(self.tolerance_mm) and self.tolerance_mm > 0):
            raise ValueError(f"`tolerance_mm` must be a finite number > 0, got {self.tolerance_mm}")
        if self.check and self.method == "fe":
            raise ValueError("`check` applies to `method` gnn|hybrid|auto: `method` fe prints its own mismatch")
        if self.method == "gnn" and not self.check:
            solver_only = [f"--{n.replace('_', '-')}" for n in SOLVER_OPTIONS if n in self.given]
            if solver_only:
                raise ValueError(f"{' and '.join(solver_only)} appl{'y' if len(solver_only) > 1 else 'ies'} to "
                                 f"`method` fe|hybrid: `method` gnn solves nothing")
        if self.runs and self.method == "fe":
            raise ValueError("`run` applies to `method` gnn|hybrid|auto")

    def plan(self, n_nodes: int) -> tuple[UnloadPlan, MethodChoice | None]:
        """What to run on a mesh of `n_nodes` nodes, and for --method auto the trade table's row that
        chose it (its method, preset, inverse-update budget; the runs an ensemble needs)."""
        asked = {name: getattr(self, name) for name in TRAINED_CHOICES if name in self.given}
        runs = self.runs
        if not runs and self.method != "fe":  # no --run: the network shipped with heartctl
            from trainer.shipped import shipped_run

            runs = (shipped_run(),)
        plan = UnloadPlan(self.method, self.fidelity, self.base, self.fibres, self.tol_mm, runs, self.rotations, asked,
                          tolerance_mm=self.tolerance_mm if self.fidelity == ADAPTIVE else None)
        if self.method != "auto":
            return plan, None
        from .method_choice import choose_method, load_trade

        choice = choose_method(load_trade(runs[0]), self.tolerance_mm, n_nodes, with_ensemble=len(runs) > 1)
        chosen = choice.run
        runs = runs if chosen.ensemble or chosen.method != "gnn" else runs[:1]
        return replace(plan, method=chosen.method, fidelity=chosen.preset or self.fidelity, runs=runs,
                       max_updates=chosen.updates, tolerance_mm=chosen.tolerance_mm), choice


@dataclass(frozen=True)
class UnloadPlan:
    """A checked request made concrete: `method` fe | gnn | hybrid with its settings (UnloadRequest's),
    `asked` the model choices the user named, `max_updates` a hybrid's inverse-update budget,
    `tolerance_mm` the adaptive loop's target (fidelity adaptive)."""

    method: str
    fidelity: str
    base: str
    fibres: str
    tol_mm: float | None
    runs: tuple
    rotations: int
    asked: dict
    max_updates: int | None = None
    tolerance_mm: float | None = None


@dataclass
class UnloadResult:
    """An ED mesh unloaded as a plan asked: the unloaded geometry [n, 3] (mm) by `method` (fe | gnn |
    hybrid), with the inverse FE's InverseResult (fe, hybrid), the AdaptiveResult (fe at fidelity
    adaptive) and the network's NetworkUnload (gnn, hybrid)."""

    method: str
    unloaded_nodes: object
    inverse: object = None
    adaptive: object = None
    network: object = None

    @property
    def warnings(self) -> list:
        return list(self.network.warnings) if self.network is not None else []


def unload_mesh(lv, params, plan: UnloadPlan) -> UnloadResult:
    """Unload the ED TetMesh `lv` (mm) at CaseParameters `params` by plan.method (fe | gnn | hybrid).
    SolveError when the inverse FE fails."""
    if plan.method == "fe" and plan.fidelity == ADAPTIVE:
        from solver.adaptive import adaptive_unload
        from solver.progress import report

        result = adaptive_unload(lv, params, plan.tolerance_mm, plan.base, plan.fibres, tol_mm=plan.tol_mm,
                                 report=report)
        return UnloadResult("fe", result.unloaded_nodes, result.inverse, adaptive=result)
    if plan.method == "fe":
        from solver.lv import inverse_solve

        result = inverse_solve(lv, params, plan.fidelity, plan.base, tol_mm=plan.tol_mm, fibres=plan.fibres)
        return UnloadResult("fe", result.unloaded_nodes, result)
    from trainer.evaluation.predict import unload_with_network

    result = unload_with_network(lv, params, [Path(r) for r in plan.runs], plan.method, plan.fidelity,
                                 plan.base, plan.tol_mm, fibres=plan.fibres, asked=plan.asked,
                                 rotations=plan.rotations, max_updates=plan.max_updates)
    return UnloadResult(plan.method, result.unloaded_nodes, result.inverse, network=result)
