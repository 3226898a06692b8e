"""Forward inflation: Newton–Raphson on the total-Lagrangian problem with adaptive load stepping
(cut on divergence or det F ≤ 0, grow after easy steps)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .assembly import MechanicsProblem
from .linear import SingularMatrix, SparseSolver
from .progress import report


STALE_TANGENT_RATE = 0.25  # refactorise when a modified-Newton step reduces |R| by less than 4×
MODIFIED_STEP_WEIGHT = 1.0 / 3.0  # a modified-Newton step's share of the iteration budget: it contracts
# only linearly (≥ 4× per step, else the tangent is refreshed), so it may take several where full Newton
# takes one; it costs a residual assembly and a back-substitution, not a tangent and a factorisation
BACKTRACK_STEPS = (1.0, 0.5, 0.25)  # fractions of a full Newton step tried in turn
# a full step accepted that cut |R|∞ by less than EXTEND_WHEN is tried once more at EXTENDED_STEP × its
# length, and taken if its residual is lower still and no det F fell below EXTEND_MIN_J_SHARE of the full
# step's smallest. Far up the exponential law's stiff range Newton's linearisation undershoots: each
# full step cuts |R|∞ only ~e× (docs/solver.md, "Solves"); the doubled step costs one residual assembly
EXTEND_WHEN = 0.3
EXTENDED_STEP = 2.0
EXTEND_MIN_J_SHARE = 0.5
# intermediate load steps: |R|∞ ≤ 1e-2 P·area, 1 % of a typical nodal force at full load (the increment
# test, |Δu| ≤ 1 mm at this looseness, still needs that residual). Their states only start the next
# step, and the last step is solved to the full tolerance. Over 33 forward solves
# (800 nodes; the corners of two extreme shapes and of shape 0, and three mid cases): 1e4 478
# factorisations, 1e5 426, 1e7 351, 1e8 327; at 1e9 one solve failed (its load steps collapsed), so
# 1e7 keeps a 100× margin
INTERMEDIATE_LOOSENESS = 1e7
# a correction at full load from a given state (a guessed reference, an inverse update's re-solve) goes
# past the preset's Newton budget, up to PATIENT_BUDGET_FACTOR times it, while |R|∞ at least halves an
# iteration on average over the last PATIENT_WINDOW iterations (one backtracked step is no reason to
# stop). From a rough guess on a soft wall, Newton descends the exponential law's stiff range linearly,
# |R|∞ falling ~e× an iteration (a network's guess at P 14 mmHg, C 50 Pa, 329 nodes: 5e13 → 3e2 in 24
# iterations); giving up at the budget restarts from zero strain, which costs more than the whole
# correction (docs/benchmarks.md)
PATIENT_BUDGET_FACTOR = 3
PATIENT_CONTRACTION = 0.5
PATIENT_WINDOW = 3
# load stepping from zero strain: the first step carries at most this many times the law's C of cavity
# pressure (the preset's ¼ of the load otherwise). The linearised step's strain grows as P / C, and past
# ~4 C it lands far up the exponential law's stiff range (NaN or |R| × 1e4, then step cuts): at
# P 14 mmHg, C 50 Pa (P = 37 C) a first step of 0.107 of the load against ¼ took an `accurate` forward
# solve on 689 nodes from 8.0 to 3.1 s; over 4 meshes × 5 corners and mid cases, 47.3 → 40.0 s
# (`accurate`) and 6.0 → 5.6 s (`fast`), no case slower by more than 0.22 s (docs/solver.md)
FIRST_STEP_PRESSURE_PER_C = 4.0


class SolveError(RuntimeError):
    """The nonlinear solve failed; the message gives the load reached, min det F and residual."""


@dataclass
class SolveStats:
    newton_iterations: int = 0
    load_steps: int = 0
    step_cuts: int = 0
    final_residual: float = float("nan")
    min_jacobian: float = float("nan")
    assembly_s: float = 0.0
    linear_s: float = 0.0
    wall_s: float = 0.0
    residual_history: list = field(default_factory=list)
    newton_iterations_here: int = 0
    jacobian_products: int = 0  # inverse FE's Newton–Krylov steps (solver/inverse_newton.py)

    def add(self, other: "SolveStats") -> None:
        self.newton_iterations += other.newton_iterations
        self.jacobian_products += other.jacobian_products
        self.load_steps += other.load_steps
        self.step_cuts += other.step_cuts
        self.assembly_s += other.assembly_s
        self.linear_s += other.linear_s
        self.wall_s += other.wall_s
        self.final_residual = other.final_residual
        self.min_jacobian = other.min_jacobian


def _newton(problem: MechanicsProblem, z: np.ndarray, pressure_pa: float, linsolve: SparseSolver,
            stats: SolveStats, force_scale: float, looseness: float = 1.0, reuse_factor: bool = False,
            patient: bool = False):
    """Newton iterations at a fixed load. With `reuse_factor`, reuse the last factorisation while it still
    contracts the residual fast (modified Newton) and refactorising otherwise. `patient`: past the
    preset's iteration budget, go on while |R|∞ halves an iteration over the last PATIENT_WINDOW (up to
    PATIENT_BUDGET_FACTOR × the budget).

    Converged when |R|∞ ≤ rtol·force_scale·looseness, or when a full-Newton update is below
    increment_tol_mm·looseness (the residual is then checked once more). Returns (z, ok, reason)."""
    fid = problem.fidelity
    run = _NewtonRun(problem, pressure_pa, linsolve, stats, force_scale, reuse_factor, z,
                     r_tol=fid.residual_rtol * force_scale * looseness, du_tol=fid.increment_tol_mm * looseness,
                     # a held factorisation serves only a tangent of this problem's size (a workspace
                     # holds one solver for problems of several supports)
                     need_tangent=not (reuse_factor and linsolve.size == problem.free.size), patient=patient,
                     first=len(stats.residual_history))
    # a pass that only refreshes a tangent or steps back solves nothing: at most two passes per solve
    for _ in range(2 * int(np.ceil(run.max_budget / MODIFIED_STEP_WEIGHT)) + 2):
        R, K, min_J = run.residual()
        verdict = run.verdict(R, min_J)
        if verdict == _AGAIN:
            continue
        if verdict == _OUT_OF_BUDGET:
            break
        if verdict is not None:
            return (run.z, *verdict)
        outcome = run.step(R, K)
        if outcome is not None:
            return (run.z, *outcome)
    linsolve.forget()
    return run.z, False, f"no convergence in {stats.newton_iterations_here} Newton iterations (|R|∞ {run.rnorm:.3g})"


_AGAIN, _OUT_OF_BUDGET = "again", "out of budget"  # _NewtonRun.verdict's answers that are not an outcome


@dataclass
class _NewtonRun:
    """The state of one _newton call between its iterations: the current state z, the state the last
    step started from, whether the held factorisation is the current tangent's (`fresh`) and whether
    the next assembly needs one, the first and last residuals, and the iteration budget used (a
    full step counts 1, a modified one MODIFIED_STEP_WEIGHT)."""

    problem: MechanicsProblem
    pressure_pa: float
    linsolve: SparseSolver
    stats: SolveStats
    force_scale: float
    reuse_factor: bool
    z: np.ndarray
    r_tol: float
    du_tol: float
    need_tangent: bool
    patient: bool = False
    fresh: bool = False
    z_before: np.ndarray | None = None
    known: tuple | None = None  # (R, min det F) already assembled at z, by the backtracking
    r0: float | None = None
    r_prev: float | None = None
    rnorm: float = float("nan")
    budget_used: float = 0.0
    first: int = 0  # where this run's residuals start in stats.residual_history

    @property
    def max_budget(self) -> float:
        return self.problem.fidelity.max_newton * (PATIENT_BUDGET_FACTOR if self.patient else 1)

    def out_of_budget(self) -> bool:
        """The preset's budget used up, or, when patient, the last PATIENT_WINDOW iterations cut |R|∞ by
        less than PATIENT_CONTRACTION an iteration or the extended budget is used up too."""
        if self.budget_used < self.problem.fidelity.max_newton:
            return False
        h, w = self.stats.residual_history[self.first:], PATIENT_WINDOW
        contracting = len(h) > w and h[-1] <= PATIENT_CONTRACTION ** w * h[-1 - w]
        return not (self.patient and contracting and self.budget_used < self.max_budget)

    def residual(self):
        """(R, K or None, min det F) at z: the backtracking's when it assembled them and no tangent is
        needed, else assembled (with the tangent when one is needed)."""
        if self.known is not None and not self.need_tangent:
            (R, min_J), K = self.known, None
        else:
            t0 = time.perf_counter()
            R, K, min_J = self.problem.assemble(self.z, self.pressure_pa, with_tangent=self.need_tangent)
            self.stats.assembly_s += time.perf_counter() - t0
        self.known = None
        self.rnorm = float(np.abs(R).max())
        self.stats.residual_history.append(self.rnorm)
        return R, K, min_J

    def verdict(self, R: np.ndarray, min_J: float):
        """What the residual at z says: (ok, reason) when the solve ends here, _AGAIN to assemble again
        (a step stepped back, or a stale tangent to refresh), _OUT_OF_BUDGET, or None to take a step."""
        rnorm, stats = self.rnorm, self.stats
        if self.z_before is not None and not self.fresh and not (np.isfinite(rnorm) and min_J > 0
                                                                 and rnorm <= self.r_prev):
            # a step with an old tangent made things worse (an inverse update's first step uses the
            # previous reference's tangent): go back to where it started and refactorise there
            self.z, self.z_before, self.need_tangent = self.z_before, None, True
            return _AGAIN
        if not np.isfinite(rnorm):
            self.linsolve.forget()
            return False, "non-finite residual"
        if min_J <= 0:
            self.linsolve.forget()
            return False, f"det F ≤ 0 (min {min_J:.3g})"
        stats.final_residual, stats.min_jacobian = rnorm, min_J
        if rnorm <= self.r_tol:
            return True, ""
        self.r0 = rnorm if self.r0 is None else self.r0
        if rnorm > 1e4 * max(self.r0, self.force_scale):
            self.linsolve.forget()
            return False, f"diverging residual {rnorm:.3g}"
        if not self.need_tangent and self.r_prev is not None and rnorm > STALE_TANGENT_RATE * self.r_prev:
            # the old tangent contracts too slowly here (but it did contract): refactorise at this state
            self.need_tangent = True
            return _AGAIN
        if self.out_of_budget():
            return _OUT_OF_BUDGET
        return None

    def step(self, R: np.ndarray, K):
        """One Newton step from z (on a fresh factorisation of K, or the held one): (ok, reason) when
        the solve ends with it (a singular tangent, or a full step below du_tol at a small residual),
        else None."""
        stats, problem = self.stats, self.problem
        t0 = time.perf_counter()
        if self.need_tangent:
            try:
                self.linsolve.factorize(K)
            except SingularMatrix:
                return False, "singular tangent"
        self.fresh = self.need_tangent
        try:
            dz = self.linsolve.solve_factored(-R)  # SingularMatrix: the symmetric part's LU fallback failed
        except SingularMatrix:
            return False, "singular tangent"
        stats.linear_s += time.perf_counter() - t0
        stats.newton_iterations += 1
        stats.newton_iterations_here += 1
        self.budget_used += 1.0 if self.fresh else MODIFIED_STEP_WEIGHT
        self.need_tangent = not self.reuse_factor
        self.r_prev = self.rnorm
        if not np.all(np.isfinite(dz)):
            self.linsolve.forget()
            return False, "singular tangent"
        self.z_before = self.z
        full_step_mm = float(np.abs(dz[:np.count_nonzero(problem.free < problem.n_u)]).max())
        if not self.fresh:
            self.z = self.z.copy()
            self.z[problem.free] += dz
            return None
        self.z, _, R, min_J = _backtrack(problem, self.z, dz, self.pressure_pa, self.rnorm, stats)
        self.known = (R, min_J)
        if full_step_mm <= self.du_tol:
            self.rnorm = rnorm = float(np.abs(R).max())
            stats.final_residual, stats.min_jacobian = rnorm, min_J
            if min_J > 0 and rnorm <= max(self.r_tol, 1e-3 * self.force_scale):
                return True, ""
        return None


def _backtrack(problem: MechanicsProblem, z: np.ndarray, dz: np.ndarray, pressure_pa: float, rnorm: float,
               stats: SolveStats) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The full Newton step z + α dz with the first α in BACKTRACK_STEPS whose residual |R|∞ does not
    exceed the current one (and det F > 0 everywhere), or else the α with the smallest residual.
    A full step accepted that cut |R|∞ by less than EXTEND_WHEN is tried at EXTENDED_STEP × dz as well,
    and that longer step is taken where its residual is lower and det F stays above EXTEND_MIN_J_SHARE
    of the full step's.
    Returns the new state, the step taken, and the residual and min det F there (reused by Newton).
    One residual assembly (no tangent) per trial, ~¼ of a tangent assembly's cost. From zero strain
    the Fung law's linearised step overshoots far into the stiff range; the line search saves Newton
    iterations and factorisations at the soft corners of the box. From a guess far up that range it
    undershoots (|R|∞ falls ~e× a full step), and the longer step saves them there."""
    best = None
    for alpha in BACKTRACK_STEPS:
        r, trial, R, min_J = _trial_step(problem, z, dz, alpha, pressure_pa, stats)
        if best is None or r < best[0]:
            best = (r, trial, alpha, R, min_J)
        if r <= rnorm:
            break
    if best[2] == 1.0 and EXTEND_WHEN * rnorm < best[0] <= rnorm:
        longer = _trial_step(problem, z, dz, EXTENDED_STEP, pressure_pa, stats)
        if longer[0] < best[0] and longer[3] >= EXTEND_MIN_J_SHARE * best[4]:
            best = (longer[0], longer[1], EXTENDED_STEP, longer[2], longer[3])
    _, trial, alpha, R, min_J = best
    return trial, alpha * dz, R, min_J


def _trial_step(problem: MechanicsProblem, z: np.ndarray, dz: np.ndarray, alpha: float, pressure_pa: float,
                stats: SolveStats) -> tuple[float, np.ndarray, np.ndarray, float]:
    """(|R|∞, the state z + α dz, R, min det F) at the trial step α; |R|∞ is ∞ where det F ≤ 0 or R is not
    finite."""
    trial = z.copy()
    trial[problem.free] += alpha * dz
    t0 = time.perf_counter()
    R, _, min_J = problem.assemble(trial, pressure_pa, with_tangent=False)
    stats.assembly_s += time.perf_counter() - t0
    r = float(np.abs(R).max()) if min_J > 0 else np.inf
    return (r if np.isfinite(r) else np.inf), trial, R, min_J


def _predict(problem: MechanicsProblem, z: np.ndarray, z_prev: np.ndarray, load_prev: float, load: float,
             target: float, pressure_pa: float, linsolve: SparseSolver) -> np.ndarray:
    """State predicted at `target`·P from the converged state z at `load`·P.

    Euler: along the load path's tangent, dz/dλ = −K⁻¹ P ∂R/∂P, with the tangent factorised by
    the last Newton iteration (one back-substitution). It lands nearer the converged state than the
    secant through the last two states (kept for when no factorisation of this size is held): from
    50 % to 100 % of 8 mmHg on a 250-node mesh, 1.2 mm off against the secant's 2.4 mm. With this
    predictor and no line search (`_backtrack`), a `fast` forward solve on 921 nodes takes 15 Newton
    iterations against the secant's 20 at 8 mmHg, 27 against 33 at the soft corner (14 mmHg, 50 Pa)."""
    if linsolve.size == problem.free.size:
        dz = linsolve.solve_factored(-pressure_pa * problem.pressure_load(z))
        if np.all(np.isfinite(dz)):
            guess = z.copy()
            guess[problem.free] += (target - load) * dz
            return guess
    return z + (z - z_prev) * (target - load) / (load - load_prev)


def first_load_step(problem: MechanicsProblem, pressure_pa: float) -> float:
    """The first load step's share of the load from zero strain: the preset's initial_load_step, at most
    FIRST_STEP_PRESSURE_PER_C · C / P (C the law's stiffness, Pa; P the cavity pressure, Pa), and no
    less than the preset's min_load_step."""
    fid = problem.fidelity
    step = fid.initial_load_step
    stiffness_pa = getattr(problem.material, "stiffness_pa", None)
    if stiffness_pa and pressure_pa:
        step = min(step, FIRST_STEP_PRESSURE_PER_C * stiffness_pa / abs(pressure_pa))
    return max(step, fid.min_load_step)


def force_scale_of(problem: MechanicsProblem, pressure_pa: float) -> float:
    """Typical nodal force (N·1e-6 in mm·Pa units): pressure × mean loaded facet area."""
    x = problem.nodes[problem.pressure_facets]
    area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1).mean()
    return max(abs(pressure_pa) * area, 1e-30)


def inflate(problem: MechanicsProblem, pressure_pa: float, z0: np.ndarray | None = None,
            start_load: float = 0.0, first_step: float | None = None,
            linsolve: SparseSolver | None = None, looseness: float = 1.0,
            reuse_factor: bool = False) -> tuple[np.ndarray, SolveStats]:
    """Quasi-static loading from `start_load`·P (state z0) to P with adaptive load steps.
    Intermediate steps are solved to a looser tolerance (INTERMEDIATE_LOOSENESS) than the final
    one; `looseness` scales the final tolerances (inverse FE tightens them as it converges).

    Raises SolveError with the reason when the step size collapses."""
    t_start = time.perf_counter()
    fid = problem.fidelity
    linsolve = linsolve or SparseSolver()
    stats = SolveStats()
    z = problem.zeros() if z0 is None else z0.copy()
    load = start_load
    if first_step is not None:
        step = first_step
    else:
        step = first_load_step(problem, pressure_pa) if start_load == 0.0 else fid.initial_load_step
    step = min(step, 1.0 - load)
    force_scale = force_scale_of(problem, pressure_pa)
    z_prev, load_prev = None, None
    if start_load >= 1.0:  # already at full load: correct the given state only
        stats.newton_iterations_here = 0
        z, ok, reason = _newton(problem, z, pressure_pa, linsolve, stats, force_scale, looseness, reuse_factor,
                                patient=True)
        stats.wall_s = time.perf_counter() - t_start
        if not ok:
            raise SolveError(f"Newton correction at full load failed ({reason})")
        stats.load_steps = 1
        return z, stats
    while load < 1.0 - 1e-12:
        target = min(1.0, load + step)
        if z_prev is not None and load > load_prev:
            guess = _predict(problem, z, z_prev, load_prev, load, target, pressure_pa, linsolve)
        else:
            guess = z
        iters_before = stats.newton_iterations
        stats.newton_iterations_here = 0
        loose = looseness if target >= 1.0 else max(looseness, INTERMEDIATE_LOOSENESS)
        z_new, ok, reason = _newton(problem, guess, target * pressure_pa, linsolve, stats, force_scale, loose)
        if not ok and z_prev is not None:
            stats.newton_iterations_here = 0
            z_new, ok, reason = _newton(problem, z, target * pressure_pa, linsolve, stats, force_scale, loose)
        if ok:
            z_prev, load_prev = z, load
            z, load = z_new, target
            stats.load_steps += 1
            report(f"load step {stats.load_steps}: {100 * load:.0f} % of the pressure, "
                   f"{stats.newton_iterations} Newton iterations")
            if stats.newton_iterations - iters_before <= 4:
                step = min(step * 2.0, 1.0)
            step = min(step, 1.0 - load) if load < 1.0 else step
        else:
            stats.step_cuts += 1
            step *= 0.5
            if step < fid.min_load_step:
                stats.wall_s = time.perf_counter() - t_start
                raise SolveError(f"step size collapsed at {100 * load:.1f}% of load ({reason}; "
                                 f"min det F {problem.min_jacobian(z):.3g}, |R|∞ {stats.final_residual:.3g})")
    stats.min_jacobian = problem.min_jacobian(z)
    stats.wall_s = time.perf_counter() - t_start
    return z, stats
