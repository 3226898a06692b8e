"""Import of the original paper's public dataset (Loaded2UnNet, SiyuMU, MIT licence):
`ED{shape}_{P}_{C}_{endo}_{epi}.vtu` / `unloaded{shape}_…vtu` pairs in cm → done cases of our store.

The file name drops the epicardial angle's sign; it is restored (θepi = −epi). Coordinates are cm and
are converted to mm. All files of a shape must share one topology; pairs that do not are skipped
and counted. The parameter grid of the dataset is incomplete: grid positions with no pair are
recorded as failed with the reason "absent from the source dataset" (never as data). Shapes get
ids 0…N−1 in the order of the source's shape numbers, which are kept as the `source_shape` attribute
with the source split (train / val / test) and the file names of every case."""
from __future__ import annotations

import os
import re
import shutil
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from solver.parameters import CaseParameters, ParameterError

from .location import StoreError, is_url
from .schema import DONE, FAILED, inspect_store
from .writer import PairStore, stats_row

NAME = re.compile(r"^(ED|unloaded)(\d+)_(\d+(?:\.\d+)?)_(\d+(?:\.\d+)?)_(\d+(?:\.\d+)?)_(\d+(?:\.\d+)?)\.vtu$")
CM_TO_MM = 10.0
SOURCE = "GitHub SiyuMU/Loaded2UnNet dataset (MIT licence, Copyright (c) 2025 SiyuMU)"
ABSENT = "absent from the source dataset"


@dataclass
class SourcePair:
    shape: int
    params: tuple  # (P mmHg, C Pa, θendo °, θepi °) with the epicardial sign restored
    ed_path: Path
    unloaded_path: Path
    split: str | None  # train / val / test folder of the source, if any


@dataclass
class ImportReport:
    found_files: int = 0
    pairs: int = 0
    imported: int = 0
    skipped: dict = field(default_factory=dict)  # reason → [file names]
    shapes: int = 0

    def skip(self, reason: str, name: str) -> None:
        self.skipped.setdefault(reason, []).append(name)

    @property
    def n_skipped(self) -> int:
        return sum(len(v) for v in self.skipped.values())

    def skipped_files(self) -> list[tuple[str, str]]:
        """(file name, reason) of every skipped file, by name."""
        return sorted((name, reason) for reason, names in self.skipped.items() for name in names)

    def nothing_imported(self, root) -> str:
        """The one line of an import that found no usable pair, with the first skipped file's reason."""
        files = self.skipped_files()
        first = f": {files[0][0]}: {files[0][1]}" + (", …" if len(files) > 1 else "") if files else ""
        return f"no pair could be imported from {root} ({len(files)} files skipped{first})"


def _split_of(path: Path, root: Path) -> str | None:
    for part in path.relative_to(root).parts[:-1]:
        if part.lower() in ("train", "val", "test"):
            return part.lower()
    return None


def find_pairs(root: str | os.PathLike, report: ImportReport) -> list[SourcePair]:
    """Every ED/unloaded pair under root (any depth), matched by their common suffix."""
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root} is not a folder")
    files = {"ED": {}, "unloaded": {}}
    for path in sorted(root.rglob("*.vtu")):
        report.found_files += 1
        m = NAME.match(path.name)
        if not m:
            report.skip("malformed name", path.name)
            continue
        kind, shape, p, c, endo, epi = m.groups()
        key = (int(shape), float(p), float(c), float(endo), -float(epi))
        try:
            CaseParameters(*key[1:])
        except ParameterError as exc:
            report.skip(f"parameters out of range ({exc})", path.name)
            continue
        if key in files[kind]:
            report.skip("duplicate file", path.name)
            continue
        files[kind][key] = path
    pairs = []
    for key in sorted(set(files["ED"]) | set(files["unloaded"])):
        ed, un = files["ED"].get(key), files["unloaded"].get(key)
        if ed is None or un is None:
            report.skip("unmatched (no partner file)", (ed or un).name)
            continue
        pairs.append(SourcePair(key[0], key[1:], ed, un, _split_of(ed, root)))
    report.pairs = len(pairs)
    return pairs


class UnusableFile(Exception):
    """A source file that import-l2u skips; `reason` says why in a few words, for its report."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


def _read(path: Path):
    """(points mm, tets) of one source file; UnusableFile when it is unreadable, not all linear tets,
    or has a point in no tet."""
    from solver.mesh import MeshError

    from .meshfiles import check_points_used, linear_tets, read_meshio

    try:
        m = read_meshio(path)
    except MeshError:
        raise UnusableFile("unreadable") from None
    try:
        tets = linear_tets(m, path)
    except MeshError:
        raise UnusableFile("not linear tetrahedra only") from None
    try:
        check_points_used(tets, len(m.points), path.name)
    except MeshError:
        raise UnusableFile("points in no tetrahedron") from None
    return np.asarray(m.points, dtype=float) * CM_TO_MM, tets


def import_l2u(root, location, progress=None) -> ImportReport:
    """Write every readable, topology-consistent pair under root as a done case of a new store.
    A shape's mesh comes from the first of its pairs whose ED geometry is a valid mesh (pairs before
    it are skipped with the reason). The store is built beside its final place and renamed into it
    at the end (local paths), so an interrupted import leaves nothing behind. Raises StoreError if
    no pair could be imported; a shape whose sizes are no human LV's in cm draws a MeshUnitsWarning."""
    report = ImportReport()
    if inspect_store(location) is not None or (not is_url(location) and Path(location).exists()):
        raise StoreError(f"{location} already exists; import-l2u writes a new store")
    shapes = _read_shapes(find_pairs(root, report), report, progress)
    usable = _usable_shapes(shapes, report)
    if not usable:
        raise StoreError(report.nothing_imported(root))
    axes = [sorted({d[0].params[i] for _, data in shapes.values() for d in data}) for i in range(4)]
    grid = np.array(np.meshgrid(*axes, indexing="ij")).reshape(4, -1).T
    final = str(location)
    staging = final if is_url(final) else str(Path(final).with_name(Path(final).name + ".importing"))
    if not is_url(final) and Path(staging).exists():
        shutil.rmtree(staging)
    try:
        store = PairStore.create(staging, _store_attrs(axes, grid, len(usable)))
        index = {tuple(row): k for k, row in enumerate(grid.tolist())}
        for shape_id, (shape, mesh, data) in enumerate(usable):
            _write_shape(store, shape_id, shape, mesh, data, index, report)
        if report.imported == 0:
            raise StoreError(report.nothing_imported(root))
        if staging != final:
            os.replace(staging, final)
    except BaseException:
        if staging != final and Path(staging).exists():
            shutil.rmtree(staging, ignore_errors=True)
        raise
    return report


def _read_shapes(pairs: list, report: ImportReport, progress=None) -> dict:
    """{source shape: (tets, [(pair, ed, unloaded)])} of the pairs that read and share one topology
    with their shape's first; the others are skipped with their reason."""
    by_shape = defaultdict(list)
    for pair in pairs:
        by_shape[pair.shape].append(pair)
    shapes = {}
    for shape, group in sorted(by_shape.items()):
        ref_tets, data = None, []
        for pair in group:
            reading = pair.ed_path
            try:
                ed, tets = _read(reading)
                reading = pair.unloaded_path
                un, tets_u = _read(reading)
            except UnusableFile as exc:  # a corrupt file, cells other than linear tets, a point in no tet
                reason = exc.reason
                report.skip(reason if reading == pair.ed_path else f"{reason} (its partner {reading.name})",
                            pair.ed_path.name)
                continue
            if ed.shape != un.shape or not np.array_equal(tets, tets_u):
                report.skip("ED and unloaded differ in node count or connectivity", pair.ed_path.name)
                continue
            if ref_tets is None:
                ref_tets = tets
            elif not np.array_equal(tets, ref_tets):
                report.skip("topology differs from the shape's first pair", pair.ed_path.name)
                continue
            data.append((pair, ed, un))
        if data:
            shapes[shape] = (ref_tets, data)
        if progress:
            progress(shape)
    return shapes


def _usable_shapes(shapes: dict, report: ImportReport) -> list:
    """[(source shape, mesh, pairs)] of the shapes with a usable ED mesh (a shape none of whose ED
    meshes is usable gets no id); a shape whose sizes are no human LV's in cm draws a warning."""
    from solver.mesh import MeshUnitsWarning

    from .meshfiles import units_warning

    usable = []
    for shape, (tets, data) in sorted(shapes.items()):
        mesh, tried = _shape_mesh(data, tets)
        for pair, reason in tried:  # pairs whose own ED mesh is unusable (a NaN, a folded tet …)
            report.skip(f"ED mesh unusable: {reason}", pair.ed_path.name)
        data = data[len(tried):]
        if mesh is None:
            continue
        warning = units_warning(mesh, "cm", f"source shape {shape} ({data[0][0].ed_path.name})", hint=False)
        if warning is not None:
            warnings.warn(warning, MeshUnitsWarning, stacklevel=3)
        usable.append((shape, mesh, data))
    return usable


def _store_attrs(axes: list, grid: np.ndarray, n_shapes: int) -> dict:
    """The new store's root attributes: the grid of every parameter value found, and the source."""
    return {
        "grid": {"shapes": n_shapes, "pressure_mmhg": axes[0], "stiffness_pa": axes[1],
                 "helix_endo_deg": axes[2], "helix_epi_deg": axes[3]},
        "fidelity": "imported", "seed": None, "mesh_nodes": None, "base": "source pipeline",
        "n_cases_per_shape": int(len(grid)), "case_params": grid.tolist(),
        "acceptance": {"roundtrip_tol_mm": 1e-3, "min_jacobian_gt": 0.0, "finite": True},
        "source": SOURCE, "source_units": "cm (converted to mm)", "shape_source": "imported",
        "epi_sign": "restored: file names give |θepi|, θepi = −value",
    }


def _write_shape(store: PairStore, shape_id: int, shape, mesh, data: list, index: dict, report: ImportReport) -> None:
    """A source shape as shape `shape_id`: its mesh, its pairs as done cases (one shard write), every
    case of the grid it has no pair for failed as ABSENT."""
    from solver.shape_model import MODES

    store.write_shape(shape_id, mesh.nodes, mesh.tets, mesh.endo, mesh.epi, mesh.base, np.full(len(MODES), np.nan),
                      {"source_shape": shape, "source_split": data[0][0].split, "n_source_pairs": len(data)})
    present, files = set(), {}
    # the acceptance checks (finite, no inverted tet, min det F > 0) apply; no solve ran here,
    # so the solver's round trip and residual pass trivially and are stored as NaN
    cases = {index[tuple(pair.params)]: (pair, ed, un, _min_jacobian(un, ed, mesh.tets)) for pair, ed, un in data}
    reasons = store.write_pairs(shape_id, {k: (un, ed, {"roundtrip_error_mm": 0.0, "min_jacobian": min_j,
                                                        "final_residual": 0.0})
                                           for k, (_, ed, un, min_j) in cases.items()})
    for k, (pair, _, _, min_j) in cases.items():
        if reasons[k] is not None:
            report.skip(reasons[k], pair.ed_path.name)
            continue
        store.set_case(shape_id, k, DONE, stats_row({"min_jacobian": min_j}))
        present.add(k)
        files[str(k)] = [pair.ed_path.name, pair.unloaded_path.name]
        report.imported += 1
    for k in range(len(index)):
        if k not in present:
            store.set_case(shape_id, k, FAILED, stats_row({}), reason=ABSENT)
    store.update_shape_attrs(shape_id, source_shape=shape, source_split=data[0][0].split, source_files=files)
    store.flush()
    report.shapes += 1


def _shape_mesh(data: list, tets: np.ndarray) -> tuple:
    """(the shape's mesh from the first pair whose ED geometry makes a valid mesh, or None;
    [(pair, reason)] of the pairs tried before it, each unusable)."""
    from solver.mesh import MeshError, make_mesh

    tried = []
    for pair, ed, _ in data:
        try:
            return make_mesh(ed, tets), tried
        except MeshError as exc:
            tried.append((pair, str(exc)))
    return None, tried


def _min_jacobian(unloaded: np.ndarray, ed: np.ndarray, tets: np.ndarray) -> float:
    """min det F of the piecewise-linear map unloaded → ED."""
    def edges(x):
        e = x[tets]
        return np.stack([e[:, 1] - e[:, 0], e[:, 2] - e[:, 0], e[:, 3] - e[:, 0]], axis=2)

    F = edges(ed) @ np.linalg.inv(edges(unloaded))
    return float(np.linalg.det(F).min())
