"""What `heartctl generate` asks for, checked and resolved against the store before Ray starts: the
sweep's grid and settings (SweepSpec), the store's attributes, the cases left, and the run's plan.

Options left None take the store's values when it is resumed, else the --local preset's or the
paper's (grid.resolve_spec). Every refusal is one line (ValueError, StoreError or MeshError).
"""
from __future__ import annotations

from dataclasses import dataclass

from .grid import SweepSpec


@dataclass(frozen=True)
class SweepRequest:
    """A sweep as asked: the `store`; the grid as the command line spells it (comma-separated
    `pressures` mmHg, `stiffness` Pa, `endo` and `epi` helix angles in degrees; None = the store's or
    the default); the shape set (`shapes` of the shape model's version `shape_model` at `seed` meshed to
    about `nodes` nodes, or the ED mesh files `meshes`, a folder or a glob, in `mesh_units`); and how it runs: `local`
    (two cores, a tiny grid), `num_cpus` of a local Ray or a cluster at `address`, `max_in_flight`
    tasks, `retry_failed`, `retry_damaged` (damage is repaired, not refused), and `dry_run` (a plan,
    nothing written)."""

    store: str
    shapes: int | None = None
    pressures: str | None = None
    stiffness: str | None = None
    endo: str | None = None
    epi: str | None = None
    fidelity: str | None = None
    base: str | None = None
    fibres: str | None = None
    seed: int | None = None
    shape_model: int | None = None
    nodes: int | None = None
    meshes: str | None = None
    mesh_units: str | None = None
    local: bool = False
    address: str | None = None
    num_cpus: int | None = None
    max_in_flight: int | None = None
    retry_failed: bool = False
    retry_damaged: bool = False
    dry_run: bool = False

    def __post_init__(self):
        if self.num_cpus is not None and self.num_cpus < 1:
            raise ValueError(f"`num_cpus` must be ≥ 1, got {self.num_cpus}")
        if self.max_in_flight is not None and self.max_in_flight < 1:
            raise ValueError(f"`max_in_flight` must be ≥ 1, got {self.max_in_flight}")
        if self.address is not None and self.local:
            raise ValueError("`local` starts its own two-core Ray; it does not take `address`")
        if self.address is not None and self.num_cpus is not None:
            raise ValueError("`num_cpus` sizes a local Ray; a cluster joined with `address` has its own CPUs")

    @property
    def local_cpus(self) -> int | None:
        """CPUs of the local Ray: --num-cpus, else 2 in --local mode, else None (all cores)."""
        return self.num_cpus or (2 if self.local else None)


@dataclass(frozen=True)
class ResolvedSweep:
    """A request resolved against its store: the spec to run, the store's attributes (None: a new
    store) and, for a run on an existing store, its counts (done, failed, to_run; else None)."""

    request: SweepRequest
    spec: SweepSpec
    stored: dict | None
    left: dict | None

    def high_pressures(self) -> list[float]:
        """Pressures above end-diastolic ones: allowed (the solver decides), likely a systolic value typed by mistake."""
        from solver.parameters import HIGHEST_ED_PRESSURE_MMHG

        return [p for p in self.spec.pressure_mmhg if p > HIGHEST_ED_PRESSURE_MMHG]

    def nothing_to_run(self, retry_damaged: bool) -> bool:
        """Whether the store holds every case already (damage is found only by reading every case, in the sweep)."""
        return self.left is not None and not retry_damaged and self.left["to_run"] == 0

    def plan(self, warm_start: bool):
        """The dry run's plan: cases, a calibration solve's timing, core-hours and the store's size."""
        from .plan import cluster_cores, make_plan

        req = self.request
        return make_plan(self.spec, req.store, self.stored, cores=req.local_cpus or cluster_cores(),
                         warm_start=warm_start, retry_failed=req.retry_failed)


def resolve_sweep(request: SweepRequest) -> ResolvedSweep:
    """Check the request and resolve it against its store, read-only: every --meshes file must be a
    usable ED mesh, the grid must parse, and the store must accept the spec (sweep.check_request)."""
    from solver.mesh import MeshError
    from storage.meshfiles import read_mesh
    from storage.location import reading_store
    from storage.reader import PairReader
    from storage.schema import inspect_store

    from .grid import AXIS_OPTIONS, find_meshes, parse_axis, resolve_spec
    from .sweep import check_request, remaining_cases

    r = request
    explicit = {"shapes": r.shapes, "fidelity": r.fidelity, "seed": r.seed, "nodes": r.nodes, "base": r.base,
                "fibres": r.fibres, "mesh_units": r.mesh_units, "shape_model_version": r.shape_model}
    if r.meshes is not None:
        explicit["meshes"] = find_meshes(r.meshes)
        explicit["shapes"] = explicit["shapes"] or len(explicit["meshes"])
        for path in explicit["meshes"]:  # every file must be a usable ED mesh before anything runs
            read_mesh(path, r.mesh_units or "mm")
    for axis, text in zip(AXIS_OPTIONS, (r.pressures, r.stiffness, r.endo, r.epi)):
        explicit[axis] = parse_axis(AXIS_OPTIONS[axis], text)
    with reading_store(r.store, keep=(MeshError, ValueError, OSError)):  # argument and file errors keep their words
        stored = inspect_store(r.store)
        spec = resolve_spec(explicit, local=r.local, stored_attrs=stored)
        if r.mesh_units is not None and not spec.meshes:
            raise ValueError("`units` gives the length unit of `meshes` files; this sweep meshes the shape model")
        reader = PairReader(r.store) if stored is not None else None  # the store, opened once for every check
        stored = check_request(spec, r.store, for_writing=not r.dry_run, retry_damaged=r.retry_damaged, reader=reader)
        left = remaining_cases(spec, r.store, r.retry_failed, reader) if stored is not None and not r.dry_run else None
    return ResolvedSweep(r, spec, stored, left)
