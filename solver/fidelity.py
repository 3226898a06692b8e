"""Fidelity presets: element, incompressibility treatment, quadrature and Newton tolerances.
A case is fully described by (shape, parameters, fidelity), so presets are frozen values."""
from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class Fidelity:
    """How a solve is discretised.

    displacement_order: 1 (linear tets) or 2 (quadratic tets).
    incompressibility: "mixed" (a P1 pressure field, perturbed Lagrangian J − 1 = p/κ) or
      "penalty" (U = κ/2 (J − 1)^2, no pressure field).
    bulk_ratio: κ / C, the bulk modulus as a multiple of the stiffness C; float("inf") makes the
      mixed form exactly incompressible (the penalty form needs a finite value).
    penalty_ratio: (mixed only) an added κ_pen/2 (J − 1)^2 with κ_pen = penalty_ratio · C; it vanishes
      when J = 1 and damps the pointwise J oscillations that P2/P1 allows between pressure nodes.
    stabilization: Brezzi–Pitkäranta factor α for equal-order P1/P1 (adds −α h²/μ0 ∫∇p·∇q).
    quad_degree / facet_quad_degree: exact polynomial degree of the cell / surface rules.
    coarse_guess: a cheaper preset whose unloaded geometry starts this preset's inverse in pairs.
    refinement_levels: solve on the mesh refined this many times uniformly (each tet split in 8,
      the vertices kept) and answer at the original vertices: the same polyhedral domain resolved
      finer, for a reference near the converged solution of the model on the user's mesh.
    inverse_step: "fixed-point" (X ← X − G, Anderson-accelerated) or "newton" (J δ = −G by GMRES with
      Jacobian–vector products from the factorised tangent: solver/inverse_newton.py).
    residual_rtol: Newton stops when |R|∞ ≤ rtol · P · (mean endo facet area) and the last
      update is below increment_tol_mm.
    """

    name: str
    displacement_order: int
    incompressibility: str
    bulk_ratio: float
    stabilization: float
    quad_degree: int
    facet_quad_degree: int
    residual_rtol: float = 1e-9
    increment_tol_mm: float = 1e-7
    penalty_ratio: float = 0.0
    coarse_guess: str | None = None
    max_newton: int = 12
    initial_load_step: float = 0.25
    min_load_step: float = 1e-3
    inverse_tol_mm: float = 1e-4
    max_inverse_updates: int = 60
    refinement_levels: int = 0
    inverse_step: str = "fixed-point"

    def unrefined(self) -> "Fidelity":
        """This preset on the mesh as given (what it solves on the refined mesh)."""
        return replace(self, refinement_levels=0)


# Quadrature degrees from `heartctl bench convergence`'s quadrature study (docs/solver.md): the
# exponential law is not a polynomial, so the cell rule sets an error of its own. P1's fibre angle
# varies inside a tet, which the 4-point rule (degree 2) resolves; P2's strain is linear in a tet and
# its 14-point rule (degree 5, positive weights) is converged to ~0.002 mm at ~1.5× the cost of degree 2.
# The facet degree moves the answer by ≤ 2e-4 mm and stays at its lowest exact-for-P1 value.
# P2's inverse takes Newton–Krylov steps: on a thin, soft wall the fixed point contracts by only ~0.7 an
# update; P1's re-solves are cheap enough that the fixed point's extra updates cost less than the products.
PRESETS: dict[str, Fidelity] = {
    "fast": Fidelity("fast", 1, "mixed", float("inf"), 0.05, 2, 1),
    "accurate": Fidelity("accurate", 2, "mixed", float("inf"), 0.0, 5, 2, penalty_ratio=10.0, coarse_guess="fast",
                         inverse_step="newton"),
    # accurate on the once-refined mesh, started from accurate's answer on the mesh as given
    "reference": Fidelity("reference", 2, "mixed", float("inf"), 0.0, 5, 2, penalty_ratio=10.0,
                          coarse_guess="accurate", refinement_levels=1, inverse_step="newton"),
}


def get_fidelity(name: str) -> Fidelity:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown fidelity {name!r}; choose one of {', '.join(PRESETS)}") from None
