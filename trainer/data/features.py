"""What the network sees of a mesh: its edges (tet edges both ways), wall coordinates and regions
(base / mid / apex × endo / epi half), the linear-elastic response to a unit pressure, and a case's
graph built from them."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import torch
from torch_geometric.data import Data

from trainer.errors import TrainerError
from trainer.data.normalisation import Normalisation

N_REGIONS = 6  # base / mid / apex × endo / epi half of the wall
TET_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


def mesh_edges(tets: np.ndarray) -> torch.Tensor:
    """[2, E] long: every tet edge once in each direction, sorted, no duplicates."""
    t = np.asarray(tets, dtype=np.int64)
    e = np.concatenate([t[:, [a, b]] for a, b in TET_EDGES])
    e = np.unique(np.sort(e, axis=1), axis=0)
    both = np.concatenate([e, e[:, ::-1]])
    both = both[np.lexsort((both[:, 1], both[:, 0]))]
    return torch.from_numpy(np.ascontiguousarray(both.T))


def wall_coordinates(nodes: np.ndarray, endo_nodes: np.ndarray, epi_nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ζ, τ) per node: ζ = 0 at the base plane … 1 at the apex (by z), τ = d_endo / (d_endo + d_epi)
    (0 on the endocardium, 1 on the epicardium), from distances to the surface nodes."""
    from scipy.spatial import cKDTree

    z = nodes[:, 2]
    zeta = (z.max() - z) / max(z.max() - z.min(), 1e-12)
    if len(endo_nodes) == 0 or len(epi_nodes) == 0:
        return zeta, np.full(len(nodes), 0.5)
    d_en = cKDTree(nodes[endo_nodes]).query(nodes)[0]
    d_ep = cKDTree(nodes[epi_nodes]).query(nodes)[0]
    tau = d_en / np.maximum(d_en + d_ep, 1e-12)
    return zeta, tau


def node_regions(zeta: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Region id 0..5 = 3 · [τ ≥ ½] + (base, mid, apex third of ζ)."""
    third = np.minimum((zeta * 3).astype(np.int64), 2)
    return third + 3 * (tau >= 0.5).astype(np.int64)


RESPONSE_STIFFNESS_PA = 150.0  # the linear response's material: Guccione C (mid grid), helix ±65°
RESPONSE_PRESSURE_PA = 4000.0  # ũ = u(this pressure) / R: of order 1 on the shape model's LVs


def linear_response_feature(mesh) -> np.ndarray:
    """[n, 3] the dimensionless linear response ũ = u_lin · RESPONSE_PRESSURE_PA / R of a TetMesh
    taken as stress-free: u_lin the nodal displacement per Pa of one linear FE solve at zero strain
    (solver.lv.linear_response; sliding base, Laplace fibres at ±65°, C = RESPONSE_STIFFNESS_PA),
    R the RMS distance of the nodes from their centroid (mm). How this whole shape gives under
    pressure, which a few message-passing hops cannot work out. ũ is unchanged when the mesh is
    scaled and turns with it about z, as the unloading displacement does (trainer.data.augment).
    Raises TrainerError when the solve fails."""
    from solver.forward import SolveError
    from solver.lv import linear_response
    from solver.parameters import CaseParameters

    nodes = np.asarray(mesh.nodes, dtype=np.float64)
    radius = float(np.sqrt(((nodes - nodes.mean(axis=0)) ** 2).sum(axis=1).mean()))
    try:
        u = linear_response(mesh, CaseParameters(1.0, RESPONSE_STIFFNESS_PA, 65.0, -65.0), "fast")
    except (SolveError, ValueError) as exc:
        raise TrainerError(f"linear response of the mesh failed: {str(exc).splitlines()[0]}") from None
    return u * RESPONSE_PRESSURE_PA / max(radius, 1e-12)


@dataclass
class MeshFeatures:
    """What one mesh topology contributes to its graphs (shared by all cases of a shape)."""

    ed_mm: np.ndarray  # [n,3]
    edge_index: torch.Tensor  # [2,E]
    region: torch.Tensor  # [n] long
    zeta: np.ndarray
    tau: np.ndarray
    tets: np.ndarray = field(repr=False, default=None)
    mesh: object = field(repr=False, default=None)  # the solver TetMesh (surfaces), for the linear response
    base_nodes: np.ndarray | None = field(repr=False, default=None)  # base surface nodes: placement (coords)

    @property
    def coords_placed(self):
        """ed_mm with its base nodes, for Normalisation.coords (the mesh placed in the training frame)."""
        if self.base_nodes is None or not len(self.base_nodes):
            raise TrainerError("these mesh features carry no base nodes to place the mesh by (build them with "
                               "mesh_features from a mesh with a tagged base)")
        return self.ed_mm, self.base_nodes

    @cached_property
    def wall(self) -> torch.Tensor:
        """[n, 2] float32: (ζ, τ) per node."""
        return torch.from_numpy(np.stack([self.zeta, self.tau], axis=1).astype(np.float32))

    @cached_property
    def response(self) -> torch.Tensor:
        """[n, 3] float32: the linear response ũ of this ED geometry (linear_response_feature),
        computed on first use (~45 ms for 350 nodes, ~0.1 s for 700, one core) and shared by every
        case of the shape; an imported case with its own ED geometry (StoreCases.case_features)
        pays its own solve."""
        if self.mesh is None:
            raise TrainerError("these mesh features carry no mesh to compute the linear response on")
        mesh = self.mesh if np.array_equal(self.mesh.nodes, self.ed_mm) else self.mesh.with_nodes(self.ed_mm)
        return torch.from_numpy(linear_response_feature(mesh).astype(np.float32))


def mesh_features(mesh) -> MeshFeatures:
    """Features of a solver TetMesh (nodes in mm)."""
    nodes = np.asarray(mesh.nodes, dtype=np.float64)
    zeta, tau = wall_coordinates(nodes, mesh.endo_nodes(), mesh.epi_nodes())
    return MeshFeatures(nodes, mesh_edges(mesh.tets), torch.from_numpy(node_regions(zeta, tau)), zeta, tau,
                        np.asarray(mesh.tets), mesh, np.asarray(mesh.base_nodes()))


def case_graph(feat: MeshFeatures, params, norm: Normalisation, unloaded_mm: np.ndarray | None = None,
               labelled: bool = True, key=(-1, -1), response: bool = False) -> Data:
    """One case as a graph: x = normalised ED coordinates [n,3] of the mesh placed in the training
    frame (Normalisation.coords); y = normalised unloading
    displacement (NaN when the label is withheld or unknown); params [1,4] in [0,1]; wall [n,2] =
    the wall coordinates (ζ, τ), region [n] their base/mid/apex × endo/epi cell; with `response`,
    response [n,3] = the mesh's linear response ũ (MeshFeatures.response)."""
    x = norm.coords(*feat.coords_placed)
    if unloaded_mm is not None and labelled:
        y = (np.asarray(unloaded_mm, dtype=np.float64) - feat.ed_mm) / norm.disp_scale_mm
    else:
        y = np.full_like(x, np.nan)
    extra = {"response": feat.response} if response else {}
    return Data(x=torch.from_numpy(x.astype(np.float32)), edge_index=feat.edge_index,
                y=torch.from_numpy(y.astype(np.float32)),
                params=torch.from_numpy(norm.params(params).astype(np.float32)).view(1, -1),
                region=feat.region, wall=feat.wall,
                labelled=torch.tensor([bool(labelled and unloaded_mm is not None)]),
                key=torch.tensor([[int(key[0]), int(key[1])]], dtype=torch.long), **extra)
