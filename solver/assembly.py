"""Total-Lagrangian residual and consistent tangent of the passive LV (or benchmark) problem:
the Guccione law (from `material`), incompressibility (mixed or penalty), follower pressure,
supports and the rigid-motion gauge. Vectorised over elements and quadrature points; sparsity built
once. Tensor names, the fibre frame and the Voigt order are `material`'s."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from skfem.quadrature import get_quadrature
from skfem.refdom import RefTri

from .elements import build_dofmap, cell_quadrature, facet_dofs, facet_quadrature, simplex_shape
from .fidelity import Fidelity
from .material import FungParameters, green_lagrange, guccione_response, voigt_frame_tensors


@dataclass(frozen=True)
class Supports:
    """Displacement supports: on the dofs of `facets`, the listed components are fixed at zero.
    With `gauge`, the in-plane rigid motions left free (x, y translation, rotation about z) are
    removed by three Lagrange multipliers on the area-weighted mean motion of those facets
    (∫u_x dA = ∫u_y dA = ∫(X − X̄) × u · e_z dA = 0, the same conditions on any mesh of the surface). `gauge_region="volume"`
    instead imposes, as heartFEM does, ∫u_x = ∫u_y = 0 and ∫X × u = 0 (all three components, five
    multipliers) over the whole wall. An optional normal spring on `spring_facets` (reference
    normal N) resists wall motion along N."""

    facets: np.ndarray
    components: tuple[int, ...]
    gauge: bool = False
    gauge_region: str = "base"  # base | volume
    spring_facets: np.ndarray | None = None  # boundary triangles with a normal spring (Robin condition)
    spring_pa_per_mm: float = 0.0  # traction −k (u·N) N on them, k in Pa/mm

    def __post_init__(self):
        if self.gauge_region not in ("base", "volume"):
            raise ValueError(f"unknown gauge region {self.gauge_region!r}; choose base or volume")


@dataclass(frozen=True)
class ElementBlock:
    """Dense per-element blocks of the matrix. Entry (e, a, i, b, j) couples the row dof
    row_base + row_comps · row_nodes[e, a] + i (i < row_comps) with the column dof
    col_base + col_comps · col_nodes[e, b] + j; `order` is the axis order of the block's values as
    the assembly produces them (e.g. "eiajb" for values [e, i, a, j, b])."""

    row_nodes: np.ndarray
    col_nodes: np.ndarray
    row_comps: int
    col_comps: int
    order: str
    row_base: int = 0
    col_base: int = 0

    @property
    def axes(self) -> list[int]:
        """`order` as a transpose of the axes (e, a, b, i, j)."""
        return ["eabij".index(ax) for ax in self.order]

    def entries(self) -> tuple[np.ndarray, np.ndarray]:
        """Row and column of every entry, in `order` (what `SparsityPattern` takes)."""
        rows, cols = self.dofs(self.row_nodes, self.col_nodes)
        return rows.transpose(self.axes).ravel(), cols.transpose(self.axes).ravel()

    def dofs(self, row_nodes: np.ndarray, col_nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column dofs [E, m, n, ri, cj] (axes e, a, b, i, j) of nodes [E, m] and [E, n]."""
        i = np.arange(self.row_comps)
        j = np.arange(self.col_comps)
        r = self.row_base + self.row_comps * row_nodes[:, :, None, None, None] + i[:, None]
        c = self.col_base + self.col_comps * col_nodes[:, None, :, None, None] + j
        shape = (len(row_nodes), row_nodes.shape[1], col_nodes.shape[1], i.size, j.size)
        return np.broadcast_to(r, shape), np.broadcast_to(c, shape)


class SparsityPattern:
    """COO entries → CSR data positions, built once; assembling is then one bincount.

    The pattern is scipy's canonical CSR of the kept entries (duplicates merged, column indices
    sorted); each entry's position is then read back from a CSR whose data are 0 … nnz − 1 (a binary
    search per entry in C), about 2× faster than np.unique over the entry keys. `from_blocks` does
    that once per distinct node pair of each element block instead of once per entry."""

    def __init__(self, rows: np.ndarray, cols: np.ndarray, full_to_reduced: np.ndarray, n_reduced: int):
        r = full_to_reduced[rows]
        c = full_to_reduced[cols]
        self.keep = keep = (r >= 0) & (c >= 0)
        r, c = r[keep], c[keep]
        slots = sp.csr_matrix((np.ones(r.size, np.int8), (r, c)), shape=(n_reduced, n_reduced))
        slots.sum_duplicates()
        slots.data = np.arange(slots.nnz, dtype=np.int64)
        # entries on removed (supported) dofs go to one extra slot, dropped after summing: cheaper
        # than masking every assembly's values
        self.position = np.full(rows.size, slots.nnz, dtype=np.int64)
        self.position[keep] = np.asarray(slots[r, c]).ravel()
        self.indices = slots.indices.astype(np.int32, copy=False)
        self.indptr = slots.indptr.astype(np.int32, copy=False)
        self.n = n_reduced
        self.nnz = slots.nnz

    @classmethod
    def from_blocks(cls, blocks: list[ElementBlock], rows: np.ndarray, cols: np.ndarray,
                    full_to_reduced: np.ndarray, n_reduced: int) -> "SparsityPattern":
        """The pattern of the blocks' entries (in block order, each in its `order`) followed by the
        loose entries (rows, cols). Neighbouring elements share node pairs (an edge is in ~5 tets),
        so each block's distinct node pairs are found first (np.unique over m·n keys per element,
        not m·n·ri·cj) and only their entries are looked up; every entry then takes its node pair's
        position. The same positions as the plain constructor (tested): on shape 0 at 800 nodes,
        24 ms against 80 ms for the P1/P1 tangent's 0.6 M entries, 137 ms against 457 ms for
        P2/P1's 2.9 M."""
        distinct_rows, distinct_cols, inverses = [], [], []
        for block in blocks:
            n_cols = int(block.col_nodes.max(initial=0)) + 1
            keys = block.row_nodes[:, :, None].astype(np.int64) * n_cols + block.col_nodes[:, None, :]
            pairs, inverse = np.unique(keys.ravel(), return_inverse=True)
            r, c = block.dofs(*(v[:, None] for v in np.divmod(pairs, n_cols)))  # [pairs, 1, 1, ri, cj]
            distinct_rows.append(r.ravel())
            distinct_cols.append(c.ravel())
            inverses.append(inverse.reshape(keys.shape))
        pattern = cls(np.concatenate(distinct_rows + [rows]), np.concatenate(distinct_cols + [cols]),
                      full_to_reduced, n_reduced)
        positions, start = [], 0
        for block, inverse, r in zip(blocks, inverses, distinct_rows):
            table = pattern.position[start: start + r.size].reshape(-1, block.row_comps, block.col_comps)
            positions.append(table[inverse].transpose(block.axes).ravel())  # [e, a, b, i, j] → order
            start += r.size
        positions.append(pattern.position[start:])
        pattern.position = np.concatenate(positions)
        pattern.keep = pattern.position < pattern.nnz
        return pattern

    def matrix(self, values: np.ndarray) -> sp.csr_matrix:
        data = np.bincount(self.position, weights=values, minlength=self.nnz + 1)[: self.nnz]
        K = sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
        K.has_sorted_indices = True  # canonical by construction: spare the solver a sort per factorisation
        return K


@dataclass(frozen=True)
class _QuadratureState:
    """The kinematics and stresses of one state at the cell quadrature points [e, q, …]."""

    F: np.ndarray
    J: np.ndarray
    cof: np.ndarray
    law: object  # the Guccione response (material.guccione_response)
    P: np.ndarray  # Guccione's first Piola–Kirchhoff stress
    pq: np.ndarray | None  # the interpolated pressure (mixed form)
    vol_coef: np.ndarray  # the volumetric stress coefficient v


class MechanicsProblem:
    """Discrete quasi-static inflation problem on a fixed topology.

    Unknowns z = [u (3 per displacement dof, mm), p (one per vertex, Pa, mixed only), λ (gauge)],
    with supported components removed. The reference geometry and fibre frames can be replaced
    (inverse FE moves the reference) without rebuilding the sparsity.
    """

    def __init__(self, nodes, tets, pressure_facets, supports: Supports, fidelity: Fidelity,
                 material: FungParameters, frames: np.ndarray):
        self.tets = np.asarray(tets)
        self.fidelity = fidelity
        self.material = material
        self.supports = supports
        self.pressure_facets = np.asarray(pressure_facets, dtype=np.int64).reshape(-1, 3)
        self.mixed = fidelity.incompressibility == "mixed"
        self.bulk_modulus_pa = fidelity.bulk_ratio * material.stiffness_pa
        self.penalty_pa = fidelity.penalty_ratio * material.stiffness_pa if self.mixed else 0.0
        if fidelity.incompressibility not in ("mixed", "penalty"):
            raise ValueError(f"unknown incompressibility treatment {fidelity.incompressibility!r}")
        if not self.mixed and not np.isfinite(self.bulk_modulus_pa):
            raise ValueError("the penalty form needs a finite bulk_ratio")
        self.fq = facet_quadrature(fidelity.displacement_order, fidelity.facet_quad_degree)
        self.set_reference(nodes, frames)
        dm = self.dofmap
        self.n_u = 3 * dm.n_dofs
        self.n_p = dm.n_vertices if self.mixed else 0
        self.cell_udofs = (3 * dm.cell_dofs[:, :, None] + np.arange(3)).reshape(len(self.tets), -1)
        self.pdofs = facet_dofs(dm, self.pressure_facets)
        self.facet_udofs = (3 * self.pdofs[:, :, None] + np.arange(3)).reshape(len(self.pdofs), 3 * self.pdofs.shape[1])
        support_dofs = np.unique(facet_dofs(dm, np.asarray(supports.facets)))
        self.support_dofs = support_dofs
        fixed = np.zeros(self.n_u + self.n_p, bool)
        for comp in supports.components:
            fixed[3 * support_dofs + comp] = True
        self.n_gauge = (5 if supports.gauge_region == "volume" else 3) if supports.gauge else 0
        n_full = self.n_u + self.n_p + self.n_gauge
        fixed = np.concatenate([fixed, np.zeros(self.n_gauge, bool)])
        self.free = np.flatnonzero(~fixed)
        self.full_to_reduced = -np.ones(n_full, np.int64)
        self.full_to_reduced[self.free] = np.arange(self.free.size)
        self.n_full = n_full
        self._build_pattern()

    # --- geometry -----------------------------------------------------------------------------
    def set_reference(self, nodes: np.ndarray, frames: np.ndarray) -> None:
        """Set the stress-free configuration (vertex coordinates, mm) and fibre frames."""
        fid = self.fidelity
        self.nodes = np.array(nodes, dtype=float)  # a copy: the caller's array may change later
        self.dofmap = build_dofmap(self.nodes, self.tets, fid.displacement_order)
        self.cq = cell_quadrature(self.nodes, self.tets, fid.displacement_order, fid.quad_degree)
        if frames.shape[:2] != self.cq.dV.shape:
            raise ValueError(f"fibre frames {frames.shape[:2]} do not match quadrature {self.cq.dV.shape}")
        self.frames = frames
        # fixed while the reference is: Rᵀ and ∇φ by dof [e, a, (q I)]; the tangent's own arrays are made
        # when a tangent is first assembled on this reference (`_tangent_arrays`: a residual alone, as
        # inverse FE's Jacobian–vector products assemble on moved references, needs none of them)
        self._frames_t = np.ascontiguousarray(np.swapaxes(frames, -1, -2))
        ne, nq, na, _ = self.cq.grads.shape
        self._grads_by_dof = np.ascontiguousarray(self.cq.grads.transpose(0, 2, 1, 3)).reshape(ne, na, nq * 3)
        self._tangent_geometry = None
        B = self.material.exponent_weights()
        if self.mixed and fid.stabilization > 0:
            h2 = (6.0 * np.sqrt(2.0) * np.abs(self.cq.volumes)) ** (2.0 / 3.0)
            mu0 = 0.5 * self.material.stiffness_pa * B.mean()
            tau = fid.stabilization * h2 / mu0 * np.abs(self.cq.volumes)
            self._stab = tau[:, None, None] * np.einsum("eaI,ebI->eab", self.cq.p1_grads, self.cq.p1_grads)
        else:
            self._stab = None
        if getattr(self, "n_gauge", 0) or self.supports.gauge:
            self._gauge_values = self._gauge_rows()
        self._spring = self._spring_matrix() if self._has_spring() else None

    def _has_spring(self) -> bool:
        sp_f = self.supports.spring_facets
        return sp_f is not None and len(sp_f) > 0 and self.supports.spring_pa_per_mm > 0

    def _spring_matrix(self) -> np.ndarray:
        """Element matrices [nf, 3nb, 3nb] of ∫ k (u·N)(δu·N) dA on the reference spring facets."""
        fq = self.fq
        sdofs = facet_dofs(self.dofmap, np.asarray(self.supports.spring_facets))
        X = self.dofmap.points[sdofs]
        a1 = np.einsum("fbi,bq->fqi", X, fq.dxi[:, 0])
        a2 = np.einsum("fbi,bq->fqi", X, fq.dxi[:, 1])
        n = np.cross(a1, a2)  # N dA per unit parametric area
        nn = n[..., :, None] * n[..., None, :] / np.linalg.norm(n, axis=-1)[..., None, None]
        K = self.supports.spring_pa_per_mm * np.einsum("bq,cq,fqij,q->fbicj", fq.values, fq.values, nn, fq.weights)
        self._spring_udofs = (3 * sdofs[:, :, None] + np.arange(3)).reshape(len(sdofs), 3 * sdofs.shape[1])
        return K.reshape(len(sdofs), self._spring_udofs.shape[1], -1)

    def _gauge_rows(self) -> np.ndarray:
        if self.supports.gauge_region == "volume":
            return self._volume_gauge_rows()
        w, m = _surface_moments(self.dofmap, np.asarray(self.supports.facets))
        dofs = np.unique(facet_dofs(self.dofmap, np.asarray(self.supports.facets)))
        w, m = w[dofs], m[dofs]
        area = w.sum()
        c = m.sum(axis=0) / area  # the base's centroid
        m = m - w[:, None] * c
        rows = np.concatenate([np.full(dofs.size, 0), np.full(dofs.size, 1), np.full(2 * dofs.size, 2)])
        cols = np.concatenate([3 * dofs, 3 * dofs + 1, 3 * dofs + 1, 3 * dofs])
        vals = np.concatenate([w, w, m[:, 0], -m[:, 1]]) / area
        self._gauge_cols = cols
        self._gauge_r = rows
        return vals

    def _volume_gauge_rows(self) -> np.ndarray:
        """Rows of ∫u_x, ∫u_y, ∫(X×u)_z, ∫(X×u)_x, ∫(X×u)_y over the wall (moments about the
        coordinate origin, as heartFEM takes them), scaled by the wall volume (and a lever arm):
        w_i = ∫φ_i dV and m_i = ∫X φ_i dV per displacement dof, from the cell quadrature."""
        cq, dm = self.cq, self.dofmap
        xq = np.einsum("eai,aq->eqi", self.nodes[self.tets], cq.lam)
        n = dm.n_dofs
        w = np.bincount(dm.cell_dofs.ravel(), weights=np.einsum("bq,eq->eb", cq.values, cq.dV).ravel(), minlength=n)
        m = np.stack([np.bincount(dm.cell_dofs.ravel(), weights=np.einsum("bq,eq,eq->eb", cq.values, cq.dV,
                                                                            xq[..., i]).ravel(), minlength=n)
                      for i in range(3)], axis=1)
        dofs = np.arange(n)
        ux, uy, uz = 3 * dofs, 3 * dofs + 1, 3 * dofs + 2
        parts = [(0, ux, w), (1, uy, w),
                 (2, uy, m[:, 0]), (2, ux, -m[:, 1]),  # X u_y − Y u_x
                 (3, uz, m[:, 1]), (3, uy, -m[:, 2]),  # Y u_z − Z u_y
                 (4, ux, m[:, 2]), (4, uz, -m[:, 0])]  # Z u_x − X u_z
        self._gauge_r = np.concatenate([np.full(n, r) for r, _, _ in parts])
        self._gauge_cols = np.concatenate([c for _, c, _ in parts])
        total = w.sum()
        lever = float(np.sqrt((m ** 2).sum() / max((w ** 2).sum(), 1e-300)))  # ~ wall radius, mm
        # rows in force units (Pa·mm² per mm of mean motion), so that Newton's residual test holds the
        # constraints as tightly as equilibrium (these multipliers exert real forces: the inverse
        # problem's fixed point stalls at the constraint slack otherwise)
        force = self.material.stiffness_pa * total ** (1.0 / 3.0)
        vals = np.concatenate([v * force / total for _, _, v in parts[:2]] +
                              [v * force / (total * lever) for _, _, v in parts[2:]])
        return vals

    # --- sparsity ----------------------------------------------------------------------------
    def _build_pattern(self) -> None:
        rows, cols = self.pattern_loose_entries()
        self.pattern = SparsityPattern.from_blocks(self.pattern_blocks(), rows, cols, self.full_to_reduced,
                                                   self.free.size)

    def pattern_blocks(self) -> list[ElementBlock]:
        """The tangent's element blocks in the order `_assemble` lays out their values: Kuu as
        [e, a, i, b, j] (`_displacement_tangent`), the follower-load block as [f, b, c, i, j], the
        spring as [f, b, i, c, j], K_up as [e, a, i, c], K_pu with the same values, K_pp as [e, c, d]."""
        cell_nodes = self.dofmap.cell_dofs
        blocks = [ElementBlock(cell_nodes, cell_nodes, 3, 3, "eaibj"),
                  ElementBlock(self.pdofs, self.pdofs, 3, 3, "eabij")]
        if self._spring is not None:
            spring_nodes = self._spring_udofs[:, ::3] // 3
            blocks.append(ElementBlock(spring_nodes, spring_nodes, 3, 3, "eaibj"))
        if self.mixed:
            blocks += [ElementBlock(cell_nodes, self.tets, 3, 1, "eaibj", col_base=self.n_u),
                       ElementBlock(self.tets, cell_nodes, 1, 3, "ebjai", row_base=self.n_u),
                       ElementBlock(self.tets, self.tets, 1, 1, "eaibj", self.n_u, self.n_u)]
        return blocks

    def pattern_loose_entries(self) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns of the entries after the blocks: the gauge constraints' (if any)."""
        if not self.n_gauge:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        g_rows = self.n_u + self.n_p + self._gauge_r
        return np.concatenate([g_rows, self._gauge_cols]), np.concatenate([self._gauge_cols, g_rows])

    # --- state helpers -----------------------------------------------------------------------
    def split(self, z_full: np.ndarray):
        u = z_full[: self.n_u].reshape(-1, 3)
        p = z_full[self.n_u : self.n_u + self.n_p]
        return u, p

    def zeros(self) -> np.ndarray:
        return np.zeros(self.n_full)

    def deformation_gradient(self, u: np.ndarray) -> np.ndarray:
        """F = I + ∇u [e, q, 3, 3] at the cell quadrature points: one matmul per element over its dofs,
        u_e [i, a] @ ∇φ [a, (q J)] (1.4 ms against 2.1 ms for a 3 × 3 product per point, 39,000 points)."""
        ue = u[self.dofmap.cell_dofs]  # [e, a, i]
        ne, nq = self.cq.dV.shape
        grad_u = (np.swapaxes(ue, 1, 2) @ self._grads_by_dof).reshape(ne, 3, nq, 3)  # [e, i, q, J]
        F = np.ascontiguousarray(grad_u.transpose(0, 2, 1, 3))
        for i in range(3):
            F[..., i, i] += 1.0
        return F

    def min_jacobian(self, z_full: np.ndarray) -> float:
        u, _ = self.split(z_full)
        return float(_det_cofactor(self.deformation_gradient(u))[0].min())

    # --- assembly ----------------------------------------------------------------------------
    def _follower_load(self, u: np.ndarray):
        """Surface tangents a1, a2 [nf, nq, 3] of the deformed loaded facets and the follower load
        per unit pressure, ∫ n da · δu per facet dof [nf, 3·nb] (mm², n outward from the wall)."""
        xf = (self.dofmap.points + u)[self.pdofs]
        fq = self.fq
        a1 = fq.dxi[:, 0].T @ xf
        a2 = fq.dxi[:, 1].T @ xf
        n = np.cross(a1, a2)
        load = ((fq.values * fq.weights) @ n).reshape(len(xf), self.facet_udofs.shape[1])
        return a1, a2, load

    def pressure_load(self, z_full: np.ndarray) -> np.ndarray:
        """∂R/∂P at state z: the reduced residual's derivative with respect to the cavity pressure
        (mm², R being linear in P). With the tangent K = ∂R/∂z, the load-path tangent is
        dz/dP = −K⁻¹ ∂R/∂P (the Euler predictor of `forward.inflate`)."""
        _, _, load = self._follower_load(self.split(z_full)[0])
        full = np.zeros(self.n_full)
        np.add.at(full, self.facet_udofs.ravel(), load.ravel())
        return full[self.free]

    def assemble(self, z_full: np.ndarray, pressure_pa: float, with_tangent: bool = True):
        """Reduced residual R (N), reduced tangent K (CSR) and min det F over quadrature points."""
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return self._assemble(z_full, pressure_pa, with_tangent)

    def _assemble(self, z_full: np.ndarray, pressure_pa: float, with_tangent: bool):
        """R(z) = the sum of the named terms below, each with its weak form in its docstring, over the
        full unknowns, then restricted to the free ones; K = ∂R/∂z term by term, in the sparsity
        pattern's order (Kuu of both stress terms first, written in place)."""
        u, p = self.split(z_full)
        state = self._kinematics(u, p)
        full = np.zeros(self.n_full)
        self._add_stress_residual(full, state)
        if self.mixed:
            self._add_incompressibility_residual(full, state, p)
        a1, a2 = self._add_follower_pressure_residual(full, u, pressure_pa)
        self._add_base_spring_residual(full, z_full)
        self._add_gauge_residual(full, z_full)
        residual = full[self.free]
        min_J = float(state.J.min())
        if not with_tangent:
            return residual, None, min_J
        penalty = self.penalty_pa if self.mixed else self.bulk_modulus_pa
        entries = np.empty(self.pattern.position.size)  # in pattern order: Kuu first, written in place
        n_uu = self.cell_udofs.size * self.cell_udofs.shape[1]
        S = self.frames @ state.law.stress @ self._frames_t
        H = self._displacement_tangent(state.F, state.law, S, state.P, state.cof, state.vol_coef / state.J, penalty,
                                       out=entries[:n_uu])
        values = [self._follower_pressure_tangent(a1, a2, pressure_pa).ravel()]
        if self._spring is not None:
            values.append(self._spring.ravel())
        if self.mixed:
            values += self._incompressibility_tangent(H)
        if self.n_gauge:
            values += [self._gauge_values, self._gauge_values]
        np.concatenate(values, out=entries[n_uu:])
        return residual, self.pattern.matrix(entries), min_J

    def _kinematics(self, u: np.ndarray, p: np.ndarray) -> "_QuadratureState":
        """F = I + ∇u, J = det F and cof F at the cell quadrature points; the Guccione law's response to
        the fibre-frame Green–Lagrange strain E_loc = Rᵀ E R and its first Piola–Kirchhoff stress
        P = F R S_loc Rᵀ; and the volumetric stress coefficient: p + κ_pen (J − 1) with the
        interpolated pressure p (mixed), or κ (J − 1) (penalty form)."""
        F = self.deformation_gradient(u)
        F_loc = F @ self.frames
        law = guccione_response(green_lagrange(F_loc), self.material)
        P = F_loc @ law.stress @ self._frames_t
        J, cof = _det_cofactor(F)
        pq = None
        if self.mixed:
            pq = np.einsum("ec,cq->eq", p[self.tets], self.cq.lam)
            vol_coef = pq + self.penalty_pa * (J - 1.0)
        else:
            vol_coef = self.bulk_modulus_pa * (J - 1.0)
        return _QuadratureState(F, J, cof, law, P, pq, vol_coef)

    def _add_stress_residual(self, full: np.ndarray, s: "_QuadratureState") -> None:
        """Guccione and incompressibility, tested with δu:
        ∫_Ω₀ (P(F) + v(J, p) cof F) : ∇₀δu dV, with W = C/2 (e^Q − 1) the Guccione law (P = ∂W/∂F) and
        v the volumetric coefficient of _kinematics (cof F = J F⁻ᵀ = ∂J/∂F). One matmul per element over
        its points, ∇φ [a, (q J)] @ (dV Pᵀ) [(q J), i] (1.2 ms against 2.4 ms for a product per point and
        a sum over them, 39,000 points)."""
        ne, nq = s.J.shape
        P_total = s.P + s.vol_coef[..., None, None] * s.cof
        weighted = np.ascontiguousarray(np.swapaxes(P_total, -1, -2)) * self.cq.dV[..., None, None]  # [e, q, J, i]
        Ru = (self._grads_by_dof @ weighted.reshape(ne, nq * 3, 3)).reshape(ne, -1)
        np.add.at(full, self.cell_udofs.ravel(), Ru.ravel())

    def _add_incompressibility_residual(self, full: np.ndarray, s: "_QuadratureState", p: np.ndarray) -> None:
        """The mixed form's constraint, tested with the P1 pressure δp:
        ∫_Ω₀ (J − 1 − p/κ) δp dV − Σ_e δpᵀ S_e p_e, κ the bulk modulus (∞: exact incompressibility) and
        S_e the element's pressure stabilisation (none when the pair is inf-sup stable)."""
        cq = self.cq
        inv_k = 0.0 if np.isinf(self.bulk_modulus_pa) else 1.0 / self.bulk_modulus_pa
        Rp = ((s.J - 1.0 - inv_k * s.pq) * cq.dV) @ cq.lam.T
        if self._stab is not None:
            Rp -= np.einsum("ecd,ed->ec", self._stab, p[self.tets])
        np.add.at(full, self.n_u + self.tets.ravel(), Rp.ravel())

    def _incompressibility_tangent(self, H: np.ndarray) -> list:
        """K_up = ∫ (cof F ∇₀φ_a)_i ψ_c dV (and its transpose K_pu), K_pp = −(1/κ) ∫ ψ_c ψ_d dV − S_e,
        as the pattern lists them."""
        cq = self.cq
        ne = H.shape[0]
        inv_k = 0.0 if np.isinf(self.bulk_modulus_pa) else 1.0 / self.bulk_modulus_pa
        Kup = np.swapaxes(H * cq.dV[..., None], 1, 2) @ cq.lam.T  # [e, (a i), c]
        Kpp = -inv_k * np.einsum("cq,dq,eq->ecd", cq.lam, cq.lam, cq.dV)
        if self._stab is not None:
            Kpp = Kpp - self._stab
        Kup_flat = Kup.reshape(ne, -1, 4)
        return [Kup_flat.ravel(), Kup_flat.ravel(), Kpp.ravel()]

    def _add_follower_pressure_residual(self, full: np.ndarray, u: np.ndarray, pressure_pa: float):
        """The cavity pressure P on the deformed endocardium, following it:
        + P ∫_Γ n da · δu, n outward from the wall (n da = a₁ × a₂ dξ on each facet). Returns the
        deformed facets' tangents a₁, a₂ (the tangent term needs them)."""
        a1, a2, Rf = self._follower_load(u)
        np.add.at(full, self.facet_udofs.ravel(), pressure_pa * Rf.ravel())
        return a1, a2

    def _follower_pressure_tangent(self, a1: np.ndarray, a2: np.ndarray, pressure_pa: float) -> np.ndarray:
        """∂/∂u of the follower load: P ∫ φ_a (∂n/∂x_c) φ_c dξ with ∂n/∂x_c = −ξ1_c [a₂]ₓ + ξ2_c [a₁]ₓ
        ([a]ₓ the cross-product matrix), as [f, b, c, i, j]."""
        fq = self.fq
        sk1, sk2 = _skew(a1), _skew(a2)
        d1, d2 = (fq.dxi[:, k].T[None, :, :, None, None] for k in (0, 1))  # [1, q, c, 1, 1]
        dn = d2 * sk1[:, :, None] - d1 * sk2[:, :, None]
        return (pressure_pa * fq.values * fq.weights) @ dn.reshape(*dn.shape[:2], 9 * dn.shape[2])

    def _add_base_spring_residual(self, full: np.ndarray, z_full: np.ndarray) -> None:
        """The epicardial spring of the `spring` and `heartfem` bases: ∫_Γepi k (u · n₀) (δu · n₀) dA,
        k in Pa/mm (its matrix per facet, _spring_matrix, is also its tangent)."""
        if self._spring is not None:
            us = z_full[: self.n_u][self._spring_udofs]
            np.add.at(full, self._spring_udofs.ravel(), np.einsum("fab,fb->fa", self._spring, us).ravel())

    def _add_gauge_residual(self, full: np.ndarray, z_full: np.ndarray) -> None:
        """Rigid motions the supports leave free, removed by Lagrange multipliers λ:
        λ · G u (the constraint rows G: the base ring's or the wall's mean translation and turn, zero)
        and its transpose δu · Gᵀ λ; the same values are the tangent's."""
        if self.n_gauge:
            lam_g = z_full[self.n_u + self.n_p:]
            uflat = z_full[: self.n_u]
            g_off = self.n_u + self.n_p
            np.add.at(full, g_off + self._gauge_r, self._gauge_values * uflat[self._gauge_cols])
            np.add.at(full, self._gauge_cols, self._gauge_values * lam_g[self._gauge_r])

    def _displacement_tangent(self, F, law, S, P, cof, vol_over_J, penalty, out):
        """Writes Kuu [e, a, i, b, j] = Σ_q dV ∇φ_a,I ∂(P + vol cof F)_iI/∂F_jJ ∇φ_b,J to `out` (flat),
        vol = p + κ_pen (J − 1) (mixed) or κ (J − 1) (penalty form), and returns H [e, q, (a i)] =
        (cof F ∇φ_a)_i, K_up's integrand per unit volume.

        ∂P/∂F = ∂ε/∂Fᵀ D_v ∂ε/∂F + δ_ij S_IJ with the law's D_v = diag(d) + c σσᵀ, and ∂ε/∂F · σ = P;
        ∂(cof F)_iI/∂F_jJ = (cof_iI cof_jJ − cof_jI cof_iJ) / J. All but the geometric term and the
        second cofactor term are sums of outer products w_k U_k ⊗ U_k over (a i), (b j), with
        U_v = ∇φ M_v Fᵀ (∂ε_v/∂u), U_6 = ∇φ Pᵀ, U_7 = ∇φ cof Fᵀ = H and w = dV (d, c, vol/J + κ_pen)
        (κ_pen → κ in the penalty form):
        one batched matmul per element over (q, k).

        Elements go in chunks whose U takes about 256 KiB, so that a chunk's products stay in cache:
        on 2,786 P2 tets, 26 ms of CPU against 45 ms for all elements at once (2-core box)."""
        ne, nq, na, _ = self.cq.grads.shape
        voigt_grads, grads_t, grads_t_dv = self._tangent_arrays()
        dV = self.cq.dV
        w = np.empty((ne, nq, 8))
        w[..., :6] = law.tangent_diagonal
        w[..., 6] = law.tangent_rank_one
        w[..., 7] = vol_over_J + penalty
        w *= dV[..., None]
        swap_w = vol_over_J * dV
        H = np.empty((ne, nq, 3 * na))
        Kuu = out.reshape(ne, 3 * na, 3 * na)
        step = max(1, 2 ** 15 // (nq * 8 * 3 * na))  # elements per chunk
        for start in range(0, ne, step):
            c = slice(start, start + step)
            H[c] = _displacement_chunk(F[c], S[c], P[c], cof[c], w[c], swap_w[c], voigt_grads[c],
                                       self.cq.grads[c], grads_t[c], grads_t_dv[c], Kuu[c])
        return H

    def _tangent_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """∇φ M_v [e, q, (v a), J], ∇φᵀ and ∇φᵀ dV [e, q, I, a] on the current reference, made once per
        reference (numpy's batched matmul runs about twice as fast on contiguous operands as on
        transposed views)."""
        if self._tangent_geometry is None:
            ne, nq, na, _ = self.cq.grads.shape
            self._tangent_geometry = (
                (self.cq.grads[:, :, None] @ voigt_frame_tensors(self.frames)).reshape(ne, nq, 6 * na, 3),
                np.ascontiguousarray(np.swapaxes(self.cq.grads, -1, -2)),
                np.ascontiguousarray(np.swapaxes(self.cq.grads * self.cq.dV[..., None, None], -1, -2)))
        return self._tangent_geometry


def _displacement_chunk(F, S, P, cof, w, swap_w, voigt_grads, grads, grads_t, grads_t_dv, K):
    """`MechanicsProblem._displacement_tangent` on a chunk of elements: Kuu into K [e, (a i), (b j)],
    returns H [e, q, (a i)]."""
    ne, nq, na, _ = grads.shape
    U = np.empty((ne, nq, 8 * na, 3))  # [e, q, (k a), i]
    np.matmul(voigt_grads, np.swapaxes(F, -1, -2), out=U[:, :, : 6 * na])
    np.matmul(grads, np.swapaxes(P, -1, -2), out=U[:, :, 6 * na : 7 * na])
    np.matmul(grads, np.swapaxes(cof, -1, -2), out=U[:, :, 7 * na :])
    U = U.reshape(ne, nq * 8, 3 * na)
    np.matmul(np.swapaxes(U, 1, 2), U * w.reshape(ne, nq * 8, 1), out=K)
    K = K.reshape(ne, na, 3, na, 3)
    H = U.reshape(ne, nq, 8, 3 * na)[:, :, 7]
    swapped = np.swapaxes(H, 1, 2) @ (H * swap_w[..., None])  # Σ_q c H[a, i] H[b, j]
    K -= swapped.reshape(ne, na, 3, na, 3).transpose(0, 1, 4, 3, 2)  # −Σ_q c H[a, j] H[b, i]
    S_grads = (S @ grads_t).reshape(ne, nq * 3, na)  # [e, (q I), b]
    geometric = np.swapaxes(grads_t_dv.reshape(ne, nq * 3, na), 1, 2) @ S_grads  # Σ_q dV ∇φ_a S ∇φ_b
    for i in range(3):
        K[:, :, i, :, i] += geometric
    return H


def _surface_moments(dofmap, facets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """w_d = ∫_S φ_d dA (mm²) and m_d = ∫_S φ_d X dA (mm³, [ndofs, 3]) over the triangles `facets` in the
    reference configuration, for every dof d (zero off S; a P2 vertex's w is zero, its edges' carry
    the area), by the degree-3 triangle rule (exact: a quadratic φ times a linear X)."""
    X, W = get_quadrature(RefTri, 3)
    lam = np.vstack([1 - X.sum(axis=0), X])
    vals, _ = simplex_shape(dofmap.order, lam)
    fd = facet_dofs(dofmap, facets)
    corners = dofmap.points[facets]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    dA = 2.0 * area[:, None] * W[None, :]  # [nf, nq]; the reference triangle's weights sum to 1/2
    xq = np.einsum("fvi,vq->fqi", corners, lam)
    w = np.bincount(fd.ravel(), weights=np.einsum("bq,fq->fb", vals, dA).ravel(), minlength=dofmap.n_dofs)
    m = np.stack([np.bincount(fd.ravel(), weights=np.einsum("bq,fq,fq->fb", vals, dA, xq[..., i]).ravel(),
                              minlength=dofmap.n_dofs) for i in range(3)], axis=1)
    return w, m


def _det_cofactor(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J = det F and cof F = J F⁻ᵀ = ∂J/∂F for F [..., 3, 3]: the columns of cof F are the cross
    products of F's columns (f1 × f2, f2 × f0, f0 × f1), written out component by component (no
    inversion: finite where F is singular), on the components laid out contiguously (points last).
    On 39,000 points 1.3 ms, against 2.9 ms on strided views of F; np.linalg.det + inv took 4.9 ms on
    11,144."""
    f = np.moveaxis(F, (-2, -1), (0, 1)).copy()  # f[i, j] = F_ij over the points, contiguous
    cof = np.empty_like(f)
    for col, (a, b) in enumerate(((1, 2), (2, 0), (0, 1))):  # column a × column b
        np.subtract(f[1, a] * f[2, b], f[2, a] * f[1, b], out=cof[0, col])
        np.subtract(f[2, a] * f[0, b], f[0, a] * f[2, b], out=cof[1, col])
        np.subtract(f[0, a] * f[1, b], f[1, a] * f[0, b], out=cof[2, col])
    J = f[0, 0] * cof[0, 0] + f[1, 0] * cof[1, 0] + f[2, 0] * cof[2, 0]
    return J, np.ascontiguousarray(np.moveaxis(cof, (0, 1), (-2, -1)))


def _skew(a: np.ndarray) -> np.ndarray:
    """[a]x with [a]x v = a × v, for a [..., 3]."""
    z = np.zeros(a.shape[:-1])
    return np.stack([np.stack([z, -a[..., 2], a[..., 1]], -1),
                     np.stack([a[..., 2], z, -a[..., 0]], -1),
                     np.stack([-a[..., 1], a[..., 0], z], -1)], -2)
