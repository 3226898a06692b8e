"""The Newton–Krylov step of inverse FE: solve J δ = −G for the change δ of the unloaded geometry X, where
G(X) = x(X) − x_ED is the mismatch at the vertices and J = ∂x/∂X = I + ∂u/∂X its Jacobian.

J is never formed. At an equilibrium z of the reference X (residual R(z; X) = 0, tangent K = ∂R/∂z),
moving the reference by v with z fixed changes the residual by ∂R/∂X · v, and equilibrium is restored by
δz = −K⁻¹ ∂R/∂X · v, so

    J v = v + [δz]ᵤ (the displacement part at the vertices),

with ∂R/∂X · v taken as a forward difference (R(z; X + εv) − R(z; X)) / ε, ε|v|∞ = FD_STEP_MM. Each product
costs one residual assembly on a moved reference and one back-substitution with K's factorisation.
Inverse FE holds the fibre frames at X's in the product: the Jacobian then leaves out how the fibres turn
with the reference, which slows Newton's convergence, not its answer (the mismatch G is evaluated with the
frames recomputed on every trial reference). Recomputing them in every product (`frames_of`) saved an
update on a thin wall but cost more time than it saved.

GMRES solves J δ = −G to a relative residual `rtol`. Where the fixed point X ← X − G contracts slowly
(a thin, soft wall: ‖∂u/∂X‖ near 1), Newton's steps still converge fast."""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla

from .assembly import MechanicsProblem
from .linear import SparseSolver

FD_STEP_MM = 1e-4  # the reference moves at most this far in a Jacobian–vector product


class ReferenceJacobian:
    """J = ∂x/∂X at the equilibrium z of problem's reference X (products only; J is never formed). Making it
    assembles and factorises the tangent at z (linsolve then holds it). Each product moves problem's
    reference; `restore` puts X back. frames_of(X) → fibre frames on a moved reference (None: hold X's)."""

    def __init__(self, problem: MechanicsProblem, z: np.ndarray, pressure_pa: float, linsolve: SparseSolver,
                 frames_of=None):
        self.problem, self.z, self.pressure_pa, self.linsolve = problem, z, pressure_pa, linsolve
        self.X = problem.nodes.copy()
        self.frames = problem.frames
        self.frames_of = frames_of
        self.products = 0
        self.R0, K, _ = problem.assemble(z, pressure_pa, with_tangent=True)
        linsolve.factorize(K)

    def state_change(self, v: np.ndarray) -> np.ndarray:
        """δz = −K⁻¹ ∂R/∂X · v [full unknown vector]: the equilibrium's change when the reference moves by v."""
        problem = self.problem
        dz = np.zeros(problem.n_full)
        size = float(np.abs(v).max())
        if size == 0.0:
            return dz
        eps = FD_STEP_MM / size
        moved = self.X + eps * v
        problem.set_reference(moved, self.frames if self.frames_of is None else self.frames_of(moved))
        R1, _, _ = problem.assemble(self.z, self.pressure_pa, with_tangent=False)
        dz[problem.free] = self.linsolve.solve_factored(-(R1 - self.R0) / eps)
        return dz

    def product(self, v: np.ndarray) -> np.ndarray:
        """J v [n, 3] mm per mm: v plus the vertices' displacement change."""
        self.products += 1
        return v + self.problem.split(self.state_change(v))[0][: len(self.X)]

    def restore(self) -> None:
        self.problem.set_reference(self.X, self.frames)


def newton_krylov_step(problem: MechanicsProblem, z: np.ndarray, pressure_pa: float, mismatch: np.ndarray,
                       linsolve: SparseSolver, rtol: float = 0.1, max_products: int = 40,
                       frames_of=None) -> tuple[np.ndarray, np.ndarray, int]:
    """δ [n, 3] mm with J δ ≈ −mismatch at the equilibrium z of problem's reference; the state z + δz
    predicted for the reference X + δ (to first order); the number of Jacobian–vector products it took.
    problem's reference is restored on return; linsolve holds the tangent at z (for the next re-solve's
    modified Newton). frames_of: as ReferenceJacobian."""
    jac = ReferenceJacobian(problem, z, pressure_pa, linsolve, frames_of)
    n = len(jac.X)
    try:
        J = spla.LinearOperator((3 * n, 3 * n), matvec=lambda v: jac.product(v.reshape(n, 3)).ravel(), dtype=float)
        delta, _ = spla.gmres(J, -mismatch.ravel(), rtol=rtol, atol=0.0, restart=max_products, maxiter=1)
        delta = delta.reshape(n, 3)
        predicted = z + jac.state_change(delta)  # the re-solve's start: first-order exact in δ, pressure field too
    finally:
        jac.restore()
    return delta, predicted, jac.products + 1
