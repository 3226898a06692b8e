"""Numerical stability at the extremes: FE pairs (inverse, then forward from zero load) at the corners
of the paper's parameter box and of an extended box, on the shape model's most extreme members.

Each case reports whether it converged and, if not, why; the load-step cutbacks, Newton iterations and
inverse updates it took; the smallest det F; the largest Fung exponent Q of the answer (W ∝ e^Q, which
overflows double precision at Q ≈ 709.8, so 709.8 − Q is the headroom left); the round-trip error; and
its time. A result counts only if it is finite and its round trip met the store's acceptance bound."""
from __future__ import annotations

import itertools
import math
import time
from dataclasses import asdict, dataclass, replace

import numpy as np

from solver.forward import SolveError
from solver.lv import make_pair
from solver.material import green_lagrange
from solver.mesh import MeshError
from solver.meshing import mesh_lv
from solver.parameters import CaseParameters
from solver.shape_model import extreme_shapes

Q_OVERFLOW = math.log(np.finfo(float).max)  # e^Q overflows beyond this (≈ 709.78)
ROUNDTRIP_BOUND_MM = 1e-3  # the store's acceptance: 10 × the inverse tolerance (orchestrator.grid)
SHAPE_NAMES = ("all −2 SD", "all +2 SD", "mixed corner")


@dataclass(frozen=True)
class Box:
    """A parameter box by its bounds per axis (mmHg, Pa, degrees)."""

    name: str
    pressure_mmhg: tuple[float, float]
    stiffness_pa: tuple[float, float]
    helix_endo_deg: tuple[float, float]
    helix_epi_deg: tuple[float, float]

    def corners(self) -> list[CaseParameters]:
        """Its 16 corners, hardest loading first (highest pressure on the softest wall)."""
        combos = itertools.product(self.pressure_mmhg[::-1], self.stiffness_pa, self.helix_endo_deg,
                                   self.helix_epi_deg)
        return sorted((CaseParameters(*c) for c in combos), key=lambda p: -p.pressure_mmhg / p.stiffness_pa)


PAPER_BOX = Box("paper", (4.0, 14.0), (50.0, 300.0), (60.0, 70.0), (-60.0, -70.0))
EXTENDED_BOX = Box("extended", (2.0, 30.0), (20.0, 2000.0), (40.0, 80.0), (-40.0, -80.0))


def fung_exponent_max(problem, z_full: np.ndarray) -> float:
    """Largest Q = Σ B_ab E_ab² (fibre frame) over the quadrature points of a solved state."""
    u, _ = problem.split(z_full)
    E = green_lagrange(problem.deformation_gradient(u))
    R = problem.frames  # columns (f, s, n)
    E_local = np.einsum("...ia,...ij,...jb->...ab", R, E, R)
    Q = np.einsum("ab,...ab->...", problem.material.exponent_weights(), E_local * E_local)
    return float(Q.max())


@dataclass(frozen=True, kw_only=True)
class CornerCase:
    """One pair at a corner: its box and shape (names), preset, parameters (mmHg, Pa, degrees) and mesh
    nodes; whether it counts (`ok`) or why not (`reason`), its time (s); when it solved: load-step
    cutbacks, Newton iterations, inverse updates, the smallest det F, the largest Fung exponent Q and the
    headroom before e^Q overflows, the round-trip error (mm) and whether the answer is finite."""

    box: str = ""
    shape: str = ""
    preset: str
    pressure_mmhg: float
    stiffness_pa: float
    helix_endo_deg: float
    helix_epi_deg: float
    nodes: int
    ok: bool
    reason: str
    wall_s: float
    step_cuts: int | None = None
    newton: int | None = None
    inverse_updates: int | None = None
    min_jacobian: float | None = None
    q_max: float | None = None
    q_headroom: float | None = None
    roundtrip_mm: float | None = None
    finite: bool | None = None

    @property
    def solved(self) -> bool:
        """Whether the pair solved (counted or not): its figures are there."""
        return self.roundtrip_mm is not None

    def as_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}


def stability_case(mesh, params: CaseParameters, preset: str, base: str = "sliding",
                   fibres: str = "laplace") -> CornerCase:
    """One pair at `params`, forward from zero load, with the figures of the module docstring."""
    case = dict(preset=preset, pressure_mmhg=params.pressure_mmhg, stiffness_pa=params.stiffness_pa,
                helix_endo_deg=params.helix_endo_deg, helix_epi_deg=params.helix_epi_deg, nodes=mesh.n_nodes)
    t0 = time.perf_counter()
    try:
        pair = make_pair(mesh, params, preset, base, forward_from_scratch=True, fibres=fibres)
    except (SolveError, MeshError, FloatingPointError) as exc:
        return CornerCase(**case, ok=False, reason=str(exc).splitlines()[0][:200], wall_s=time.perf_counter() - t0)
    s = pair.stats
    q_max = fung_exponent_max(pair.inverse.problem, pair.forward.state)
    finite = bool(np.all(np.isfinite(pair.unloaded_nodes)) and np.all(np.isfinite(pair.loaded_nodes))
                  and math.isfinite(q_max))
    accepted = finite and s["roundtrip_error_mm"] <= ROUNDTRIP_BOUND_MM and s["min_jacobian"] > 0
    return CornerCase(**case, ok=accepted,
                      reason="" if accepted else "answer not finite or round trip above the acceptance bound",
                      step_cuts=pair.inverse.stats.step_cuts + pair.forward.stats.step_cuts,
                      newton=s["inverse_newton_iterations"] + s["forward_newton_iterations"],
                      inverse_updates=s["inverse_updates"], min_jacobian=s["min_jacobian"], q_max=q_max,
                      q_headroom=Q_OVERFLOW - q_max, roundtrip_mm=s["roundtrip_error_mm"], finite=finite,
                      wall_s=time.perf_counter() - t0)


def run_stability(presets, box: Box, nodes: int, base: str = "sliding", fibres: str = "laplace",
                  progress=None) -> list[CornerCase]:
    """Every corner of `box` on the three extreme shapes with every preset; progress(case) after each."""
    rows = []
    for shape, name in zip(extreme_shapes(), SHAPE_NAMES):
        mesh = mesh_lv(shape, nodes)
        for params in box.corners():
            for preset in presets:
                row = replace(stability_case(mesh, params, preset, base, fibres), box=box.name, shape=name)
                rows.append(row)
                if progress:
                    progress(row)
    return rows


def format_row(r: CornerCase) -> str:
    case = (f"{r.box:>8} {r.shape:<12} {r.preset:<8} P={r.pressure_mmhg:>4g} C={r.stiffness_pa:>5g} "
            f"θ={r.helix_endo_deg:g}/{r.helix_epi_deg:g}:")
    if not r.solved:
        return f"{case} FAILED ({r.wall_s:.1f} s) {r.reason}"
    return (f"{case} {'ok' if r.ok else 'REJECTED'} round trip {r.roundtrip_mm:.1e} mm, {r.step_cuts} cutbacks, "
            f"{r.newton} Newton, {r.inverse_updates} updates, min J {r.min_jacobian:.3f}, "
            f"max Q {r.q_max:.1f} (headroom {r.q_headroom:.0f}), {r.wall_s:.1f} s")


def region_table(rows: list[CornerCase]) -> str:
    """Markdown: per box, pressure × stiffness corner and preset, converged / tried (over shapes and
    fibre angles), the worst min J and max Q, and the failure reasons."""
    lines = ["| box | P mmHg | C Pa | preset | converged | min J | max Q | cutbacks | reasons of failure |",
             "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | --- |"]
    corner = lambda r: (r.box, r.pressure_mmhg, r.stiffness_pa, r.preset)  # noqa: E731
    keys = sorted({corner(r) for r in rows}, key=lambda k: (k[0] != "paper", k[1], k[2], k[3]))
    for key in keys:
        box, p, c, preset = key
        rs = [r for r in rows if corner(r) == key]
        ok = [r for r in rs if r.ok]
        reasons = sorted({_short(r.reason) for r in rs if not r.ok})
        lines.append(f"| {box} | {p:g} | {c:g} | {preset} | {len(ok)}/{len(rs)} | "
                     f"{min((r.min_jacobian for r in ok), default=float('nan')):.3f} | "
                     f"{max((r.q_max for r in ok), default=float('nan')):.1f} | "
                     f"{sum(r.step_cuts or 0 for r in ok)} | {'; '.join(reasons)} |")
    return "\n".join(lines) + "\n"


def _short(reason: str) -> str:
    """A failure reason without its numbers, to group like with like."""
    return reason.split(" (")[0].split(":")[0][:90]
