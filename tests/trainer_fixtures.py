"""Tiny synthetic stores for the trainer tests: real gmsh LV meshes (~120 nodes), unloaded geometries
from a smooth closed-form shrink that depends on P and C (no FE solve), written with the PairStore API.

The heavier imports (gmsh, scikit-fem, zarr) are made where they are used: a GPU host that has only
torch, PyG, numpy and meshio runs the CUDA tests (scripts/gpu_check.sh) on the meshes saved in
tests/data (lv_mesh falls back to them; written from the gmsh meshes with storage.meshfiles.write_mesh)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

_MESHES: dict = {}
SAVED_MESHES = Path(__file__).parent / "data"


def saved_mesh_path(shape_id: int, seed: int = 0, nodes: int = 120) -> Path:
    return SAVED_MESHES / f"lv_shape{shape_id}_seed{seed}_nodes{nodes}.vtu"


def tiny_spec(shapes: int = 4, seed: int = 0, pressures=(8.0, 12.0), stiffness=(100.0, 200.0)):
    from orchestrator.grid import SweepSpec

    # version 1: the meshes these stores hold (lv_mesh, and their copies in tests/data)
    return SweepSpec(shapes=shapes, pressure_mmhg=pressures, stiffness_pa=stiffness, helix_endo_deg=(60.0,),
                     helix_epi_deg=(-60.0,), fidelity="fast", seed=seed, nodes=120, shape_model_version=1)


def lv_mesh(shape_id: int, seed: int = 0, nodes: int = 120):
    """The gmsh mesh of a shape, or without gmsh/scikit-fem its copy saved in tests/data."""
    key = (shape_id, seed, nodes)
    if key not in _MESHES:
        try:
            import gmsh  # noqa: F401  (solver.meshing imports it only when meshing)

            from solver.meshing import mesh_lv
            from solver.shape_model import lv_shape
        except ImportError:
            from storage.meshfiles import read_mesh

            _MESHES[key] = read_mesh(saved_mesh_path(shape_id, seed, nodes))
        else:
            _MESHES[key] = mesh_lv(lv_shape(shape_id, seed), nodes)
    return _MESHES[key]


def synthetic_unloaded(nodes: np.ndarray, pressure_mmhg: float, stiffness_pa: float) -> np.ndarray:
    """A smooth, P- and C-dependent shrink towards the long axis and the base (mm)."""
    s = 0.012 * pressure_mmhg * (100.0 / stiffness_pa) ** 0.5
    z = nodes[:, 2]
    depth = -z / max(-z.min(), 1e-9)  # 0 at the base, 1 at the apex
    out = nodes.copy()
    out[:, :2] *= (1.0 - s * (1.0 + 0.3 * depth))[:, None]
    out[:, 2] *= 1.0 - 0.5 * s
    return out


def make_tiny_store(path, shapes: int = 4, seed: int = 0, pressures=(8.0, 12.0), stiffness=(100.0, 200.0),
                    attrs: dict | None = None, shift_mm: float = 0.0, schema_version: int = 2) -> str:
    """Write a store with every case done (unloaded geometries moved by shift_mm along x); returns its
    location. schema_version 1: a chunk per case and array, no case_layout attribute (local paths)."""
    from storage.schema import DONE
    from storage.writer import PairStore, stats_row

    spec = tiny_spec(shapes, seed, pressures, stiffness)
    store = PairStore.create(str(path), {**spec.store_attrs(), **(attrs or {}),
                                         **({"schema_version": 1} if schema_version == 1 else {})})
    if schema_version == 1:
        import zarr

        root = zarr.open_group(str(path), mode="r+")
        root.attrs.put({k: v for k, v in root.attrs.asdict().items() if k != "case_layout"})
        store = PairStore.open(str(path))
    params = spec.case_params()
    for s in range(shapes):
        m = lv_mesh(s, seed)
        store.write_shape(s, m.nodes, m.tets, m.endo, m.epi, m.base, np.zeros(3), {})
        stats = {"min_jacobian": 0.9, "roundtrip_error_mm": 1e-6, "final_residual": 1e-9}
        pairs = {k: (synthetic_unloaded(m.nodes, p, c) + [shift_mm, 0.0, 0.0], m.nodes, stats)
                 for k, (p, c, _, _) in enumerate(params)}
        for k, reason in store.write_pairs(s, pairs).items():  # the shape's shard written once
            assert reason is None, reason
            store.set_case(s, k, DONE, stats_row({**stats, "run": 0}))
    store.flush()
    return str(path)


def case_chunk(store, shape_id: int, name: str, k: int) -> tuple[Path, int, int]:
    """(file, offset, length) of the stored bytes of case k of a local store's case array `name`
    (unloaded or loaded): its inner chunk in the shape's shard (the shard index at the file's end: an
    (offset, length) uint64 pair per case, then a CRC-32C), or its own chunk file in a version 1 store."""
    import zarr

    array = zarr.open_group(str(store), mode="r")[f"shapes/{shape_id}/{name}"]
    folder = Path(store) / "shapes" / str(shape_id) / name / "c"
    if array.shards is None:
        path = folder / str(k) / "0" / "0"
        return path, 0, path.stat().st_size
    path = folder / str(k // array.shards[0]) / "0" / "0"
    per_shard = array.shards[0]
    data = path.read_bytes()
    from storage.schema import SHARD_INDEX_BYTES_PER_CASE

    index_bytes = SHARD_INDEX_BYTES_PER_CASE * per_shard
    index = np.frombuffer(data[len(data) - index_bytes - 4:-4], dtype="<u8").reshape(per_shard, 2)
    offset, length = index[k % per_shard]
    return path, int(offset), int(length)


def flip_index_byte(store, shape_id: int, name: str = "unloaded") -> None:
    """Change one bit in the index at the end of a shape's shard of the case array `name` (local store)."""
    path = case_chunk(store, shape_id, name, 0)[0]
    data = bytearray(path.read_bytes())
    data[-10] ^= 0x04  # inside the last case's (offset, length), before the index's CRC-32C
    path.write_bytes(bytes(data))


def flip_byte(store, shape_id: int, name: str, k: int, where: float = 0.5, bit: int = 0x01) -> None:
    """Change one bit in the stored bytes of case k (at `where` of its chunk's length)."""
    path, offset, length = case_chunk(store, shape_id, name, k)
    data = bytearray(path.read_bytes())
    data[offset + int(length * where)] ^= bit
    path.write_bytes(bytes(data))
