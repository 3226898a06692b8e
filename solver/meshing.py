"""gmsh (Python API, no GUI) meshing of an LV shape into linear tets with a target node count,
tagged endocardium, epicardium and base, and a quality report."""
from __future__ import annotations

import numpy as np

from .mesh import TetMesh, make_mesh, orient_positive, scaled_jacobian
from .progress import report
from .shape_model import LVShape

DEFAULT_NODES = 800  # the paper's meshes have 645–692 nodes; our default range is 600–1000
MESH_LEVELS = {"coarse": 350, "default": DEFAULT_NODES, "fine": 2500}
APEX_ELEMENTS_PER_MM = 2.5  # version 2: element size at a thin apex, × its thickness
MIN_NODES, MAX_NODES = 50, 200_000  # 250× the default: a mistyped count (1e8) must not mesh until killed


def check_node_target(nodes: int, name: str = "`nodes`") -> None:
    """ValueError unless the target node count is MIN_NODES–MAX_NODES."""
    if not MIN_NODES <= nodes <= MAX_NODES:
        raise ValueError(f"{name} must be {MIN_NODES}–{MAX_NODES:,} (a target node count), got {nodes}")


def _gmsh_truncated_shell(endo_axes, epi_axes, centre_z: float, base_z: float, size_mm: float,
                          apex_size_mm: float | None = None):
    """Mesh (ellipsoid(epi) − ellipsoid(endo)) ∩ {z ≤ base_z}; returns nodes, tets, tagged triangles.
    apex_size_mm: element size at the apex (a thin apex), growing to size_mm over a few sizes."""
    import gmsh

    # the same mesh for the same input, whatever the user's ~/.gmshrc or ~/.gmsh-options and whatever
    # runs beside it: no config files, and one thread everywhere (parallel surface meshing's order
    # depends on the load)
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        for option in ("General.NumThreads", "Mesh.MaxNumThreads1D", "Mesh.MaxNumThreads2D", "Mesh.MaxNumThreads3D"):
            gmsh.option.setNumber(option, 1)
        gmsh.model.add("lv")
        occ = gmsh.model.occ
        outer = occ.addSphere(0, 0, centre_z, 1.0)
        occ.dilate([(3, outer)], 0, 0, centre_z, *epi_axes)
        inner = occ.addSphere(0, 0, centre_z, 1.0)
        occ.dilate([(3, inner)], 0, 0, centre_z, *endo_axes)
        wall, _ = occ.cut([(3, outer)], [(3, inner)])
        L = 4.0 * max(max(epi_axes), abs(centre_z) + 1.0)
        box = occ.addBox(-L, -L, base_z, 2 * L, 2 * L, 2 * L)
        occ.cut(wall, [(3, box)])
        occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.5 * size_mm if apex_size_mm is None else apex_size_mm)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size_mm)
        if apex_size_mm is not None:
            _apex_size_field(gmsh, centre_z - endo_axes[2], centre_z - epi_axes[2], size_mm, apex_size_mm)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.option.setNumber("Mesh.OptimizeNetgen", 1)
        gmsh.option.setNumber("Mesh.RandomFactor", 1e-9)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        nodes = coords.reshape(-1, 3)
        index = np.full(int(tags.max()) + 1, -1, np.int64)
        index[tags.astype(np.int64)] = np.arange(tags.size)
        etypes, _, enodes = gmsh.model.mesh.getElements(3)
        tets = index[np.concatenate([n for t, n in zip(etypes, enodes) if t == 4]).astype(np.int64)].reshape(-1, 4)
        surfaces = {}
        for dim, tag in gmsh.model.getEntities(2):
            st, _, sn = gmsh.model.mesh.getElements(dim, tag)
            tri = index[np.concatenate([n for t, n in zip(st, sn) if t == 2]).astype(np.int64)].reshape(-1, 3)
            if np.all(np.abs(nodes[np.unique(tri), 2] - base_z) < 1e-6 * L):
                kind = "base"
            else:  # which ellipsoid the surface lies on
                p = nodes[np.unique(tri)] - [0.0, 0.0, centre_z]
                on_endo = np.abs(((p / np.asarray(endo_axes)) ** 2).sum(axis=1) - 1.0).mean()
                on_epi = np.abs(((p / np.asarray(epi_axes)) ** 2).sum(axis=1) - 1.0).mean()
                kind = "endo" if on_endo < on_epi else "epi"
            surfaces.setdefault(kind, []).append(tri)
    finally:
        gmsh.finalize()
    if not all(k in surfaces for k in ("endo", "epi", "base")):
        raise RuntimeError(f"gmsh produced surfaces {sorted(surfaces)}; expected endo, epi and base")
    endo, epi, base = (np.vstack(surfaces[k]) for k in ("endo", "epi", "base"))
    used = np.unique(tets)
    remap = np.full(nodes.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    return nodes[used], remap[tets], remap[endo], remap[epi], remap[base]


def _apex_size_field(gmsh, endo_apex_z: float, epi_apex_z: float, size_mm: float, apex_size_mm: float) -> None:
    """Element size apex_size_mm near the apex (within 1.5 of it of the point between the two
    apices), growing linearly to size_mm over the next 2 × size_mm: a formula, no geometry added."""
    z0, d0 = 0.5 * (endo_apex_z + epi_apex_z), 1.5 * apex_size_mm + 0.5 * abs(endo_apex_z - epi_apex_z)
    slope = (size_mm - apex_size_mm) / (2.0 * size_mm)
    field = gmsh.model.mesh.field
    f = field.add("MathEval")
    dist = f"sqrt(x*x + y*y + (z - ({z0:.9g}))*(z - ({z0:.9g})))"
    field.setString(f, "F", f"min({size_mm:.9g}, {apex_size_mm:.9g} + {slope:.9g} * max(0, {dist} - {d0:.9g}))")
    field.setAsBackgroundMesh(f)


def _mesh_once(endo_axes, epi_axes, centre_z, base_z, size_mm, info, apex_size=None, node_map=None) -> TetMesh:
    """One gmsh mesh at element size size_mm; apex_size(size_mm) → the apex's size or None;
    node_map: a smooth map of the nodes (keeping the base plane) applied before the checks."""
    for attempt in range(4):  # gmsh may fail on a coarse mesh of a thin wall (its surfaces cross): a little finer
        apex_mm = apex_size(size_mm) if apex_size is not None else None
        try:
            nodes, tets, endo, epi, base = _gmsh_truncated_shell(endo_axes, epi_axes, centre_z, base_z, size_mm,
                                                                 apex_mm)
            break
        except Exception as exc:
            if attempt == 3 or "PLC" not in str(exc):
                raise
            size_mm *= 0.9
    nodes[np.abs(nodes[:, 2] - base_z) < 1e-9, 2] = base_z
    if node_map is not None:
        nodes = node_map(nodes)
    tets = orient_positive(nodes, tets)
    quality = scaled_jacobian(nodes, tets)
    info = dict(info, size_mm=float(size_mm), min_scaled_jacobian=float(quality.min()),
                mean_scaled_jacobian=float(quality.mean()))
    return make_mesh(nodes, tets, endo, epi, base, info=info)


def mesh_truncated_ellipsoid(endo_axes, epi_axes, centre_z: float, base_z: float,
                             target_nodes: int = DEFAULT_NODES, info=None, apex_size=None,
                             node_map=None) -> TetMesh:
    """Mesh with about `target_nodes` nodes (within ~15 %): the element size is calibrated from
    a first mesh (node count ∝ h^-3) and refined once more if needed. apex_size, node_map: as
    _mesh_once (version 2 of the shape model)."""
    check_node_target(target_nodes, "target node count")
    info = dict(info or {})
    ax, ay, c = epi_axes
    wall_volume = 4.0 / 3.0 * np.pi * (ax * ay * c - np.prod(endo_axes)) * 0.6
    size = (wall_volume / (target_nodes * 0.9)) ** (1.0 / 3.0) * 1.6
    mesh = _mesh_once(endo_axes, epi_axes, centre_z, base_z, size, info, apex_size, node_map)
    for _ in range(3 if apex_size is None else 6):  # a refined apex's nodes do not scale with the size
        ratio = mesh.n_nodes / target_nodes
        if 0.87 <= ratio <= 1.15:
            break
        report(f"gmsh made {mesh.n_nodes:,} nodes for the target {target_nodes:,}: meshing again")
        size *= ratio ** (1.0 / 3.0)
        mesh = _mesh_once(endo_axes, epi_axes, centre_z, base_z, size, info, apex_size, node_map)
    return mesh


def mesh_lv(shape: LVShape, target_nodes: int = DEFAULT_NODES) -> TetMesh:
    """The ED mesh of a shape-model member (mm, base plane z = 0)."""
    info = {"shape_id": shape.shape_id, "coefficients": list(shape.coefficients),
            "cavity_volume_ml": shape.cavity_volume_ml()}
    if not shape.has_map():
        return mesh_truncated_ellipsoid(shape.endo_semi_axes_mm, shape.epi_semi_axes_mm,
                                        -shape.base_height_mm, 0.0, target_nodes, info)
    info["shape_model_version"] = shape.version
    ta = shape.apex_thickness_mm

    def apex_size(size_mm: float) -> float | None:  # a thin apex gets elements about its thickness
        return APEX_ELEMENTS_PER_MM * ta if APEX_ELEMENTS_PER_MM * ta < 0.5 * size_mm else None

    return mesh_truncated_ellipsoid(shape.endo_semi_axes_mm, shape.epi_semi_axes_mm, -shape.base_height_mm, 0.0,
                                    target_nodes, info, apex_size, shape.map_nodes)


def mesh_lv_fresh_process(shape_id: int, seed: int, version: int, target_nodes: int) -> TetMesh:
    """mesh_lv(lv_shape(shape_id, seed, version), target_nodes), made in a new Python process.

    gmsh's result is tested to be the same in every fresh process, whatever runs beside it; a process
    that has meshed and solved for hours (a sweep's Ray worker) has been seen to make another mesh of the
    same shape once, a case not reproduced since. A store's meshes are therefore each made in a fresh
    process (~1 s more per shape), the condition under which determinism is tested."""
    import pickle
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    root = str(Path(__file__).resolve().parents[1])
    code = ("import pickle, sys; sys.path.insert(0, sys.argv[1]); from solver.meshing import mesh_lv; "
            "from solver.shape_model import lv_shape; a = pickle.load(sys.stdin.buffer); "
            "m = mesh_lv(lv_shape(a[0], a[1], a[2]), a[3]); open(sys.argv[2], 'wb').write(pickle.dumps(m))")
    with tempfile.TemporaryDirectory(prefix="heartctl-mesh-") as folder:
        result = Path(folder) / "mesh.pickle"
        done = subprocess.run([sys.executable, "-c", code, root, str(result)], capture_output=True,
                              input=pickle.dumps((int(shape_id), int(seed), int(version), int(target_nodes))))
        if done.returncode != 0 or not result.exists():
            lines = done.stderr.decode(errors="replace").strip().splitlines() or ["no message"]
            raise RuntimeError(f"meshing shape {shape_id} (seed {seed}, version {version}) failed: {lines[-1]}")
        return pickle.loads(result.read_bytes())
