"""Mesh files in and out (any meshio format): unit conversion to and from mm, surface tags,
and atomic writes (a temporary file renamed into place, so nothing half-written is left)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from solver.mesh import MeshError, TetMesh, check_coordinates, make_mesh

UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
SURFACE_CODES = {"endo": 1, "epi": 2, "base": 3}
TAG_NAME = "surface"


def unit_scale(units: str) -> float:
    try:
        return UNIT_TO_MM[units]
    except KeyError:
        raise ValueError(f"unknown length unit {units!r}; choose mm, cm or m") from None


# sizes a human LV at end-diastole can have, healthy or diseased (small hypertrophied to dilated)
HUMAN_LV_RANGE = {"long_axis_mm": (30.0, 200.0), "wall_mm": (1.5, 40.0), "cavity_ml": (10.0, 1500.0)}
_SIZE_WORDS = {"long_axis_mm": ("LV long axis", "mm"), "wall_mm": ("wall", "mm"), "cavity_ml": ("cavity", "mL")}
_SIZE_POWER = {"long_axis_mm": 1, "wall_mm": 1, "cavity_ml": 3}


def units_warning(mesh: TetMesh, units: str, name: str, hint: bool = True) -> str | None:
    """One line when the mesh (read in `units`, now in mm) has sizes no human LV has, naming the
    unit that would give human sizes ("…: this looks like cm; pass --units cm"), or None when its
    sizes are plausible. hint: end with the --units to pass (False where the unit is fixed)."""
    from solver.mesh import lv_dimensions

    dims = {k: v for k, v in lv_dimensions(mesh).items() if v is not None}

    def plausible(factor: float) -> bool:
        return all(lo <= dims[k] * factor ** _SIZE_POWER[k] <= hi for k, (lo, hi) in HUMAN_LV_RANGE.items() if k in dims)

    if plausible(1.0):
        return None
    sizes = ", ".join(f"{_SIZE_WORDS[k][0]} {v:.3g} {_SIZE_WORDS[k][1]}" for k, v in dims.items())
    scale = unit_scale(units)
    fits = [u for u in UNIT_TO_MM if u != units and plausible(UNIT_TO_MM[u] / scale)]
    if len(fits) == 1:
        return (f"{name}: {sizes} read in {units}: this looks like {fits[0]}"
                + (f"; pass units={fits[0]}" if hint else f", not {units}"))
    ranges = ", ".join(f"{_SIZE_WORDS[k][0]} {lo:g}–{hi:g} {_SIZE_WORDS[k][1]}" for k, (lo, hi) in HUMAN_LV_RANGE.items())
    return f"{name}: {sizes} read in {units}: outside a human LV's sizes ({ranges}); check the mesh's length unit"


def read_mesh(path: str | os.PathLike, units: str = "mm", check_units: bool = True) -> TetMesh:
    """Read a linear tet mesh; coordinates converted to mm. Surfaces come from a `surface` triangle
    tag (1 endo, 2 epi, 3 base) when present, otherwise they are found from the geometry.
    check_units: a MeshUnitsWarning (units_warning) when the sizes are no human LV's; its text is
    kept in the mesh's info["units_warning"] too."""
    scale = unit_scale(units)
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"mesh file {path} does not exist")
    m = read_meshio(path)
    tets = linear_tets(m, path)
    points = np.asarray(m.points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"{path} must have 3-D points")
    _check_indices(tets, points.shape[0], path, "tetrahedra")
    check_points_used(tets, points.shape[0], path)
    try:
        check_coordinates(points, scale, units)  # before scaling: 1e306 m would overflow to inf
    except MeshError as exc:
        raise MeshError(f"{path}: {exc}") from None
    surfaces = _tagged_surfaces(m, path)
    mesh = make_mesh(points * scale, tets, *surfaces, info={"source": str(path), "units": units})
    if check_units:
        message = units_warning(mesh, units, path.name)
        if message is not None:
            import warnings

            from solver.mesh import MeshUnitsWarning

            mesh.info["units_warning"] = message
            warnings.warn(message, MeshUnitsWarning, stacklevel=2)
    return mesh


def check_points_used(tets: np.ndarray, n_points: int, path) -> None:
    """MeshError when a point belongs to no tetrahedron. Such a point has no stiffness, and dropping
    it would renumber the nodes, so that the output's nodes and point data would not be the input's."""
    unused = np.setdiff1d(np.arange(n_points), tets)
    if unused.size:
        raise MeshError(f"{path} has {unused.size} points that belong to no tetrahedron (e.g. point {unused[0]}); "
                        f"remove them, so that the output's nodes are the input's")


def _check_indices(cells: np.ndarray, n_points: int, path, what: str) -> None:
    """MeshError when a cell refers to a point the file does not have (negative or past the last)."""
    bad = (cells < 0) | (cells >= n_points)
    if bad.any():
        raise MeshError(f"{path}: {what} refer to point {int(cells[bad][0])}, but the file's points are numbered "
                        f"0–{n_points - 1}")


def read_meshio(path: Path):
    """meshio.read, quiet, with any failure (meshio raises many types, even SystemExit, for corrupt
    files) as a one-line MeshError."""
    import contextlib
    import io

    import meshio

    chatter = io.StringIO()
    try:
        with contextlib.redirect_stdout(chatter), contextlib.redirect_stderr(chatter):
            return meshio.read(path)
    except (Exception, SystemExit) as exc:
        reason = " ".join(chatter.getvalue().split()) if isinstance(exc, SystemExit) else str(exc).split("\n")[0]
        raise MeshError(f"cannot read mesh file {path}: {reason or type(exc).__name__}") from None


VOLUME_CELLS = ("tetra10", "hexahedron", "hexahedron20", "hexahedron27", "wedge", "wedge12", "wedge15", "pyramid",
                "pyramid13", "pyramid14", "polyhedron")


def linear_tets(m, path) -> np.ndarray:
    """The linear tetrahedra of a meshio mesh [m, 4]; MeshError when there are none, or when other
    volume cells (wedges, hexahedra, quadratic tets …) fill part of the wall and would be dropped."""
    kinds = {c.type for c in m.cells}
    other = sorted(k for k in kinds if k.startswith(VOLUME_CELLS))
    tets = [c.data for c in m.cells if c.type == "tetra"]
    if not tets:
        raise MeshError(f"{path} has no linear tetrahedra (cell types: {', '.join(sorted(kinds)) or 'none'})")
    if other:
        n = sum(len(c.data) for c in m.cells if c.type in other)
        raise MeshError(f"{path} has {n} volume cells that are not linear tetrahedra ({', '.join(other)}); "
                        f"heartctl needs a mesh of linear tetrahedra only")
    return np.vstack(tets).astype(np.int64)


def _tagged_surfaces(m, path):
    if TAG_NAME not in m.cell_data:
        return None, None, None
    tris, codes = [], []
    for block, data in zip(m.cells, m.cell_data[TAG_NAME]):
        if block.type == "triangle":
            tris.append(block.data)
            codes.append(np.asarray(data).ravel())
    if not tris:
        return None, None, None
    tris, codes = np.vstack(tris), np.concatenate(codes)
    unknown = ~np.isin(codes, list(SURFACE_CODES.values()))
    if unknown.any():
        raise MeshError(f"{path}: {int(unknown.sum())} triangles carry a `{TAG_NAME}` value other than "
                        f"{', '.join(f'{v} ({k})' for k, v in SURFACE_CODES.items())}, e.g. {codes[unknown][0]:g}")
    _check_indices(tris, len(m.points), path, "surface triangles")
    return tuple(tris[codes == SURFACE_CODES[k]] for k in ("endo", "epi", "base"))


def write_mesh(path: str | os.PathLike, mesh: TetMesh, nodes_mm: np.ndarray | None = None,
               point_data: dict | None = None, cell_data: dict | None = None, units: str = "mm",
               length_fields: tuple[str, ...] = ()) -> None:
    """Write tets (+ tagged surface triangles) in `units`; fields named in `length_fields` are
    converted from mm too. `cell_data` holds per-tet arrays. The write is atomic."""
    import meshio

    scale = unit_scale(units)
    nodes = mesh.nodes if nodes_mm is None else nodes_mm
    point_data = {k: (np.asarray(v) / scale if k in length_fields else np.asarray(v)) for k, v in (point_data or {}).items()}
    tris = np.vstack([mesh.endo, mesh.epi, mesh.base])
    codes = np.concatenate([np.full(len(mesh.endo), 1), np.full(len(mesh.epi), 2), np.full(len(mesh.base), 3)])
    cells = [("tetra", mesh.tets), ("triangle", tris)]
    cdata = {TAG_NAME: [np.zeros(len(mesh.tets), np.int32), codes.astype(np.int32)]}
    for k, v in (cell_data or {}).items():
        v = np.asarray(v)
        cdata[k] = [v, np.zeros((len(tris),) + v.shape[1:], v.dtype)]
    out = meshio.Mesh(nodes / scale, cells, point_data=point_data, cell_data=cdata)
    atomic_write(Path(path), lambda tmp: meshio.write(tmp, out, file_format=_format_of(Path(path))))


OUTPUT_SUFFIXES = (".vtu", ".vtk")  # keep tets, surface tags, point data (displacement) and cell data (fibres)


def check_output_path(path: str | os.PathLike) -> None:
    """ValueError unless `path` can take a written mesh: a VTK suffix (the formats that keep all we
    write: tets, surface tags, the displacement and fibre fields; meshio's .msh, .inp, .xml and
    .mdpa writers drop the fields, .stl the tets, .avs does not read back), an existing, writable
    folder, and no directory of that name."""
    path = Path(path)
    if path.suffix.lower() not in OUTPUT_SUFFIXES:
        raise ValueError(f"output {path}: write the mesh as .vtu or .vtk (the formats that keep the tets, "
                         f"surface tags and fields; convert it afterwards if you need another)")
    if path.is_dir():
        raise ValueError(f"output {path} is a directory")
    folder = path.parent
    if not folder.is_dir():
        raise ValueError(f"output folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"output folder {folder} is not writable")


def _format_of(path: Path) -> str | None:
    import meshio

    try:
        return meshio._helpers._filetypes_from_path(path)[0]
    except Exception:
        return None


def atomic_write(path: Path, writer) -> None:
    """Call writer(tmp_path) then rename over `path`; on any error the temporary file is removed."""
    path = Path(path)
    if path.exists() and path.is_dir():
        raise ValueError(f"output {path} is a directory")
    if not path.parent.exists():
        raise ValueError(f"output folder {path.parent} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; the result gets an ordinary file's mode
    try:
        writer(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
