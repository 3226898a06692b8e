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
# intermediate load steps: |R|∞ ≤ 1e-2 P·area, 1 % of a typical nodal force at full load (the increment
# test, |Δu| ≤ 1 mm at this looseness, still needs that residual). Their states only start the next
# step, and the last step is solved to the full tolerance. Over 33 forward solves
# (800 nodes; the corners of two extreme shapes and of shape 0, and three mid cases): 1e4 478
# factorisations, 1e5 426, 1e7 351, 1e8 327; at 1e9 one solve failed (its load steps collapsed), so
# 1e7 keeps a 100× margin
INTERMEDIATE_LOOSENESS = 1e7


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
            stats: SolveStats, force_scale: float, looseness: float = 1.0, reuse_factor: bool = False):
    """Newton iterations at a fixed load. With `reuse_factor`, reuse the last factorisation while it still
    contracts the residual fast (modified Newton) and refactorising otherwise.

    Converged when |R|∞ ≤ rtol·force_scale·looseness, or when a full-Newton update is below
    increment_tol_mm·looseness (the residual is then checked once more). Returns (z, ok, reason)."""
    fid = problem.fidelity
    free = problem.free
    n_u_free = np.count_nonzero(free < problem.n_u)
    r_tol = fid.residual_rtol * force_scale * looseness
    du_tol = fid.increment_tol_mm * looseness
    r0 = None
    r_prev = None
    rnorm = float("nan")
    fresh = False  # does the factorisation belong to the current state's tangent?
    # a held factorisation serves only a tangent of this problem's size (a workspace holds one solver
    # for problems of several supports)
    need_tangent = not (reuse_factor and linsolve.size == problem.free.size)
    z_before = None  # the state the last step started from
    known = None  # (R, min det F) already assembled at z, by the backtracking
    budget_used = 0.0  # max_newton counts full steps; a modified step counts MODIFIED_STEP_WEIGHT
    # a pass that only refreshes a tangent or steps back solves nothing: at most two passes per solve
    for _ in range(2 * int(np.ceil(fid.max_newton / MODIFIED_STEP_WEIGHT)) + 2):
        if known is not None and not need_tangent:
            (R, min_J), K = known, None
        else:
            t0 = time.perf_counter()
            R, K, min_J = problem.assemble(z, pressure_pa, with_tangent=need_tangent)
            stats.assembly_s += time.perf_counter() - t0
        known = None
        rnorm = float(np.abs(R).max())
        stats.residual_history.append(rnorm)
        if z_before is not None and not fresh and not (np.isfinite(rnorm) and min_J > 0 and rnorm <= r_prev):
            # a step with an old tangent made things worse (an inverse update's first step uses the
            # previous reference's tangent): go back to where it started and refactorise there
            z, z_before, need_tangent = z_before, None, True
            continue
        if not np.isfinite(rnorm):
            linsolve.forget()
            return z, False, "non-finite residual"
        if min_J <= 0:
            linsolve.forget()
            return z, False, f"det F ≤ 0 (min {min_J:.3g})"
        stats.final_residual, stats.min_jacobian = rnorm, min_J
        if rnorm <= r_tol:
            return z, True, ""
        r0 = rnorm if r0 is None else r0
        if rnorm > 1e4 * max(r0, force_scale):
            linsolve.forget()
            return z, False, f"diverging residual {rnorm:.3g}"
        if not need_tangent and r_prev is not None and rnorm > STALE_TANGENT_RATE * r_prev:
            # the old tangent contracts too slowly here (but it did contract): refactorise at this state
            need_tangent = True
            continue
        if budget_used >= fid.max_newton:
            break
        t0 = time.perf_counter()
        if need_tangent:
            try:
                linsolve.factorize(K)
            except SingularMatrix:
                return z, False, "singular tangent"
            fresh = True
        else:
            fresh = False
        try:
            dz = linsolve.solve_factored(-R)  # SingularMatrix: the symmetric part's LU fallback failed
        except SingularMatrix:
            return z, False, "singular tangent"
        stats.linear_s += time.perf_counter() - t0
        stats.newton_iterations += 1
        stats.newton_iterations_here += 1
        budget_used += 1.0 if fresh else MODIFIED_STEP_WEIGHT
        need_tangent = not reuse_factor
        r_prev = rnorm
        if not np.all(np.isfinite(dz)):
            linsolve.forget()
            return z, False, "singular tangent"
        z_before = z
        full_step_mm = float(np.abs(dz[:n_u_free]).max())
        if fresh:
            z, _, R, min_J = _backtrack(problem, z, dz, pressure_pa, rnorm, stats)
            known = (R, min_J)
        else:
            z = z.copy()
            z[free] += dz
        if fresh and full_step_mm <= du_tol:
            rnorm = float(np.abs(R).max())
            stats.final_residual, stats.min_jacobian = rnorm, min_J
            if min_J > 0 and rnorm <= max(r_tol, 1e-3 * force_scale):
                return z, True, ""
    linsolve.forget()
    return z, False, f"no convergence in {fid.max_newton} Newton iterations (|R|∞ {rnorm:.3g})"


def _backtrack(problem: MechanicsProblem, z: np.ndarray, dz: np.ndarray, pressure_pa: float, rnorm: float,
               stats: SolveStats) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The full Newton step z + α dz with the first α in BACKTRACK_STEPS whose residual |R|∞ does not
    exceed the current one (and det F > 0 everywhere), or else the α with the smallest residual.
    Returns the new state, the step taken, and the residual and min det F there (reused by Newton).
    One residual assembly (no tangent) per trial, ~¼ of a tangent assembly's cost. From zero strain
    the Fung law's linearised step overshoots far into the stiff range. On shape 0 (921 nodes, `fast`),
    a forward solve at the soft corner (14 mmHg, 50 Pa) took 20 Newton iterations instead of 27 and
    its pair 2.2 s instead of 3.1 s (best of three); over 33 forward solves (the corners of two extreme
    shapes and of shape 0, plus three mid cases; 800 nodes), 478 factorisations instead of 579."""
    best = None
    for alpha in BACKTRACK_STEPS:
        trial = z.copy()
        trial[problem.free] += alpha * dz
        t0 = time.perf_counter()
        R, _, min_J = problem.assemble(trial, pressure_pa, with_tangent=False)
        stats.assembly_s += time.perf_counter() - t0
        r = float(np.abs(R).max()) if min_J > 0 else np.inf
        r = r if np.isfinite(r) else np.inf
        if best is None or r < best[0]:
            best = (r, trial, alpha, R, min_J)
        if r <= rnorm:
            break
    _, trial, alpha, R, min_J = best
    return trial, alpha * dz, R, min_J


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
    step = first_step if first_step is not None else fid.initial_load_step
    step = min(step, 1.0 - load)
    force_scale = force_scale_of(problem, pressure_pa)
    z_prev, load_prev = None, None
    if start_load >= 1.0:  # already at full load: correct the given state only
        stats.newton_iterations_here = 0
        z, ok, reason = _newton(problem, z, pressure_pa, linsolve, stats, force_scale, looseness, reuse_factor)
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
