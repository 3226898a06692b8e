"""LV inflation problems on a tagged mesh: forward (unloaded → loaded), inverse (ED → unloaded by
backward-displacement fixed point) and the training pair (inverse, then forward). No Ray, Zarr
or torch here: the orchestrator schedules these functions as they are."""
from __future__ import annotations

import time
from contextlib import nullcontext
from dataclasses import dataclass, field

import numpy as np

from .anderson import Anderson
from .assembly import MechanicsProblem, Supports
from .elements import quadrature_barycentric
from .fibres import rule_frames
from .fidelity import Fidelity, get_fidelity
from .forward import SolveError, SolveStats, inflate
from .inverse_failure import STALL_GAIN, STALL_UPDATES, InverseError, stalled, where_largest
from .inverse_newton import newton_krylov_step
from .linear import SingularMatrix, SparseSolver
from .material import FungParameters
from .mesh import MeshError, TetMesh, check_geometry
from .parameters import BASE_CONDITIONS, FIBRE_RULES, CaseParameters
from .progress import report
from .refine import refine_uniform, refined_unloaded

EPI_SPRING_PA_PER_MM = 9.0  # the original pipeline's 90 Pa per unit length, with lengths in cm


NEWTON_HALVINGS = 4
NEWTON_WHEN_SLOWER = 0.5  # a Newton step once an update cut the mismatch by less than this
NEWTON_JACOBIAN_FRAMES = False  # the products hold X's fibre frames: as many updates, cheaper products
ROUGH_FIRST_STATE_FORCE = 0.1  # rough_first_state: stop at |R|∞ ≤ this × P · (mean endo facet area)


def _supports(mesh: TetMesh, base: str) -> Supports:
    """sliding: base z fixed, in-plane rigid motions removed; clamped: base fixed; spring: sliding
    plus a normal spring on the epicardium; heartfem: as spring, but the rigid motions are removed
    the original pipeline's way (∫u_x = ∫u_y = 0, ∫X × u = 0 over the wall)."""
    if base == "sliding":
        return Supports(mesh.base, (2,), gauge=True)
    if base == "spring":
        return Supports(mesh.base, (2,), gauge=True, spring_facets=mesh.epi, spring_pa_per_mm=EPI_SPRING_PA_PER_MM)
    if base == "heartfem":
        return Supports(mesh.base, (2,), gauge=True, gauge_region="volume", spring_facets=mesh.epi,
                        spring_pa_per_mm=EPI_SPRING_PA_PER_MM)
    if base == "clamped":
        return Supports(mesh.base, (0, 1, 2), gauge=False)
    raise ValueError(f"unknown base condition {base!r}; choose {' or '.join(BASE_CONDITIONS)}")


def _frames(mesh: TetMesh, params: CaseParameters, fidelity: Fidelity, fibres: str = "laplace") -> np.ndarray:
    lam = quadrature_barycentric(fidelity.quad_degree)
    return rule_frames(fibres, mesh, params.helix_endo_deg, params.helix_epi_deg, lam,
                       order=fidelity.displacement_order)


def lv_problem(mesh: TetMesh, params: CaseParameters, fidelity: Fidelity | str, base: str = "sliding",
               material: FungParameters | None = None, fibres: str = "laplace") -> MechanicsProblem:
    """Fibres are computed on `mesh` (the stress-free configuration) by the rule `fibres`:
    "laplace" (Laplace transmural coordinate, ours) or "heartfem" (the original dataset's)."""
    if fibres not in FIBRE_RULES:
        raise ValueError(f"unknown fibre rule {fibres!r}; choose {' or '.join(FIBRE_RULES)}")
    fidelity = get_fidelity(fidelity) if isinstance(fidelity, str) else fidelity
    material = material or FungParameters(params.stiffness_pa)
    return MechanicsProblem(mesh.nodes, mesh.tets, mesh.endo, _supports(mesh, base), fidelity, material,
                            _frames(mesh, params, fidelity, fibres))


class PairWorkspace:
    """What consecutive pairs on one ED mesh share: the FE problem of each (preset, base, fibre rule,
    stiffness), so its sparsity pattern and P2 dof map are built once, and the sparse solver, so
    PARDISO's analysis is done once. `orchestrator.tasks.run_chain` keeps one per pressure chain; the
    pairs it solves equal those solved alone to round-off. A problem it hands out is re-pointed
    (`set_reference`) by the next pair. Use it as a context manager: leaving frees the solver's memory."""

    def __init__(self, ed_mesh: TetMesh):
        self.tets = ed_mesh.tets
        self.linsolve = SparseSolver()
        self._problems: dict[tuple, MechanicsProblem] = {}
        self._solved: dict[tuple, list[tuple[float, np.ndarray, np.ndarray]]] = {}  # key → [(P, X, loaded)]
        self._refined: tuple[int, TetMesh, PairWorkspace] | None = None

    def refined(self, ed_mesh: TetMesh, levels: int) -> tuple[TetMesh, "PairWorkspace"]:
        """`refine_uniform(ed_mesh, levels)` and its own workspace, built once (again for another
        level or ED geometry): where a preset with `refinement_levels` solves the pairs of this chain."""
        if (self._refined is None or self._refined[0] != levels
                or not np.array_equal(self._refined[1].nodes[: ed_mesh.n_nodes], ed_mesh.nodes)):
            if self._refined is not None:
                self._refined[2].close()
            fine = refine_uniform(ed_mesh, levels)
            self._refined = (levels, fine, PairWorkspace(fine))
        return self._refined[1], self._refined[2]

    def _key_of(self, problem: MechanicsProblem) -> tuple | None:
        return next((k for k, p in self._problems.items() if p is problem), None)

    @staticmethod
    def _key(params: CaseParameters, fidelity: Fidelity, base: str, fibres: str) -> tuple:
        return (fidelity, base, fibres, params.stiffness_pa)

    def problem(self, mesh: TetMesh, params: CaseParameters, fidelity: Fidelity, base: str,
                fibres: str) -> MechanicsProblem:
        """`lv_problem(mesh, params, fidelity, base, fibres=fibres)`, reusing the problem built for
        the same preset, base, fibre rule and stiffness (a pair's parameters that change between
        pairs, P and the helix angles, enter only through the load and the fibres set here)."""
        if mesh.tets is not self.tets and not np.array_equal(mesh.tets, self.tets):
            raise ValueError("a pair workspace serves one mesh topology; this mesh has other tets")
        key = self._key(params, fidelity, base, fibres)
        problem = self._problems.get(key)
        if problem is None:
            problem = self._problems[key] = lv_problem(mesh, params, fidelity, base, fibres=fibres)
        else:
            problem.set_reference(mesh.nodes, _frames(mesh, params, fidelity, fibres))
        return problem

    def remember(self, problem: MechanicsProblem, pressure_mmhg: float, state: np.ndarray) -> None:
        """Keep a solved pair (`problem` set on its unloaded geometry, `state` its final unknowns): the
        unloaded geometry, the loaded configuration (every displacement dof's position, mm) and the
        rest of the unknowns (pressure field, gauge multipliers), for the next pair's `unloaded_guess`
        and `loaded_guess`."""
        key = self._key_of(problem)
        if key is None:  # not a problem of this workspace
            return
        u, _ = problem.split(state)
        loaded = np.concatenate([(problem.dofmap.points + u).ravel(), state[problem.n_u:]])
        solved = self._solved.setdefault(key, [])
        solved.append((float(pressure_mmhg), problem.nodes.copy(), loaded))
        del solved[:-2]  # the extrapolation uses the last two

    def unloaded_guess(self, params: CaseParameters, fidelity: Fidelity, base: str, fibres: str) -> np.ndarray | None:
        """`unloaded_guess` from the remembered pairs of this preset, base, fibre rule and stiffness."""
        solved = [(p, X) for p, X, _ in self._solved.get(self._key(params, fidelity, base, fibres), [])]
        return _extrapolate_in_pressure(solved, params.pressure_mmhg)

    def loaded_guess(self, problem: MechanicsProblem, pressure_mmhg: float, x_ed: np.ndarray) -> np.ndarray | None:
        """A starting state for `problem` (already set on the trial unloaded geometry X) at
        `pressure_mmhg`: the remembered loaded configurations and pressure fields extrapolated in P
        (`unloaded_guess`'s rule), as a displacement from X, with the vertices exactly on `x_ed`.
        None before a pair of this problem is remembered. Where the vertex-only start
        (`_state_from_vertices`: straight edges, zero pressure field) is far from equilibrium, this
        one starts with the curved edges and the pressure field of the neighbouring pairs, whose
        first residual is 1e2–1e3× smaller on an `accurate` chain."""
        solved = [(p, loaded) for p, _, loaded in self._solved.get(self._key_of(problem), [])]
        extrapolated = _extrapolate_in_pressure(solved, pressure_mmhg)
        if extrapolated is None:
            return None
        u = extrapolated[: problem.n_u].reshape(-1, 3) - problem.dofmap.points
        u[: len(x_ed)] = x_ed - problem.nodes
        guess = np.concatenate([u.ravel(), extrapolated[problem.n_u:]])
        z = problem.zeros()  # the supported components stay zero
        z[problem.free] = guess[problem.free]
        return z

    def close(self) -> None:
        self.linsolve.free()
        if self._refined is not None:
            self._refined[2].close()

    def __enter__(self) -> "PairWorkspace":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class ForwardResult:
    loaded_nodes: np.ndarray  # [n, 3] mm
    displacement: np.ndarray  # [n, 3] mm, at the mesh nodes
    stats: SolveStats
    state: np.ndarray = field(repr=False, default=None)  # full unknown vector (warm starts)


def forward_solve(mesh: TetMesh, params: CaseParameters, fidelity: Fidelity | str = "accurate",
                  base: str = "sliding", linsolve: SparseSolver | None = None,
                  initial_state: np.ndarray | None = None, fibres: str = "laplace") -> ForwardResult:
    """Inflate the stress-free `mesh` to ED pressure, from zero load with adaptive steps; or, given
    `initial_state` (a full unknown vector near the loaded equilibrium), by Newton at full load,
    falling back to load stepping. Raises SolveError if it does not converge.

    A preset with `refinement_levels` solves on the refined mesh and answers at `mesh`'s nodes (no
    state: `initial_state` does not apply there)."""
    fid = get_fidelity(fidelity) if isinstance(fidelity, str) else fidelity
    if fid.refinement_levels:
        fine = forward_solve(refine_uniform(mesh, fid.refinement_levels), params, fid.unrefined(), base, linsolve,
                             fibres=fibres)
        n = mesh.n_nodes
        return ForwardResult(fine.loaded_nodes[:n].copy(), fine.displacement[:n].copy(), fine.stats)
    problem = lv_problem(mesh, params, fid, base, fibres=fibres)
    return _inflate_problem(problem, mesh, params, linsolve, initial_state)


def _inflate_problem(problem: MechanicsProblem, mesh: TetMesh, params: CaseParameters,
                     linsolve: SparseSolver | None, initial_state: np.ndarray | None,
                     reuse_factor: bool = False) -> ForwardResult:
    """forward_solve on a problem already set up on `mesh` for this case (`make_pair` passes the
    inverse's, on the unloaded geometry it found: no second sparsity and fibre build, and its last
    factorised tangent for modified Newton with `reuse_factor`)."""
    z = None
    if initial_state is not None:
        try:
            z, stats = inflate(problem, params.pressure_pa, z0=initial_state, start_load=1.0, linsolve=linsolve,
                               reuse_factor=reuse_factor)
        except SolveError:
            z = None
    if z is None:
        z, stats = inflate(problem, params.pressure_pa, linsolve=linsolve)
    u = problem.split(z)[0][: mesh.n_nodes]
    return ForwardResult(mesh.nodes + u, u.copy(), stats, z)


@dataclass
class InverseResult:
    unloaded_nodes: np.ndarray  # [n, 3] mm
    mismatch_mm: float  # max nodal |x(X) − x_ED| at exit
    updates: int
    stats: SolveStats
    mismatch_history: list
    state: np.ndarray = field(repr=False, default=None)  # final unknown vector (warm starts)
    problem: MechanicsProblem = field(repr=False, default=None)  # set up on the unloaded geometry


def inverse_solve(ed_mesh: TetMesh, params: CaseParameters, fidelity: Fidelity | str = "accurate",
                  base: str = "sliding", initial_unloaded: np.ndarray | None = None,
                  tol_mm: float | None = None, linsolve: SparseSolver | None = None,
                  reuse_factor: bool = True, fibres: str = "laplace",
                  workspace: PairWorkspace | None = None, max_updates: int | None = None,
                  rough_first_state: bool = False) -> InverseResult:
    """Unloaded geometry X with x(X) = x_ED, by the backward-displacement fixed point
    X ← X − (x(X) − x_ED) (Anderson-accelerated), each re-solve warm-started from the previous
    displacement field shifted so that the trial reference maps exactly onto x_ED (for the plain
    update, the previous field itself). With the preset's inverse_step "newton", an update that cut the
    mismatch by less than NEWTON_WHEN_SLOWER is followed by a Newton–Krylov step (`_newton_update`),
    whose re-solve starts from the state it predicts.

    Fibres are recomputed on each trial reference (they are defined on the stress-free state),
    so forward_solve(unloaded) reproduces x_ED. `initial_unloaded` (from the network, or from a
    cheaper preset) replaces X0 = x_ED (`_first_state`). Stops when the max nodal mismatch ≤ tol_mm.

    `max_updates` k: stop after at most k fixed-point updates and return that reference with its
    mismatch, met tolerance or not (a fixed budget asked for by the caller: `bench trade`'s
    "network guess + k updates"); without it, not reaching tol_mm in the preset's updates raises
    InverseError, and so does an inverse that stalls or diverges first (`inverse_failure.stalled`: 10
    updates without a mismatch below 0.9 × the best before them) or whose update folds the reference.

    `rough_first_state` (a guess whose error is tenths of a mm, such as a network's): the first forward
    solve on the guessed reference stops at |R|∞ ≤ ROUGH_FIRST_STATE_FORCE · P · (mean endo facet area)
    instead of the preset's tolerance × 1e3. The guess's own error is far larger than what the last Newton
    iterations would remove, and the updates that follow tighten their re-solves as the mismatch falls,
    so the answer is the same to the inverse's tolerance, for fewer factorisations (docs/benchmarks.md).

    `reuse_factor`: each re-solve is modified Newton, keeping a factorised tangent while it still
    cuts the residual 4× per back-substitution: a re-solve starts close to its answer, so most need no
    new factorisation. Load stepping from zero keeps full Newton, where reuse costs more than it
    saves. A step with the previous reference's tangent that makes things worse steps back and
    refactorises (`forward._newton`)."""
    fid = get_fidelity(fidelity) if isinstance(fidelity, str) else fidelity
    if fid.refinement_levels:
        return _refined_inverse(ed_mesh, params, fid, base, initial_unloaded, tol_mm, fibres)
    tol = fid.inverse_tol_mm if tol_mm is None else tol_mm
    budget = fid.max_inverse_updates if max_updates is None else int(max_updates)
    if budget < 0:
        raise ValueError(f"max_updates must be ≥ 0, got {max_updates}")
    t_start = time.perf_counter()
    x_ed = ed_mesh.nodes
    X = x_ed.copy() if initial_unloaded is None else np.array(initial_unloaded, dtype=float)
    if X.shape != x_ed.shape or not np.all(np.isfinite(X)):
        raise ValueError("initial unloaded guess must be finite and have one point per ED node")
    check_geometry(X, ed_mesh.tets)
    linsolve = linsolve or (workspace.linsolve if workspace is not None else SparseSolver())
    problem = (workspace.problem(ed_mesh.with_nodes(X), params, fid, base, fibres) if workspace is not None
               else lv_problem(ed_mesh.with_nodes(X), params, fid, base, fibres=fibres))
    stats, history, accel = SolveStats(), [], Anderson(memory=5)
    rough = rough_first_state and initial_unloaded is not None
    first_looseness = ROUGH_FIRST_STATE_FORCE / fid.residual_rtol if rough else 1e3
    z, st = _first_state(problem, params, x_ed, X, initial_unloaded is not None, workspace, linsolve, reuse_factor,
                         first_looseness)
    stats.add(st)
    for update in range(budget + 1):
        mismatch = X + problem.split(z)[0][:ed_mesh.n_nodes] - x_ed
        err = float(np.linalg.norm(mismatch, axis=1).max())
        history.append(err)
        report(f"inverse update {update}: mismatch {err:.2e} mm (stops at {tol:g} mm)")
        if err <= tol or (max_updates is not None and update == budget):
            stats.wall_s = time.perf_counter() - t_start
            stats.min_jacobian = problem.min_jacobian(z)
            return InverseResult(X, err, update, stats, history, z, problem)
        if update == budget:
            break
        if stalled(history):
            raise InverseError(f"inverse FE stalled: the mismatch stayed above {STALL_GAIN:g} × its best "
                               f"({min(history[:-STALL_UPDATES]):.3g} mm) for {STALL_UPDATES} updates "
                               f"(now {err:.3g} mm, {where_largest(mismatch, x_ed)}; update {update})")
        X, z = _update_reference(problem, z, X, mismatch, history, accel, stats,
                                 _UpdateContext(ed_mesh, params, fid, fibres, linsolve, reuse_factor, update))
    raise InverseError(f"inverse FE did not reach {tol:g} mm in {fid.max_inverse_updates} updates "
                       f"(mismatch {history[-1]:.3g} mm, {where_largest(mismatch, x_ed)})")


def _first_state(problem: MechanicsProblem, params: CaseParameters, x_ed: np.ndarray, X: np.ndarray, guessed: bool,
                 workspace: PairWorkspace | None, linsolve: SparseSolver, reuse_factor: bool, looseness: float = 1e3):
    """(state, stats) of the first forward solve on the reference X, to the preset's tolerance × `looseness`
    (inverse_solve's `rough_first_state`: far looser from a guess). From a `guessed` reference it
    starts from u0 = x_ED − X at full load, or, with a `workspace` that has solved pairs of this
    problem, from their loaded states extrapolated to this pressure (`PairWorkspace.loaded_guess`), by
    modified Newton on the factorisation the workspace holds; load stepping from zero when that fails,
    and always from x_ED itself."""
    if guessed:
        z0 = workspace.loaded_guess(problem, params.pressure_mmhg, x_ed) if workspace is not None else None
        try:
            return inflate(problem, params.pressure_pa, z0=_state_from_vertices(problem, x_ed - X) if z0 is None
                           else z0, start_load=1.0, linsolve=linsolve, looseness=looseness,
                           reuse_factor=reuse_factor and z0 is not None)
        except SolveError:
            pass
    return inflate(problem, params.pressure_pa, linsolve=linsolve, looseness=looseness)


@dataclass(frozen=True)
class _UpdateContext:
    """What every update of one inverse solve shares: the ED mesh, the case, the preset, the fibre rule,
    the linear solver, whether re-solves keep a factorisation, and the update's number."""

    ed_mesh: TetMesh
    params: CaseParameters
    fid: Fidelity
    fibres: str
    linsolve: SparseSolver
    reuse_factor: bool
    update: int


def _update_reference(problem: MechanicsProblem, z_prev: np.ndarray, X_prev: np.ndarray, mismatch: np.ndarray,
                      history: list, accel, stats: SolveStats, ctx: _UpdateContext) -> tuple[np.ndarray, np.ndarray]:
    """(X, z): the next trial reference and its re-solved state. The accelerated (or Newton) step is
    tried first; a trial that folds an element or whose re-solve fails falls back to the plain update
    X_prev − mismatch, whose failure raises SolveError."""
    # inexact inner solves: stop each re-solve when its residual, turned into a displacement
    # error (|R| · mean|u| / (P · area)), is ~1000× below the current mismatch
    n = ctx.ed_mesh.n_nodes
    u_mean = float(np.linalg.norm(problem.split(z_prev)[0][:n], axis=1).mean()) + 1e-3
    looseness = float(np.clip(1e-3 * history[-1] / (u_mean * ctx.fid.residual_rtol), 1.0, 1e6))
    for accelerated in (True, False):
        predicted = frames = None
        if not accelerated:
            X = X_prev - mismatch
        elif (ctx.fid.inverse_step == "newton" and len(history) >= 2
              and history[-1] > NEWTON_WHEN_SLOWER * history[-2]):
            X, predicted, frames, products = _newton_update(problem, z_prev, ctx.params, mismatch, ctx.linsolve,
                                                            ctx.ed_mesh, ctx.fid, ctx.fibres)
            stats.jacobian_products += products
        else:
            X = accel.step(X_prev, mismatch)
        try:
            check_geometry(X, ctx.ed_mesh.tets)  # a folded trial reference is a failure, not data
            if frames is None:  # (a Newton trial's frames were made when it was checked)
                frames = _frames(ctx.ed_mesh.with_nodes(X), ctx.params, ctx.fid, ctx.fibres)
            problem.set_reference(X, frames)
            # starts: Newton's predicted state, then where the trial reference maps exactly onto x_ED
            # (the previous field, moved by how far the accelerated step lands from the plain one)
            starts = [predicted] if predicted is not None else []
            starts.append(z_prev + _state_from_vertices(problem, X_prev - mismatch - X))
            z, st = _resolve(problem, ctx.params.pressure_pa, starts, ctx.linsolve, looseness, ctx.reuse_factor)
            stats.add(st)
            return X, z
        except (SolveError, MeshError) as exc:
            accel.reset()
            if not accelerated:
                if isinstance(exc, MeshError):
                    raise InverseError(f"inverse update {ctx.update + 1} produced an invalid reference ({exc}; "
                                       f"mismatch before it {where_largest(mismatch, ctx.ed_mesh.nodes)})") from None
                raise


def _newton_update(problem: MechanicsProblem, z: np.ndarray, params: CaseParameters, mismatch: np.ndarray,
                   linsolve: SparseSolver, ed_mesh: TetMesh, fid: Fidelity, fibres: str):
    """The Newton–Krylov trial reference X + δ (solver/inverse_newton.py) and its predicted state, δ halved
    (up to NEWTON_HALVINGS times) while the trial folds an element or the predicted state inverts one (far
    from the answer a near-singular Jacobian overshoots), the trial's fibre frames (None when every
    halving failed) and the Jacobian–vector products it took."""
    X = problem.nodes.copy()
    delta, predicted, products = newton_krylov_step(
        problem, z, params.pressure_pa, mismatch, linsolve,
        frames_of=(lambda Y: _frames(ed_mesh.with_nodes(Y), params, fid, fibres)) if NEWTON_JACOBIAN_FRAMES else None)
    for _ in range(NEWTON_HALVINGS):
        trial = X + delta
        try:
            check_geometry(trial, ed_mesh.tets)
            frames = _frames(ed_mesh.with_nodes(trial), params, fid, fibres)
            problem.set_reference(trial, frames)
            if problem.min_jacobian(predicted) > 0:
                return trial, predicted, frames, products
        except MeshError:
            pass
        delta, predicted = 0.5 * delta, z + 0.5 * (predicted - z)
    return X + delta, predicted, None, products


def _resolve(problem: MechanicsProblem, pressure_pa: float, starts: list, linsolve: SparseSolver,
             looseness: float, reuse_factor: bool):
    """Equilibrium on problem's (new) reference: Newton at full load from each start in turn, then load
    stepping from zero."""
    for z0 in starts:
        try:
            return inflate(problem, pressure_pa, z0=z0, start_load=1.0, linsolve=linsolve, looseness=looseness,
                           reuse_factor=reuse_factor)
        except SolveError:
            continue
    return inflate(problem, pressure_pa, linsolve=linsolve, looseness=looseness)


def displacement_at_dofs(inverse: InverseResult) -> np.ndarray:
    """The inverse's final displacement u = x − X at every node of its element [n_dofs, 3] (P2: the
    vertices, then the edge midpoints in the order of `refine.refine_uniform`'s new nodes)."""
    return inverse.problem.split(inverse.state)[0].copy()


def _refined_guess(ed_mesh: TetMesh, params: CaseParameters, fid: Fidelity, base: str,
                   initial_unloaded: np.ndarray | None, fibres: str) -> np.ndarray | None:
    """The starting unloaded geometry on the refined mesh: `initial_unloaded` interpolated onto the
    refined nodes, or, without one, the `coarse_guess` preset's answer on `ed_mesh` (to 0.01 mm)
    carried there by `refined_unloaded`."""
    if initial_unloaded is not None:
        return refined_unloaded(ed_mesh, initial_unloaded, levels=fid.refinement_levels)
    if not fid.coarse_guess:
        return None
    coarse = inverse_solve(ed_mesh, params, fid.coarse_guess, base, tol_mm=1e-2, fibres=fibres)
    return refined_unloaded(ed_mesh, coarse.unloaded_nodes, displacement_at_dofs(coarse), fid.refinement_levels)


def _refined_inverse(ed_mesh: TetMesh, params: CaseParameters, fid: Fidelity, base: str,
                     initial_unloaded: np.ndarray | None, tol_mm: float | None, fibres: str) -> InverseResult:
    """inverse_solve on the refined ED mesh, answered at `ed_mesh`'s vertices (its first nodes). The
    result has no state or problem (they belong to the refined mesh; make_pair handles refinement itself)."""
    t0 = time.perf_counter()
    fine_ed = refine_uniform(ed_mesh, fid.refinement_levels)
    guess = _refined_guess(ed_mesh, params, fid, base, initial_unloaded, fibres)
    fine = inverse_solve(fine_ed, params, fid.unrefined(), base, guess, tol_mm, fibres=fibres)
    fine.stats.wall_s = time.perf_counter() - t0
    return InverseResult(fine.unloaded_nodes[: ed_mesh.n_nodes].copy(), fine.mismatch_mm, fine.updates, fine.stats,
                         fine.mismatch_history)


def linear_response(mesh: TetMesh, params: CaseParameters, fidelity: Fidelity | str = "fast",
                    base: str = "sliding", fibres: str = "laplace") -> np.ndarray:
    """Nodal displacement per unit cavity pressure, mm/Pa, of `mesh` as the stress-free state: one
    linear solve with the tangent at zero strain (the small-load limit of `forward_solve`, with the
    same supports, fibres and material; ∝ 1/C). Costs one assembly and one factorisation, a few per
    cent of a forward solve. Raises SolveError when the tangent is singular."""
    problem = lv_problem(mesh, params, fidelity, base, fibres=fibres)
    z = problem.zeros()
    R, K, _ = problem.assemble(z, 1.0)
    with SparseSolver() as linsolve:
        try:
            dz = linsolve.solve(K, -R)
        except SingularMatrix:
            dz = np.full(K.shape[0], np.nan)
    # PARDISO perturbs tiny pivots instead of failing: a singular tangent shows in the residual
    if not (np.all(np.isfinite(dz)) and np.linalg.norm(K @ dz + R) <= 1e-6 * np.linalg.norm(R)):
        raise SolveError("singular tangent at zero strain")
    z[problem.free] += dz
    return problem.split(z)[0][: mesh.n_nodes].copy()


def unloaded_guess(solved: list[tuple[float, np.ndarray]], pressure_mmhg: float) -> np.ndarray | None:
    """A starting unloaded geometry (mm) for the inverse at `pressure_mmhg`, from solved unloaded
    geometries of the same ED mesh, stiffness and fibres at other pressures, `solved` = [(P mmHg,
    X [n, 3])] in the order solved: the last X alone, or the straight line in P through the last two.
    None without a solved pressure. The inverse still iterates to its own tolerance; the guess only
    saves load steps and fixed-point updates (a pressure chain of `fast` pairs: 2–3× fewer Newton
    iterations, docs/data.md)."""
    return _extrapolate_in_pressure(solved, pressure_mmhg)


def _extrapolate_in_pressure(solved: list[tuple[float, np.ndarray]], pressure_mmhg: float) -> np.ndarray | None:
    """From [(P mmHg, array)] in the order solved: the last array alone, or the straight line in P
    through the last two, at `pressure_mmhg`; None for an empty list."""
    if not solved:
        return None
    p1, x1 = solved[-1]
    if len(solved) == 1 or solved[-2][0] == p1:
        return np.array(x1, dtype=float)
    p0, x0 = solved[-2]
    return x1 + (x1 - x0) * ((pressure_mmhg - p1) / (p1 - p0))


def _state_from_vertices(problem: MechanicsProblem, u_vertices: np.ndarray) -> np.ndarray:
    """Unknown vector with vertex displacements u_vertices (edge dofs: mean of their ends), p = 0."""
    z = problem.zeros()
    u = problem.split(z)[0]
    n = problem.dofmap.n_vertices
    u[:n] = u_vertices
    if problem.dofmap.order == 2:
        ends = problem.dofmap.edge_vertices
        u[n:] = 0.5 * (u_vertices[ends[:, 0]] + u_vertices[ends[:, 1]])
    fixed = np.setdiff1d(np.arange(problem.n_u), problem.free[problem.free < problem.n_u])
    z[fixed] = 0.0
    return z


@dataclass
class Pair:
    unloaded_nodes: np.ndarray
    loaded_nodes: np.ndarray
    inverse: InverseResult
    forward: ForwardResult
    stats: dict


def make_pair(ed_mesh: TetMesh, params: CaseParameters, fidelity: Fidelity | str = "accurate",
              base: str = "sliding", initial_unloaded: np.ndarray | None = None,
              forward_from_scratch: bool = False, fibres: str = "laplace",
              workspace: PairWorkspace | None = None) -> Pair:
    """A physically consistent training pair (unloaded X, loaded x(X)).

    1. Without `initial_unloaded`, presets with a `coarse_guess` preset (accurate → fast) first run
       that cheaper inverse to 0.01 mm and start from its unloaded geometry.
    2. Inverse FE on the ED mesh to the preset's tolerance.
    3. Forward FE on the unloaded geometry: Newton at full load from the inverse's final state, to
       the full forward tolerance (or, with `forward_from_scratch`, from zero load with load
       stepping, which `solve` does; tests check that both land within 1e-3 mm of x_ED).
    With a `workspace` (pairs on the same ED mesh one after another), the inverse and forward use its
    problem and solver instead of building their own. A preset with `refinement_levels` makes the
    pair on the refined mesh (in the workspace's `refined` one, if given), started from `initial_unloaded` or its `coarse_guess`
    preset's answer on `ed_mesh`, and returns it at `ed_mesh`'s vertices: the loaded geometry is
    then x_ED to the round-trip tolerance, and the unloaded one the refined solution there.
    Raises SolveError on failure."""
    fid = get_fidelity(fidelity) if isinstance(fidelity, str) else fidelity
    if fid.refinement_levels:  # the pair on the refined mesh, at the original vertices
        t0 = time.perf_counter()
        fine_mesh, fine_workspace = ((refine_uniform(ed_mesh, fid.refinement_levels), None) if workspace is None
                                     else workspace.refined(ed_mesh, fid.refinement_levels))
        # the chain's pairs solved on the refined mesh, extrapolated there (an unloaded geometry
        # interpolated from `ed_mesh` has straight edges where the refined solutions curve)
        guess = None if fine_workspace is None else fine_workspace.unloaded_guess(params, fid.unrefined(), base, fibres)
        if guess is not None:
            try:
                check_geometry(guess, fine_mesh.tets)
            except MeshError:
                guess = None
        if guess is None:
            guess = _refined_guess(ed_mesh, params, fid, base, initial_unloaded, fibres)
        guess_s = time.perf_counter() - t0
        fine = make_pair(fine_mesh, params, fid.unrefined(), base, guess, forward_from_scratch, fibres,
                         workspace=fine_workspace)
        n = ed_mesh.n_nodes
        stats = dict(fine.stats, guess_wall_s=fine.stats["guess_wall_s"] + guess_s,
                     wall_s=time.perf_counter() - t0)
        return Pair(fine.unloaded_nodes[:n].copy(), fine.loaded_nodes[:n].copy(), fine.inverse, fine.forward, stats)
    t0 = time.perf_counter()
    guess_s = 0.0
    with SparseSolver() if workspace is None else nullcontext(workspace.linsolve) as linsolve:
        if initial_unloaded is None and fid.coarse_guess:
            initial_unloaded = inverse_solve(ed_mesh, params, fid.coarse_guess, base, tol_mm=1e-2,
                                             fibres=fibres).unloaded_nodes
            guess_s = time.perf_counter() - t0
        inv = inverse_solve(ed_mesh, params, fid, base, initial_unloaded, linsolve=linsolve, fibres=fibres,
                            workspace=workspace)
        fwd = _inflate_problem(inv.problem, ed_mesh.with_nodes(inv.unloaded_nodes), params, linsolve,
                               None if forward_from_scratch else inv.state, reuse_factor=True)
    if fwd.stats.min_jacobian <= 0 or not np.all(np.isfinite(fwd.loaded_nodes)):
        raise SolveError("forward solve of the unloaded geometry produced an invalid state")
    if workspace is not None:
        workspace.remember(inv.problem, params.pressure_mmhg, fwd.state)
    roundtrip = float(np.linalg.norm(fwd.loaded_nodes - ed_mesh.nodes, axis=1).max())
    stats = {
        "inverse_updates": inv.updates,
        "inverse_newton_iterations": inv.stats.newton_iterations,
        "forward_newton_iterations": fwd.stats.newton_iterations,
        "forward_load_steps": fwd.stats.load_steps,
        "inverse_mismatch_mm": inv.mismatch_mm,
        "roundtrip_error_mm": roundtrip,
        "final_residual": fwd.stats.final_residual,
        "min_jacobian": min(inv.stats.min_jacobian, fwd.stats.min_jacobian),
        "guess_wall_s": guess_s,
        "inverse_wall_s": inv.stats.wall_s,
        "forward_wall_s": fwd.stats.wall_s,
        "assembly_s": inv.stats.assembly_s + fwd.stats.assembly_s,
        "linear_s": inv.stats.linear_s + fwd.stats.linear_s,
        "wall_s": time.perf_counter() - t0,
    }
    return Pair(inv.unloaded_nodes, fwd.loaded_nodes, inv, fwd, stats)
