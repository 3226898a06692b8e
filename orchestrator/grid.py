"""Which cases a sweep has: shapes × P × C × θendo × θepi, and how a request is checked against
the store it resumes."""
from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass

import numpy as np

from solver.fidelity import get_fidelity
from solver.fibres import check_fibre_rule
from solver.parameters import BASE_CONDITIONS
from solver.meshing import MESH_LEVELS, check_node_target
from solver.parameters import PAPER_GRID, CaseParameters
from solver.shape_model import SHAPE_MODEL_VERSION, check_version

AXES = ("pressure_mmhg", "stiffness_pa", "helix_endo_deg", "helix_epi_deg")
AXIS_OPTIONS = {"pressure_mmhg": "pressures", "stiffness_pa": "stiffness", "helix_endo_deg": "endo",
                "helix_epi_deg": "epi"}  # the request's name for each axis
PAPER_SHAPES = 60
DEFAULT_FIDELITY = "accurate"  # the solver's measurements put `fast` ~0.7 mm from `accurate` (> 0.1 mm)
ROUNDTRIP_TOL_FACTOR = 10.0  # accept a pair when the forward round trip is within 10× the inverse tolerance


@dataclass(frozen=True)
class SweepSpec:
    shapes: int = PAPER_SHAPES
    pressure_mmhg: tuple = PAPER_GRID["pressure_mmhg"]
    stiffness_pa: tuple = PAPER_GRID["stiffness_pa"]
    helix_endo_deg: tuple = PAPER_GRID["helix_endo_deg"]
    helix_epi_deg: tuple = PAPER_GRID["helix_epi_deg"]
    fidelity: str = DEFAULT_FIDELITY
    seed: int = 0
    nodes: int = MESH_LEVELS["default"]
    base: str = "sliding"
    fibres: str = "laplace"  # fibre rule: laplace | heartfem
    meshes: tuple = ()  # user ED mesh files as the shape set (shape id = position), instead of the model
    mesh_units: str = "mm"
    shape_model_version: int = SHAPE_MODEL_VERSION  # a resumed store keeps its own (none recorded: 1)

    def __post_init__(self):
        for axis in AXES:
            object.__setattr__(self, axis, tuple(float(v) for v in getattr(self, axis)))
        object.__setattr__(self, "meshes", tuple(str(m) for m in self.meshes))

    # ---- checks

    def validate(self) -> "SweepSpec":
        """Raise ValueError (one line) for an unusable request."""
        if not isinstance(self.shapes, int) or self.shapes < 1:
            raise ValueError(f"`shapes` must be ≥ 1, got {self.shapes}")
        for axis in AXES:
            values = getattr(self, axis)
            name = f"`{AXIS_OPTIONS[axis]}`"
            if len(values) == 0:
                raise ValueError(f"{name} is empty: the grid has no cases")
            if len(set(values)) != len(values):
                raise ValueError(f"{name} has repeated values: {', '.join(f'{v:g}' for v in values)}")
            if not all(math.isfinite(v) for v in values):
                raise ValueError(f"{name} must be finite numbers")
        # every value is checked by the solver's own parameter rules (ParameterError is a ValueError)
        mids = [getattr(self, a)[0] for a in AXES]
        for i, axis in enumerate(AXES):
            for v in getattr(self, axis):
                CaseParameters(*(v if j == i else mids[j] for j in range(len(AXES))))
        get_fidelity(self.fidelity)
        if self.seed < 0:
            raise ValueError(f"`seed` must be ≥ 0, got {self.seed}")
        check_node_target(self.nodes)
        if self.base not in BASE_CONDITIONS:
            raise ValueError(f"`base` must be one of {', '.join(BASE_CONDITIONS)}, got {self.base!r}")
        check_fibre_rule(self.fibres)
        check_version(self.shape_model_version)
        if self.meshes and self.shapes != len(self.meshes):
            raise ValueError(f"shapes={self.shapes} does not match the {len(self.meshes)} mesh files given")
        return self

    def mesh_source(self, shape_id: int) -> tuple:
        """(mesh file, units) of a user-supplied shape, or () for a shape-model member."""
        return (self.meshes[shape_id], self.mesh_units) if self.meshes else ()

    # ---- cases

    @property
    def cases_per_shape(self) -> int:
        return int(np.prod([len(getattr(self, a)) for a in AXES]))

    @property
    def n_cases(self) -> int:
        return self.shapes * self.cases_per_shape

    def case_params(self) -> np.ndarray:
        """[K, 4] parameters, k = ((iP·nC + iC)·nEndo + iEndo)·nEpi + iEpi."""
        return np.array(list(itertools.product(*(getattr(self, a) for a in AXES))), dtype=float).reshape(-1, 4)

    def mid_params(self) -> tuple:
        """A mid-grid parameter set (the calibration case)."""
        return tuple(float(np.asarray(getattr(self, a))[len(getattr(self, a)) // 2]) for a in AXES)

    # ---- store attributes

    def grows(self, attrs: dict) -> int | None:
        """The store's shape count when this request raises it (a resume that grows the store), else None."""
        stored = int(attrs["grid"]["shapes"])
        return stored if self.shapes > stored else None

    def grid_attrs(self) -> dict:
        return {"shapes": self.shapes, **{a: list(getattr(self, a)) for a in AXES}}

    def store_attrs(self) -> dict:
        fid = get_fidelity(self.fidelity)
        return {
            "grid": self.grid_attrs(),
            "fidelity": self.fidelity,
            "fidelity_settings": {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                                  for k, v in asdict(fid).items()},
            "seed": self.seed,
            "mesh_nodes": self.nodes,
            "base": self.base,
            "fibres": self.fibres,
            "shape_source": "files" if self.meshes else "shape model",
            "shape_model_version": self.shape_model_version,
            "meshes": [{"path": m, "sha256": file_digest(m)} for m in self.meshes],
            "mesh_units": self.mesh_units,
            "n_cases_per_shape": self.cases_per_shape,
            "case_params": self.case_params().tolist(),
            "case_order": "k = ((iP*nC + iC)*nEndo + iEndo)*nEpi + iEpi",
            "acceptance": {"roundtrip_tol_mm": ROUNDTRIP_TOL_FACTOR * fid.inverse_tol_mm,
                           "min_jacobian_gt": 0.0, "finite": True},
        }

    @classmethod
    def from_attrs(cls, attrs: dict) -> "SweepSpec":
        """The sweep that made a store; ValueError for a store of imported pairs (no sweep made it)."""
        if attrs.get("shape_source") == "imported":
            raise ValueError(f"this store holds pairs imported from {attrs.get('source', 'another dataset')}; "
                             f"generate cannot extend it (use a new `store`)")
        g = attrs["grid"]
        return cls(int(g["shapes"]), *(tuple(g[a]) for a in AXES), fidelity=attrs["fidelity"],
                   seed=int(attrs["seed"]), nodes=int(attrs["mesh_nodes"]), base=attrs.get("base", "sliding"),
                   fibres=attrs.get("fibres", "laplace"), meshes=tuple(m["path"] for m in attrs.get("meshes", [])),
                   mesh_units=attrs.get("mesh_units", "mm"),
                   shape_model_version=stored_shape_model_version(attrs))

    def conflicts(self, attrs: dict) -> list[str]:
        """How this request differs from the store's (empty: it may resume that store). More shapes
        than the store's is no conflict: the store grows by the shape model's next members."""
        stored = SweepSpec.from_attrs(attrs)
        out = []
        if not np.array_equal(np.asarray(attrs.get("case_params"), dtype=float).reshape(-1, 4), stored.case_params()):
            out.append("the store's case_params do not follow its grid (edited by hand?); it cannot be resumed")
        if self.shapes < stored.shapes:  # a larger count grows the store (PairStore.grow_shapes)
            out.append(f"shapes={self.shapes} (store has {stored.shapes}; shrinking a store is not supported)")
        for a in AXES:
            if not np.array_equal(np.asarray(getattr(stored, a)), np.asarray(getattr(self, a))):
                out.append(f"{AXIS_OPTIONS[a]}={_fmt(getattr(self, a))} (store has {_fmt(getattr(stored, a))})")
        if stored.fidelity != self.fidelity:
            out.append(f"fidelity={self.fidelity} (store has {stored.fidelity})")
        else:  # the same preset name, but its settings edited since (a store must not mix two solvers)
            now = self.store_attrs()["fidelity_settings"]
            saved = attrs.get("fidelity_settings") or {}
            changed = [f"{k} {saved[k]} → {now[k]}" for k in sorted(saved.keys() & now.keys()) if saved[k] != now[k]]
            if changed:
                out.append(f"the {self.fidelity} preset's settings ({', '.join(changed)})")
        if stored.seed != self.seed:
            out.append(f"seed={self.seed} (store has {stored.seed})")
        if stored.shape_model_version != self.shape_model_version and not self.meshes:
            out.append(f"shape model version {self.shape_model_version} (store has {stored.shape_model_version})")
        if stored.nodes != self.nodes:
            out.append(f"nodes={self.nodes} (store has {stored.nodes})")
        if stored.base != self.base:
            out.append(f"base={self.base} (store has {stored.base})")
        if stored.fibres != self.fibres:
            out.append(f"fibres={self.fibres} (store has {stored.fibres})")
        stored_digests = [m["sha256"] for m in attrs.get("meshes", [])]
        if stored_digests != [file_digest(m) for m in self.meshes]:
            out.append(f"`meshes` ({len(self.meshes)} files; the store was made from "
                       f"{len(stored_digests) or 'the shape model'}{' other files' if stored_digests else ''})")
        elif self.meshes and stored.mesh_units != self.mesh_units:
            out.append(f"units={self.mesh_units} (store has {stored.mesh_units})")
        return out


def stored_shape_model_version(attrs: dict) -> int:
    """The shape model version a store draws its shapes from: recorded since version 2; a store
    without the record was drawn from version 1 and keeps drawing it."""
    return int(attrs.get("shape_model_version") or 1)


def file_digest(path: str) -> str:
    """sha256 of a file (user meshes are identified by content, not by name)."""
    from storage.disk import file_sha256

    return file_sha256(path)


MESH_SUFFIXES = (".vtu", ".vtk", ".msh", ".xdmf", ".mesh", ".med", ".inp", ".ply", ".stl", ".obj", ".off")


def find_meshes(pattern: str) -> tuple:
    """A folder (its mesh files, sorted) or a glob → absolute paths; ValueError if none."""
    import glob
    from pathlib import Path

    path = Path(pattern)
    if path.is_dir():
        files = sorted(str(p.resolve()) for p in path.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    else:
        files = sorted(str(Path(p).resolve()) for p in glob.glob(pattern) if Path(p).is_file())
    if not files:
        raise ValueError(f"meshes={pattern}: no mesh files found")
    return tuple(files)


def _fmt(values) -> str:
    return ",".join(f"{v:g}" for v in values)


def parse_axis(name: str, text: str | None) -> tuple | None:
    """'4,6,8' (commas and/or spaces) → (4.0, 6.0, 8.0); None stays None; '' → () (an empty grid)."""
    if text is None:
        return None
    parts = [p for p in text.replace(",", " ").split() if p]
    try:
        return tuple(float(p) for p in parts)
    except ValueError:
        raise ValueError(f"`{name}` must be comma-separated numbers, got {text!r}") from None


LOCAL_SPEC = SweepSpec(shapes=3, pressure_mmhg=(8.0, 12.0), stiffness_pa=(100.0, 200.0), helix_endo_deg=(60.0,),
                       helix_epi_deg=(-60.0,), fidelity="fast", seed=0, nodes=MESH_LEVELS["coarse"])


def resolve_spec(explicit: dict, local: bool = False, stored_attrs: dict | None = None) -> SweepSpec:
    """Options given on the command line win; then the --local preset; then the values of the
    store being resumed; then the paper defaults. `explicit` maps SweepSpec field → value or None."""
    if local:
        base = LOCAL_SPEC
    elif stored_attrs is not None:
        base = SweepSpec.from_attrs(stored_attrs)
    else:
        base = SweepSpec()
    values = asdict(base)
    values.update({k: v for k, v in explicit.items() if v is not None})
    if stored_attrs is not None and explicit.get("shape_model_version") is None:  # a store keeps its shape model
        values["shape_model_version"] = stored_shape_model_version(stored_attrs)
    return SweepSpec(**values)


MAX_CHAIN = 6  # cases per pressure chain (one Ray task): the paper's six pressures


def pressure_chains(case_params: np.ndarray, ks, max_len: int = MAX_CHAIN) -> list[list[int]]:
    """Group case indices `ks` of one shape into pressure chains: cases with the same stiffness and
    fibre angles, in increasing pressure, at most `max_len` per chain (a longer run is split). Each
    chain is one task, whose solves warm-start each other (`orchestrator.tasks.run_chain`).

    case_params: [K, 4] (P, C, θendo, θepi) of the store's cases."""
    groups: dict[tuple, list[int]] = {}
    for k in ks:
        groups.setdefault(tuple(float(v) for v in case_params[int(k), 1:]), []).append(int(k))
    chains = []
    for members in groups.values():
        members.sort(key=lambda k: (float(case_params[k, 0]), k))
        chains += [members[i:i + max_len] for i in range(0, len(members), max_len)]
    return chains
