"""`heartctl mesh`: the ED mesh of a shape-model member with the fields a user looks at in ParaView
(transmural coordinate, helix angle, fibre and sheet directions of both element orders)."""
from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class ShapeMesh:
    """A meshed shape-model member: the TetMesh `lv` (mm), its shape definition, the fields to write
    with it, and its shape descriptors (solver.descriptors)."""

    shape: int
    seed: int
    shape_model: int
    lv: object
    shape_def: object
    point_data: dict = field(repr=False)
    cell_data: dict = field(repr=False)
    descriptors: dict = field(default_factory=dict)

    @property
    def cavity_volume_ml(self) -> float:
        return float(self.shape_def.cavity_volume_ml())


def shape_mesh(shape: int, seed: int, shape_model: int, nodes: int, helix_endo_deg: float, helix_epi_deg: float,
               fidelity: str, progress=nullcontext) -> ShapeMesh:
    """Mesh shape `shape` of the shape model (version `shape_model`, `seed`) at about `nodes` nodes, with
    cell data `fibre`/`sheet` of the preset `fidelity`'s element order and `fibre_p1`/`fibre_p2` (and
    sheets) of both; `progress(nodes)` is a context the meshing runs in. ValueError for a bad input."""
    from solver.descriptors import shape_descriptors
    from solver.fibres import centroid_frames, helix_angle_at_nodes, transmural_coordinate
    from solver.fidelity import get_fidelity
    from solver.meshing import check_node_target, mesh_lv
    from solver.parameters import CaseParameters
    from solver.shape_model import lv_shape

    CaseParameters(1.0, 1.0, helix_endo_deg, helix_epi_deg)  # the angles checked as a case's
    check_node_target(nodes)
    if seed < 0:
        raise ValueError(f"`seed` must be ≥ 0, got {seed}")
    shape_def = lv_shape(shape, seed, shape_model)
    with progress(nodes):
        lv = mesh_lv(shape_def, nodes)
    phi = transmural_coordinate(lv)
    frames = {order: centroid_frames(lv, helix_endo_deg, helix_epi_deg, order) for order in (1, 2)}
    own = frames[get_fidelity(fidelity).displacement_order]
    cell_data = {"fibre": own[:, :, 0], "sheet": own[:, :, 1]}
    for order, f in frames.items():
        cell_data |= {f"fibre_p{order}": f[:, :, 0], f"sheet_p{order}": f[:, :, 1]}
    point_data = {"transmural": phi, "helix_angle_deg": helix_angle_at_nodes(lv, helix_endo_deg, helix_epi_deg, phi)}
    return ShapeMesh(shape, seed, shape_model, lv, shape_def, point_data, cell_data, shape_descriptors(lv))


def displacement_summary_mm(displacement: np.ndarray) -> tuple[float, float]:
    """(mean, max) of the nodal displacement magnitudes, mm."""
    d = np.linalg.norm(displacement, axis=1)
    return float(d.mean()), float(d.max())
