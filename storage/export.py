"""A done case as a mesh file for ParaView: its unloaded (or loaded) geometry with the displacement
and the ED mesh as point data, and its tagged surfaces."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .location import reading_store
from .reader import PairReader
from .schema import PARAM_NAMES


def case_to_meshio(reader: PairReader, shape_id: int, k: int, geometry: str = "unloaded"):
    """A meshio mesh of a done case: points = the unloaded (or loaded) geometry; point data
    `displacement` = loaded − unloaded (mm), `ed_reference`; tets + tagged surface triangles."""
    import meshio

    from .meshfiles import SURFACE_CODES, TAG_NAME

    case = reader.case(shape_id, k)
    s = reader.shape_arrays(shape_id)
    if geometry not in ("unloaded", "loaded"):
        raise ValueError("geometry must be 'unloaded' or 'loaded'")
    points = (case.unloaded if geometry == "unloaded" else case.loaded).astype(np.float64)
    tris = np.vstack([s["endo"], s["epi"], s["base"]])
    codes = np.concatenate([np.full(len(s[n]), SURFACE_CODES[n], np.int32) for n in ("endo", "epi", "base")])
    mesh = meshio.Mesh(points, [("tetra", s["tets"].astype(np.int64)), ("triangle", tris.astype(np.int64))],
                       point_data={"displacement": (case.loaded - case.unloaded).astype(np.float64),
                                   "ed_reference": case.ed_reference.astype(np.float64)},
                       cell_data={TAG_NAME: [np.zeros(len(s["tets"]), np.int32), codes]})
    mesh.field_data = {}
    return mesh


def export_case(location, shape_id: int, k: int, out, geometry: str = "unloaded") -> dict:
    """Write a done case as a mesh file (VTU etc.), atomically. Returns the case parameters."""
    import meshio

    from .meshfiles import _format_of, atomic_write

    if geometry not in ("unloaded", "loaded"):
        raise ValueError("geometry must be 'unloaded' or 'loaded'")
    with reading_store(location):
        reader = PairReader(location)
        mesh = case_to_meshio(reader, shape_id, k, geometry)
        params = dict(zip(PARAM_NAMES, map(float, reader.case_params(shape_id)[k])))
    out = Path(out)
    atomic_write(out, lambda tmp: meshio.write(tmp, mesh, file_format=_format_of(out)))
    return params
