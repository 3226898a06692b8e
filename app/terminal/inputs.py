"""A command's inputs checked the way every command checks them: the mesh file read and its warnings
printed, the output path, the parameters, the solver threads, and the memory a solve needs; each
refusal one line and exit status 2."""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

from . import console
from .console import fail, size_text, warnings_as_lines


def check_fibres(rule: str) -> None:
    from solver.fibres import check_fibre_rule

    check_fibre_rule(rule)


def set_solver_threads(threads: int | None) -> None:
    """Threads for the sparse solver and BLAS (set before they load); None leaves the environment's;
    exit 2 below 1."""
    if threads is None:
        return
    if threads < 1:
        fail(f"--threads must be ≥ 1, got {threads}")
    for var in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)


def case_parameters(pressure, stiffness, endo, epi):
    from solver.parameters import CaseParameters

    return CaseParameters(float(pressure), float(stiffness), float(endo), float(epi))


def check_output(out: Path, source: Path | None = None) -> None:
    """storage.meshfiles.check_output_path, and ValueError when `out` is the input mesh `source`
    (writing the answer would replace the user's mesh)."""
    from storage.meshfiles import check_output_path

    check_output_path(out)
    if source is not None and out.exists() and source.exists() and out.resolve() == source.resolve():
        raise ValueError(f"-o {out} is the input mesh; write the result to another file")


def write_mesh_file(out: Path, *args, **kwargs) -> None:
    """storage.meshfiles.write_mesh, with an OS refusal (disk full, permissions) as a one-line error."""
    from storage.meshfiles import write_mesh

    try:
        write_mesh(out, *args, **kwargs)
    except OSError as exc:
        fail(f"cannot write {out}: {exc.strerror or exc}")


def split_names(text: str) -> tuple[str, ...]:
    """A comma-separated option as its non-empty, stripped items."""
    return tuple(item.strip() for item in text.split(",") if item.strip())


def read_mesh_file(path: Path, units: str):
    """storage.meshfiles.read_mesh, its MeshUnitsWarning (sizes no human LV has) as one line on stderr."""
    from storage.meshfiles import read_mesh

    with warnings_as_lines():
        return read_mesh(path, units)


def solve_budget(mesh_path: Path, lv, preset: str, inverse: bool):
    """solver.budget's estimate of this solve; refused in one line (exit 2) when its peak memory
    exceeds the memory available here. An adaptive solve is bounded by `reference`'s (its finest mesh)."""
    from app.unload import ADAPTIVE
    from solver.budget import estimate_solve, mesh_counts

    asked, preset = preset, ("reference" if preset == ADAPTIVE else preset)
    edges, faces = mesh_counts(lv.tets, len(lv.endo) + len(lv.epi) + len(lv.base))
    est = estimate_solve(preset, lv.n_nodes, edges, len(lv.tets), faces, inverse)
    available = console.available_memory()
    if est.peak_bytes > available:
        instead = {"fast": "a coarser mesh", "accurate": "--fidelity fast or a coarser mesh",
                   "reference": "--fidelity accurate or fast, or a coarser mesh"}[preset]
        fail(f"{mesh_path}: the {asked} {'inverse ' if inverse else ''}solve of {lv.n_nodes:,} nodes "
             f"({est.unknowns:,} unknowns) needs about {size_text(est.peak_bytes)}; {size_text(available)} are available: "
             f"use {instead}")
    return est if asked == preset else replace(est, preset=f"{asked} (at most {preset}'s)")


