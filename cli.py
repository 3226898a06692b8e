"""heartctl: the command-line interface. Parses arguments, calls the packages, formats output;
bad input → one line on stderr and exit code 2; a solve that fails → its reason and exit code 1."""
from __future__ import annotations

import json
import os
import sys
from enum import Enum
from pathlib import Path

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Unloaded LV geometry from the end-diastolic shape: FE data, training, evaluation.")
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks (print figures and ratios).")
app.add_typer(bench_app, name="bench")


class Units(str, Enum):
    mm = "mm"
    cm = "cm"
    m = "m"


class FidelityName(str, Enum):
    fast = "fast"
    accurate = "accurate"


class Base(str, Enum):
    sliding = "sliding"
    clamped = "clamped"


class UnloadMethod(str, Enum):
    fe = "fe"


class Problem(str, Enum):
    land1 = "land1"
    land2 = "land2"
    all = "all"


def fail(message: str, code: int = 2) -> None:
    """One line on stderr, then exit."""
    typer.echo(f"heartctl: error: {message}", err=True)
    raise typer.Exit(code)


def _input_errors():
    from solver.mesh import MeshError
    from solver.parameters import ParameterError

    return (MeshError, ParameterError, ValueError, FileNotFoundError, IsADirectoryError)


def _params(pressure, stiffness, endo, epi):
    from solver.parameters import CaseParameters

    return CaseParameters(float(pressure), float(stiffness), float(endo), float(epi))


def _check_output(out: Path) -> None:
    if out.exists() and out.is_dir():
        raise ValueError(f"output {out} is a directory")
    if not out.parent.exists():
        raise ValueError(f"output folder {out.parent} does not exist")


PressureOpt = typer.Option(..., "--pressure", help="ED cavity pressure, mmHg (> 0).")
StiffnessOpt = typer.Option(..., "--stiffness", help="Guccione stiffness C, Pa (> 0).")
EndoOpt = typer.Option(60.0, "--endo", help="Endocardial helix angle, degrees (|θ| ≤ 90).")
EpiOpt = typer.Option(-60.0, "--epi", help="Epicardial helix angle, degrees (the paper's −60…−70).")
FidelityOpt = typer.Option(FidelityName.accurate, "--fidelity", help="Solver preset.")
BaseOpt = typer.Option(Base.sliding, "--base", help="Base condition: sliding (z fixed) or clamped.")
UnitsOpt = typer.Option(Units.mm, "--units", help="Length unit of the input mesh; the output uses it too.")


@app.command()
def mesh(shape: int = typer.Option(..., "--shape", help="Shape id of the built-in shape model (≥ 0)."),
         out: Path = typer.Option(..., "-o", "--out", help="Output mesh file (any meshio format, e.g. .vtu)."),
         nodes: int = typer.Option(800, "--nodes", help="Target node count (default 600–1000 nodes)."),
         seed: int = typer.Option(0, "--seed", help="Shape-model seed."),
         endo: float = EndoOpt, epi: float = EpiOpt, units: Units = UnitsOpt):
    """Write the ED mesh of a shape-model member with surface tags and fibre fields."""
    from solver.fibres import fibre_frames, helix_angle_at_nodes, transmural_coordinate
    from solver.meshing import mesh_lv
    from solver.shape_model import lv_shape
    from storage.meshfiles import write_mesh

    try:
        _params(1.0, 1.0, endo, epi)
        _check_output(out)
        if nodes < 50:
            raise ValueError(f"--nodes must be ≥ 50, got {nodes}")
        shape_def = lv_shape(shape, seed)
        lv = mesh_lv(shape_def, nodes)
        phi = transmural_coordinate(lv)
        frames = fibre_frames(lv, endo, epi, np.full((4, 1), 0.25), phi)[:, 0]
        write_mesh(out, lv, point_data={"transmural": phi, "helix_angle_deg": helix_angle_at_nodes(lv, endo, epi, phi)},
                   cell_data={"fibre": frames[:, :, 0], "sheet": frames[:, :, 1]}, units=units.value)
    except _input_errors() as exc:
        fail(str(exc))
    info = lv.info
    typer.echo(f"shape {shape} (seed {seed}): {lv.n_nodes} nodes, {len(lv.tets)} tets, "
               f"EDV {shape_def.cavity_volume_ml():.1f} mL, wall {shape_def.wall_thickness_mm:.1f} mm, "
               f"min scaled Jacobian {info['min_scaled_jacobian']:.3f} → {out}")


@app.command()
def solve(mesh_path: Path = typer.Argument(..., metavar="MESH", help="Unloaded (stress-free) mesh."),
          pressure: float = PressureOpt, stiffness: float = StiffnessOpt, endo: float = EndoOpt, epi: float = EpiOpt,
          out: Path = typer.Option(..., "-o", "--out", help="Output: deformed mesh with `displacement`."),
          fidelity: FidelityName = FidelityOpt, base: Base = BaseOpt, units: Units = UnitsOpt):
    """Forward inflation of an unloaded mesh to the ED pressure."""
    from solver.forward import SolveError
    from solver.lv import forward_solve
    from storage.meshfiles import read_mesh, write_mesh

    try:
        params = _params(pressure, stiffness, endo, epi)
        _check_output(out)
        lv = read_mesh(mesh_path, units.value)
    except _input_errors() as exc:
        fail(str(exc))
    try:
        result = forward_solve(lv, params, fidelity.value, base.value)
    except SolveError as exc:
        fail(f"forward solve did not converge: {exc}", code=1)
    write_mesh(out, lv, result.loaded_nodes, point_data={"displacement": result.displacement},
               units=units.value, length_fields=("displacement",))
    disp = np.linalg.norm(result.displacement, axis=1)
    s = result.stats
    typer.echo(f"inflated to {params.label()} ({fidelity.value}, {base.value} base): "
               f"{s.load_steps} load steps, {s.newton_iterations} Newton iterations, {s.wall_s:.2f} s; "
               f"displacement mean {disp.mean():.3f} / max {disp.max():.3f} mm → {out}")


@app.command()
def unload(mesh_path: Path = typer.Argument(..., metavar="MESH", help="End-diastolic mesh."),
           pressure: float = PressureOpt, stiffness: float = StiffnessOpt, endo: float = EndoOpt, epi: float = EpiOpt,
           out: Path = typer.Option(..., "-o", "--out", help="Output: unloaded mesh with `displacement` (ED − unloaded)."),
           method: UnloadMethod = typer.Option(UnloadMethod.fe, "--method", help="fe: inverse finite elements."),
           fidelity: FidelityName = FidelityOpt, base: Base = BaseOpt, units: Units = UnitsOpt,
           tol_mm: float = typer.Option(None, "--tol-mm", help="Max nodal mismatch to stop at, mm (preset default 1e-4).")):
    """Unload a user's ED mesh: the stress-free geometry that inflates back onto it."""
    from solver.forward import SolveError
    from solver.lv import inverse_solve
    from storage.meshfiles import read_mesh, write_mesh

    try:
        params = _params(pressure, stiffness, endo, epi)
        _check_output(out)
        if tol_mm is not None and not tol_mm > 0:
            raise ValueError(f"--tol-mm must be > 0, got {tol_mm}")
        lv = read_mesh(mesh_path, units.value)
    except _input_errors() as exc:
        fail(str(exc))
    try:
        result = inverse_solve(lv, params, fidelity.value, base.value, tol_mm=tol_mm)
    except SolveError as exc:
        fail(f"inverse solve did not converge: {exc}", code=1)
    shift = lv.nodes - result.unloaded_nodes
    write_mesh(out, lv, result.unloaded_nodes, point_data={"displacement": shift},
               units=units.value, length_fields=("displacement",))
    d = np.linalg.norm(shift, axis=1)
    typer.echo(f"unloaded at {params.label()} ({fidelity.value}, {base.value} base): {result.updates} updates, "
               f"{result.stats.newton_iterations} Newton iterations, {result.stats.wall_s:.2f} s, "
               f"mismatch {result.mismatch_mm:.2e} mm; ED − unloaded mean {d.mean():.3f} / max {d.max():.3f} mm → {out}")


@app.command()
def verify(problem: Problem = typer.Option(Problem.all, "--problem", help="Land et al. 2015 problem."),
           fidelity: FidelityName = FidelityOpt,
           as_json: bool = typer.Option(False, "--json", help="One JSON object per problem on stdout.")):
    """Run the Land et al. (2015) verification problems and compare with the published values."""
    from solver.benchmarks import land1, land2

    names = ["land1", "land2"] if problem is Problem.all else [problem.value]
    for name in names:
        result = (land1 if name == "land1" else land2)(fidelity.value)
        if as_json:
            typer.echo(json.dumps(result))
        elif name == "land1":
            typer.echo(f"land1 ({fidelity.value}, {result['nodes']} nodes, {result['dofs']} dofs, {result['wall_s']:.1f} s): "
                       f"deflection z {result['deflection_z_mm']:.3f} mm vs reference {result['reference_mm']:.3f} mm "
                       f"(error {result['error_mm']:+.3f} mm)")
        else:
            typer.echo(f"land2 ({fidelity.value}, {result['nodes']} nodes, {result['dofs']} dofs, {result['wall_s']:.1f} s): "
                       f"endo apex z {result['endo_apex_z_mm']:.2f} mm (ref −26.61, {result['endo_apex_error_mm']:+.2f}), "
                       f"epi apex z {result['epi_apex_z_mm']:.2f} mm (ref −28.28, {result['epi_apex_error_mm']:+.2f}), "
                       f"cavity {result['cavity_volume_mm3']:.0f} mm³ (ref ≈10734)")


@bench_app.command("solver")
def bench_solver(fidelity: list[FidelityName] = typer.Option(None, "--fidelity", help="Presets (default: all)."),
                 nodes: int = typer.Option(1000, "--nodes", help="Target mesh node count."),
                 shape: int = typer.Option(0, "--shape"),
                 threads: int = typer.Option(1, "--threads", help="Threads for the sparse solver (goals are for 1 core)."),
                 as_json: bool = typer.Option(False, "--json")):
    """Wall time of forward and pair per preset at a mid case (8 mmHg, 150 Pa) and the extreme (14, 50)."""
    for var in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)
    from solver.benchmark_solver import run_solver_benchmark

    presets = [f.value for f in fidelity] if fidelity else ["fast", "accurate"]
    rows = run_solver_benchmark(presets, nodes, shape)
    if as_json:
        for row in rows:
            typer.echo(json.dumps(row))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"heartctl bench solver — shape {shape}, ~{nodes} nodes, {threads} thread(s)")
    for col in ("preset", "case", "nodes", "dofs", "forward s", "asm/lin/other s", "Newton", "pair s",
                "pair asm/lin/other s", "pair Newton", "round trip mm"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(r["fidelity"], r["case"], str(r["nodes"]), str(r["dofs"]), f"{r['forward_s']:.2f}",
                      f"{r['forward_assembly_s']:.2f}/{r['forward_linear_s']:.2f}/{r['forward_other_s']:.2f}",
                      str(r["forward_newton"]), f"{r['pair_s']:.2f}",
                      f"{r['pair_assembly_s']:.2f}/{r['pair_linear_s']:.2f}/{r['pair_other_s']:.2f}",
                      str(r["pair_newton"]), f"{r['roundtrip_mm']:.1e}")
    Console().print(table)


import numpy as np  # noqa: E402  (after the app so `heartctl --help` stays light)

if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
