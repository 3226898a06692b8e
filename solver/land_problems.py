"""Land et al. (2015) verification problems 1 (beam bending) and 2 (LV inflation), with the
published reference values (../shared/reference/land2015.md). Units: mm, Pa (kPa × 1000)."""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
from skfem import MeshTet

from .assembly import MechanicsProblem, Supports
from .elements import cell_quadrature
from .fibres import uniform_frames
from .fidelity import Fidelity, get_fidelity
from .forward import inflate
from .material import FungParameters
from .mesh import boundary_facets, check_geometry, orient_positive
from .meshing import mesh_truncated_ellipsoid

REFERENCE = {
    "land1": {"deflection_z_mm": 4.1690},
    "land2": {"endo_apex_z_mm": -26.61, "epi_apex_z_mm": -28.28, "cavity_volume_mm3": 10734.0},
}
LAND1_DIVISIONS = {"fast": (40, 4, 4), "accurate": (20, 4, 4)}
LAND2_NODES = {"fast": 3000, "accurate": 1000}


@dataclass(frozen=True)
class LandSolve:
    """A verification solve's preset, size (mesh nodes, free dofs) and cost."""

    fidelity: str
    nodes: int
    dofs: int
    newton_iterations: int
    wall_s: float


@dataclass(frozen=True, kw_only=True)
class Land1Result(LandSolve):
    """Problem 1: the deformed z of the beam's probe point (10, 0.5, 1), mm, against the published
    value."""

    deflection_z_mm: float
    problem: str = "land1"

    @property
    def reference_mm(self) -> float:
        return REFERENCE["land1"]["deflection_z_mm"]

    @property
    def error_mm(self) -> float:
        return self.deflection_z_mm - self.reference_mm

    def as_dict(self) -> dict:
        return {**asdict(self), "reference_mm": self.reference_mm, "error_mm": self.error_mm}


@dataclass(frozen=True, kw_only=True)
class Land2Result(LandSolve):
    """Problem 2: the inflated apexes' z (endocardium, epicardium), mm, and the cavity volume, mm³,
    against the published values."""

    endo_apex_z_mm: float
    epi_apex_z_mm: float
    cavity_volume_mm3: float
    problem: str = "land2"

    @property
    def endo_apex_error_mm(self) -> float:
        return self.endo_apex_z_mm - REFERENCE["land2"]["endo_apex_z_mm"]

    @property
    def epi_apex_error_mm(self) -> float:
        return self.epi_apex_z_mm - REFERENCE["land2"]["epi_apex_z_mm"]

    def as_dict(self) -> dict:
        return {**asdict(self), **{f"reference_{k}": v for k, v in REFERENCE["land2"].items()},
                "endo_apex_error_mm": self.endo_apex_error_mm, "epi_apex_error_mm": self.epi_apex_error_mm}


def land1(fidelity: Fidelity | str = "accurate", divisions: tuple[int, int, int] | None = None) -> Land1Result:
    """Beam [0,10]×[0,1]×[0,1] mm, fibres along x, C = 2 kPa, bf 8, bt 2, bfs 4, x = 0 clamped,
    follower pressure 0.004 kPa on z = 0. Reports the deformed z of the point (10, 0.5, 1)."""
    fid = get_fidelity(fidelity) if isinstance(fidelity, str) else fidelity
    nx, ny, nz = divisions or LAND1_DIVISIONS.get(fid.name, (20, 4, 4))
    m = MeshTet.init_tensor(np.linspace(0, 10, nx + 1), np.linspace(0, 1, ny + 1), np.linspace(0, 1, nz + 1))
    nodes = m.p.T.copy()
    tets = check_geometry(nodes, orient_positive(nodes, m.t.T))
    facets = boundary_facets(tets)
    xf = nodes[facets]
    bottom = facets[np.all(np.abs(xf[:, :, 2]) < 1e-9, axis=1)]
    clamped = facets[np.all(np.abs(xf[:, :, 0]) < 1e-9, axis=1)]
    material = FungParameters(2000.0, b_ff=8.0, b_xx=2.0, b_fx=4.0)
    nq = cell_quadrature(nodes, tets, fid.displacement_order, fid.quad_degree).dV.shape[1]
    problem = MechanicsProblem(nodes, tets, bottom, Supports(clamped, (0, 1, 2)), fid, material,
                               uniform_frames(len(tets), nq))
    t0 = time.perf_counter()
    z, stats = inflate(problem, 4.0)
    wall = time.perf_counter() - t0
    u = problem.split(z)[0]
    probe = int(np.argmin(np.linalg.norm(problem.dofmap.points - [10.0, 0.5, 1.0], axis=1)))
    deflection = float(problem.dofmap.points[probe, 2] + u[probe, 2])
    return Land1Result(fidelity=fid.name, deflection_z_mm=deflection, nodes=int(len(nodes)),
                       dofs=int(problem.free.size), newton_iterations=stats.newton_iterations, wall_s=wall)


def land2(fidelity: Fidelity | str = "accurate", target_nodes: int | None = None) -> Land2Result:
    """Truncated ellipsoid (endo rs 7, rl 17; epi rs 10, rl 20; base z = 5 clamped), isotropic
    Guccione C = 10 kPa, b = 1, endocardial pressure 10 kPa. Apex z and cavity volume."""
    fid = get_fidelity(fidelity) if isinstance(fidelity, str) else fidelity
    n_target = target_nodes or LAND2_NODES.get(fid.name, 1500)
    mesh = mesh_truncated_ellipsoid((7.0, 7.0, 17.0), (10.0, 10.0, 20.0), 0.0, 5.0, n_target)
    material = FungParameters(10000.0, b_ff=1.0, b_xx=1.0, b_fx=1.0)
    nq = cell_quadrature(mesh.nodes, mesh.tets, fid.displacement_order, fid.quad_degree).dV.shape[1]
    problem = MechanicsProblem(mesh.nodes, mesh.tets, mesh.endo, Supports(mesh.base, (0, 1, 2)), fid, material,
                               uniform_frames(len(mesh.tets), nq))
    t0 = time.perf_counter()
    z, stats = inflate(problem, 10000.0)
    wall = time.perf_counter() - t0
    x = problem.dofmap.points + problem.split(z)[0]
    on_axis = np.linalg.norm(problem.dofmap.points[:, :2], axis=1) < 1e-6
    endo_dofs = np.unique(problem.pdofs)
    endo_apex = endo_dofs[np.argmin(problem.dofmap.points[endo_dofs, 2])]
    epi_apex = np.flatnonzero(on_axis)[np.argmin(problem.dofmap.points[on_axis, 2])] if on_axis.any() \
        else int(np.argmin(problem.dofmap.points[:, 2]))
    volume = cavity_volume(x, problem.pdofs, problem.dofmap.order, base_z=5.0)
    return Land2Result(fidelity=fid.name, endo_apex_z_mm=float(x[endo_apex, 2]), epi_apex_z_mm=float(x[epi_apex, 2]),
                       cavity_volume_mm3=float(volume), nodes=int(mesh.n_nodes), dofs=int(problem.free.size),
                       newton_iterations=stats.newton_iterations, wall_s=wall)


def cavity_volume(points: np.ndarray, endo_facet_dofs: np.ndarray, order: int, base_z: float) -> float:
    """Cavity volume (mm^3) enclosed by the endocardium and the base plane z = base_z:
    V = −∫ (z − base_z) n_z da over the endocardium (its normal points into the cavity).
    Vertices only (facets are treated as flat triangles)."""
    tri = points[endo_facet_dofs[:, :3]]
    area_vec = 0.5 * np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    zc = tri[:, :, 2].mean(axis=1) - base_z
    return float(-(zc * area_vec[:, 2]).sum())
