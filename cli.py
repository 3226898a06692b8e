"""heartctl: the command-line interface. Parses arguments, calls the packages, formats output;
bad input → one line on stderr and exit code 2; a solve that fails → its reason and exit code 1."""
from __future__ import annotations

import json
import os
import sys
from enum import Enum
from pathlib import Path

import typer

from trainer.config import CONFIG_HELP  # the trainer's one light module (no torch): --help stays fast

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Unloaded LV geometry from the end-diastolic shape: FE data, training, evaluation.")
bench_app = typer.Typer(help="Benchmarks (print figures and ratios).")
app.add_typer(bench_app, name="bench")


@bench_app.callback(invoke_without_command=True)
def bench_group(ctx: typer.Context) -> None:
    """`heartctl bench` alone: one line naming the benchmarks, exit 2, like any command missing what it needs."""
    if ctx.invoked_subcommand is None and not ctx.resilient_parsing:
        names = ", ".join(ctx.command.list_commands(ctx))
        typer.echo(f"heartctl: error: heartctl bench needs a benchmark: {names} (see heartctl bench --help)", err=True)
        raise typer.Exit(2)


class Units(str, Enum):
    mm = "mm"
    cm = "cm"
    m = "m"


class FidelityName(str, Enum):
    fast = "fast"
    accurate = "accurate"
    reference = "reference"  # accurate on the once-refined mesh, answered at the mesh's own nodes


class Direction(str, Enum):
    forward = "forward"
    inverse = "inverse"


class Base(str, Enum):
    sliding = "sliding"
    clamped = "clamped"
    spring = "spring"
    heartfem = "heartfem"


class UnloadMethod(str, Enum):
    fe = "fe"
    gnn = "gnn"
    hybrid = "hybrid"
    auto = "auto"  # the cheapest method that met --tolerance-mm on the run's trade table


class Problem(str, Enum):
    land1 = "land1"
    land2 = "land2"
    all = "all"


def fail(message: str, code: int = 2) -> None:
    """One line on stderr, then exit."""
    typer.echo(f"heartctl: error: {message}", err=True)
    raise typer.Exit(code)


def _check_fibres(rule: str) -> None:
    from solver.fibres import check_fibre_rule

    check_fibre_rule(rule)


def _input_errors():
    from solver.mesh import MeshError
    from solver.parameters import ParameterError

    return (MeshError, ParameterError, ValueError, FileNotFoundError, IsADirectoryError)


def _solver_threads(threads: int | None) -> None:
    """Threads for the sparse solver and BLAS (set before they load); None leaves the environment's;
    exit 2 below 1."""
    if threads is None:
        return
    if threads < 1:
        fail(f"--threads must be ≥ 1, got {threads}")
    for var in ("MKL_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = str(threads)


def _params(pressure, stiffness, endo, epi):
    from solver.parameters import CaseParameters

    return CaseParameters(float(pressure), float(stiffness), float(endo), float(epi))


def _check_output(out: Path, source: Path | None = None) -> None:
    """storage.meshfiles.check_output_path, and ValueError when `out` is the input mesh `source`
    (writing the answer would replace the user's mesh)."""
    from storage.meshfiles import check_output_path

    check_output_path(out)
    if source is not None and out.exists() and source.exists() and out.resolve() == source.resolve():
        raise ValueError(f"-o {out} is the input mesh; write the result to another file")


def _write_mesh(out: Path, *args, **kwargs) -> None:
    """storage.meshfiles.write_mesh, with an OS refusal (disk full, permissions) as a one-line error."""
    from storage.meshfiles import write_mesh

    try:
        write_mesh(out, *args, **kwargs)
    except OSError as exc:
        fail(f"cannot write {out}: {exc.strerror or exc}")


def _read_mesh(path: Path, units: str):
    """storage.meshfiles.read_mesh, its MeshUnitsWarning (sizes no human LV has) as one line on stderr."""
    from storage.meshfiles import read_mesh

    with _warnings_as_lines():
        return read_mesh(path, units)


SLOW_SOLVE_S = 30.0  # a solve expected to take longer shows its load steps or inverse updates on stderr
LARGE_MESH_NODES = 20_000  # meshing a larger target says so, with its estimate, before gmsh starts


def _available_memory() -> float:
    """Bytes of memory available to a new solve on this machine (psutil)."""
    import psutil

    return float(psutil.virtual_memory().available)


def _size(nbytes: float) -> str:
    gb = nbytes / 1e9
    return f"{gb:.0f} GB" if gb >= 9.5 else f"{gb:.1f} GB" if gb >= 0.95 else f"{nbytes / 1e6:.0f} MB"


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.0f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


def _solve_budget(mesh_path: Path, lv, preset: str, inverse: bool):
    """solver.budget's estimate of this solve; refused in one line (exit 2) when its peak memory
    exceeds the memory available here."""
    from solver.budget import estimate_solve, mesh_counts

    edges, faces = mesh_counts(lv.tets, len(lv.endo) + len(lv.epi) + len(lv.base))
    est = estimate_solve(preset, lv.n_nodes, edges, len(lv.tets), faces, inverse)
    available = _available_memory()
    if est.peak_bytes > available:
        instead = {"fast": "a coarser mesh", "accurate": "--fidelity fast or a coarser mesh",
                   "reference": "--fidelity accurate or fast, or a coarser mesh"}[preset]
        fail(f"{mesh_path}: the {preset} {'inverse ' if inverse else ''}solve of {lv.n_nodes:,} nodes "
             f"({est.unknowns:,} unknowns) needs about {_size(est.peak_bytes)}; {_size(available)} are available: "
             f"use {instead}")
    return est


class _progress_of:
    """Within the block, a solve estimated to take over SLOW_SOLVE_S seconds says so in one line on
    stderr, then prints solver.progress's reports (load steps, inverse updates) as lines with the
    time taken; a shorter one prints nothing."""

    def __init__(self, est, what: str):
        self._est, self._what = est, what

    def __enter__(self):
        import time
        from solver.progress import reporting

        est = self._est
        if est is None or est.seconds <= SLOW_SOLVE_S:
            self._block = None
            return self
        typer.echo(f"heartctl: {self._what}: the {est.preset} {'inverse ' if est.inverse else ''}solve of "
                   f"{est.nodes:,} nodes ({est.unknowns:,} unknowns) takes about {_duration(est.seconds)} and "
                   f"{_size(est.peak_bytes)} (a rough estimate); progress follows", err=True)
        start = time.monotonic()
        self._block = reporting(lambda text: typer.echo(f"heartctl: {time.monotonic() - start:.0f} s: {text}",
                                                        err=True))
        self._block.__enter__()
        return self

    def __exit__(self, *exc):
        if self._block is not None:
            self._block.__exit__(*exc)
        return False


def _mesh_progress(nodes: int):
    """Meshing a target above LARGE_MESH_NODES: gmsh's retries at another element size as lines on stderr."""
    import time
    from contextlib import nullcontext

    from solver.progress import reporting

    if nodes <= LARGE_MESH_NODES:
        return nullcontext()
    start = time.monotonic()
    return reporting(lambda text: typer.echo(f"heartctl: {time.monotonic() - start:.0f} s: {text}", err=True))


class _warnings_as_lines:
    """Within the block, heartctl's warnings for the user (solver.mesh.MeshUnitsWarning) print as
    one line each on stderr, `heartctl: warning: …`; other warnings pass on as usual."""

    def __enter__(self):
        import warnings

        from solver.mesh import MeshUnitsWarning

        self._category = MeshUnitsWarning
        self._catcher = warnings.catch_warnings(record=True)
        self._caught = self._catcher.__enter__()
        warnings.simplefilter("always", MeshUnitsWarning)
        return self

    def __exit__(self, *exc):
        import warnings

        self._catcher.__exit__(*exc)
        for w in self._caught:
            if issubclass(w.category, self._category):
                typer.echo(f"heartctl: warning: {w.message}", err=True)
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return False


PressureOpt = typer.Option(..., "--pressure", help="ED cavity pressure, mmHg (> 0).")
StiffnessOpt = typer.Option(..., "--stiffness", help="Guccione stiffness C, Pa (> 0).")
EndoOpt = typer.Option(60.0, "--endo", help="Endocardial helix angle, degrees (|θ| ≤ 90).")
EpiOpt = typer.Option(-60.0, "--epi", help="Epicardial helix angle, degrees (the paper's −60…−70).")
FidelityOpt = typer.Option(FidelityName.accurate, "--fidelity", help="Solver preset: fast (P1/P1) | accurate (P2/P1) | reference (accurate on the mesh refined once, answered at its nodes: near the converged solution, ~10–20× accurate's time).")
BaseOpt = typer.Option(Base.sliding, "--base", help="Base condition: sliding (z fixed), clamped, spring (sliding + epicardial normal spring), or heartfem (spring, rigid motions removed over the wall about the coordinate origin: the original paper's pipeline; mesh placement matters).")
FibresOpt = typer.Option("laplace", "--fibres", help="Fibre rule: laplace (ours) | heartfem (the original pipeline's distance rule).")
UnitsOpt = typer.Option(Units.mm, "--units", help="Length unit of the input mesh; the output uses it too.")
ThreadsOpt = typer.Option(None, "--threads", help="Threads for the sparse solver and BLAS (default: the "
                          "MKL/OMP_NUM_THREADS environment, else all cores).")
RotateDegOpt = typer.Option(0.0, "--rotate-deg", help="Augment: turn each training graph about the long axis by a "
                                                      "random angle in ±DEG (exact new FE pairs; 0 = off).")
ScalePctOpt = typer.Option(0.0, "--scale-pct", help="Augment: scale each training graph about its base by a random "
                                                    "factor in 1 ± PCT/100 (exact new FE pairs; 0 = off).")
# train --config and the options that change its network (trainer.config.compose)
NodeInputOpt = typer.Option(None, "--node-input", help="Node input: xyz (coordinates: the paper) | wall (+ wall "
                            "coordinates ζ, τ) | response (+ wall coordinates and the mesh's linear FE response). "
                            "Default: the --config's.")
EmaOpt = typer.Option(None, "--ema", help="Weight averaging: decay d of the weights' moving average, which is "
                      "validated and saved (e.g. 0.99; 0 = off). Default: the --config's.")
DropoutOpt = typer.Option(None, "--dropout", help="Dropout after every layer (0 = off; the paper's 0.1). "
                          "Default: the --config's.")
OutputScaleOpt = typer.Option(None, "--output-scale", help="global (one fitted scale: the paper) | load (also × the "
                              "case's expected displacement size from P, C and the helix angles). Default: the --config's.")
LayerOpt = typer.Option(None, "--layer", help="Mesh-encoder layer: gat (the paper) | gatv2 | gcn | sage. "
                        "Default: the --config's.")
SetOpt = typer.Option(None, "--set", metavar="KEY=VALUE", help="KEY=VALUE, repeatable, applied last: any network field "
                      "(trainer/config.py ModelConfig, e.g. hidden=64, cycle=false) or weight_decay, lr_patience, "
                      "lr_factor.")
PresetScalePctOpt = typer.Option(None, "--scale-pct", help="Augment: scale each training graph about its base by a "
                                 "random factor in 1 ± PCT/100 (exact new FE pairs; 0 = off). Default: the --config "
                                 "preset's (recommended: 8), else 0.")
PresetLrScheduleOpt = typer.Option(None, "--lr-schedule", help="plateau (halve the rate after 10 epochs without a "
                                   "better validation loss: the paper) | cosine (anneal towards 1 % of --lr over "
                                   "--epochs, set per epoch). Default: the --config preset's (recommended: cosine), "
                                   "else plateau.")
LrScheduleOpt = typer.Option("plateau", "--lr-schedule", help="plateau (halve the rate after 10 epochs without a better "
                                                              "validation loss: the paper) | cosine (anneal towards 1 % "
                                                              "of --lr over --epochs, set per epoch).")


@app.command()
def mesh(shape: int = typer.Option(..., "--shape", help="Shape id of the built-in shape model (≥ 0)."),
         out: Path = typer.Option(..., "-o", "--out", help="Output mesh file (.vtu or .vtk)."),
         nodes: int = typer.Option(800, "--nodes", help="Target node count, 50–200,000 (gmsh lands within ~15 % of it)."),
         seed: int = typer.Option(0, "--seed", help="Shape-model seed."),
         shape_model: int = typer.Option(2, "--shape-model", help="Shape model version: 2 (the default, healthy and "
                                         "diseased anatomy) or 1 (the ellipsoid family of stores made before it)."),
         endo: float = EndoOpt, epi: float = EpiOpt,
         units: Units = typer.Option(Units.mm, "--units", help="Length unit of the written mesh."),
         fidelity: FidelityName = typer.Option(FidelityName.accurate, "--fidelity", help="Whose fibre field the cell "
                                               "data `fibre`/`sheet` hold (fast: P1 φ; accurate, reference: P2 φ); "
                                               "`fibre_p1`/`fibre_p2` hold both.")):
    """Write the ED mesh of a shape-model member with surface tags and fibre fields; print its shape
    descriptors."""
    from solver.descriptors import format_descriptors, shape_descriptors
    from solver.fibres import centroid_frames, helix_angle_at_nodes, transmural_coordinate
    from solver.fidelity import get_fidelity
    from solver.meshing import check_node_target, mesh_lv
    from solver.shape_model import lv_shape

    try:
        _params(1.0, 1.0, endo, epi)
        _check_output(out)
        check_node_target(nodes)
        if seed < 0:
            raise ValueError(f"--seed must be ≥ 0, got {seed}")
        shape_def = lv_shape(shape, seed, shape_model)
        if nodes > LARGE_MESH_NODES:
            from solver.budget import estimate_mesh

            peak, seconds = estimate_mesh(nodes)
            typer.echo(f"heartctl: meshing {nodes:,} nodes takes about {_duration(seconds)} and "
                       f"{_size(peak)} (gmsh, one thread; a rough estimate)", err=True)
        with _mesh_progress(nodes):
            lv = mesh_lv(shape_def, nodes)
        phi = transmural_coordinate(lv)
        frames = {order: centroid_frames(lv, endo, epi, order) for order in (1, 2)}
        own = frames[get_fidelity(fidelity.value).displacement_order]
        cell_data = {"fibre": own[:, :, 0], "sheet": own[:, :, 1]}
        for order, f in frames.items():
            cell_data |= {f"fibre_p{order}": f[:, :, 0], f"sheet_p{order}": f[:, :, 1]}
        _write_mesh(out, lv, point_data={"transmural": phi, "helix_angle_deg": helix_angle_at_nodes(lv, endo, epi, phi)},
                   cell_data=cell_data, units=units.value)
    except _input_errors() as exc:
        fail(str(exc))
    info = lv.info
    typer.echo(f"shape {shape} (seed {seed}, shape model {shape_model}): {lv.n_nodes} nodes, {len(lv.tets)} tets, "
               f"EDV {shape_def.cavity_volume_ml():.1f} mL, wall {shape_def.wall_thickness_mm:.1f} mm, "
               f"min scaled Jacobian {info['min_scaled_jacobian']:.3f} → {out}")
    typer.echo(f"descriptors: {format_descriptors(shape_descriptors(lv))}")


@app.command()
def solve(mesh_path: Path = typer.Argument(..., metavar="MESH", help="Unloaded (stress-free) mesh."),
          pressure: float = PressureOpt, stiffness: float = StiffnessOpt, endo: float = EndoOpt, epi: float = EpiOpt,
          out: Path = typer.Option(..., "-o", "--out", help="Output: deformed mesh with `displacement`."),
          fidelity: FidelityName = FidelityOpt, base: Base = BaseOpt, units: Units = UnitsOpt,
          fibres: str = FibresOpt, threads: int = ThreadsOpt):
    """Forward inflation of an unloaded mesh to the ED pressure."""
    _solver_threads(threads)
    from solver.forward import SolveError
    from solver.lv import forward_solve

    try:
        params = _params(pressure, stiffness, endo, epi)
        _check_fibres(fibres)
        _check_output(out, mesh_path)
        lv = _read_mesh(mesh_path, units.value)
    except _input_errors() as exc:
        fail(str(exc))
    _warn_high_pressure(pressure)
    est = _solve_budget(mesh_path, lv, fidelity.value, inverse=False)
    try:
        with _progress_of(est, str(mesh_path)):
            result = forward_solve(lv, params, fidelity.value, base.value, fibres=fibres)
    except SolveError as exc:
        fail(f"forward solve did not converge: {exc}", code=1)
    _write_mesh(out, lv, result.loaded_nodes, point_data={"displacement": result.displacement},
               units=units.value, length_fields=("displacement",))
    disp = np.linalg.norm(result.displacement, axis=1)
    s = result.stats
    typer.echo(f"inflated to {params.label()} ({fidelity.value}, {base.value} base): "
               f"{s.load_steps} load steps, {s.newton_iterations} Newton iterations, {s.wall_s:.2f} s; "
               f"displacement mean {disp.mean():.3f} / max {disp.max():.3f} mm → {out}")


def _finite_or_none(value):
    """JSON has no NaN or Infinity: a non-finite number becomes null (nested dicts and lists too;
    NumPy / torch scalars and arrays as Python numbers and lists)."""
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        value = value.tolist()
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    return value


def json_line(value) -> str:
    """One line of strict JSON (non-finite numbers as null; other objects by their str)."""
    return json.dumps(_finite_or_none(value), default=str, allow_nan=False)


def _terminated(signum, frame):
    raise KeyboardInterrupt


def stop_on_sigterm() -> None:
    """SIGTERM (kill, Slurm, systemd) ends a long command as Ctrl-C does: one line, exit 130, done work
    kept; without this, Ray's own handler dumps a C++ stack. Main thread only (signal's rule)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminated)


def _given(ctx: typer.Context, name: str) -> bool:
    """Whether the user named option `name` on the command line (not left at its default). By the
    source's name: typer vendors its own click, whose ParameterSource is not click.core's."""
    source = ctx.get_parameter_source(name)
    return source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP")


def _print_auto_choice(choice: dict, tolerance_mm: float) -> None:
    """`--method auto`: the trade table's choice and the error it expects."""
    typer.echo(f"auto: {choice['label']} (p95 {choice['p95_mm']:.3f} mm, max {choice['max_mm']:.3f} mm against the "
               f"converged solution on the trade table's {choice['nodes']}-node held-out meshes, "
               f"{choice['time_mean_s']:.2f} s per case there; asked ≤ {tolerance_mm:g} mm)")


def _print_check(lv, unloaded, params, fidelity: str, base: str, fibres: str) -> None:
    """`--check`: the answer inflated again; its distance from the ED mesh estimates its error."""
    from solver.reinflate import reinflation_error

    chk = reinflation_error(lv, unloaded, params, fidelity, base, fibres)
    if not chk.ok:
        typer.echo(f"check: the answer could not be inflated again ({chk.failed}): do not trust it", err=True)
        return
    typer.echo(f"check: inflated again ({fidelity}, {chk.wall_s:.1f} s), the answer lands {chk.mean_mm:.3f} mm mean / "
               f"{chk.max_mm:.3f} mm max from the ED mesh: an estimate of its error against the {fidelity} model")


@app.command()
def unload(ctx: typer.Context, mesh_path: Path = typer.Argument(..., metavar="MESH", help="End-diastolic mesh."),
           pressure: float = PressureOpt, stiffness: float = StiffnessOpt, endo: float = EndoOpt, epi: float = EpiOpt,
           out: Path = typer.Option(..., "-o", "--out", help="Output: unloaded mesh with `displacement` (ED − unloaded)."),
           method: UnloadMethod = typer.Option(UnloadMethod.fe, "--method", help="fe: inverse finite elements; "
                                               "gnn: the trained network; hybrid: network guess refined by inverse FE; "
                                               "auto: the cheapest that met --tolerance-mm on the run's trade table."),
           fidelity: FidelityName = FidelityOpt, base: Base = BaseOpt, units: Units = UnitsOpt,
           tol_mm: float = typer.Option(None, "--tol-mm", help="Max nodal mismatch to stop at, mm (preset default 1e-4)."),
           run: list[Path] = typer.Option(None, "--run", help="Run directory of a trained network (--method gnn|hybrid|auto; "
                                                              "default: the network shipped with heartctl); "
                                                              "repeat it to average several (an ensemble; the output "
                                                              "gets their per-node spread)."),
           rotations: int = typer.Option(1, "--rotations", help="--method gnn|hybrid: average the network over K turns "
                                                                "about the long axis (K× the time; best with --rotate-deg 180 runs)."),
           fibres: str = FibresOpt,
           tolerance_mm: float = typer.Option(None, "--tolerance-mm", help="--method auto: the p95 nodal error against "
                                              "the converged solution you accept, mm (bench trade measured it)."),
           check: bool = typer.Option(False, "--check", help="--method gnn|hybrid|auto: inflate the answer again (one "
                                      "forward solve at --fidelity) and print how far it lands from the ED mesh."),
           threads: int = ThreadsOpt):
    """Unload a user's ED mesh: the stress-free geometry that inflates back onto it."""
    _solver_threads(threads)
    from trainer.unload import UnloadRequest

    try:
        params = _params(pressure, stiffness, endo, epi)
        _check_output(out, mesh_path)
        given = frozenset(n for n in ("fidelity", "tol_mm", "base", "fibres") if _given(ctx, n))
        request = UnloadRequest(method=method.value, fidelity=fidelity.value, base=base.value, fibres=fibres, tol_mm=tol_mm,
                                runs=tuple(run or ()), rotations=rotations, tolerance_mm=tolerance_mm, check=check,
                                given=given)
        lv = _read_mesh(mesh_path, units.value)
        plan, choice = request.plan(lv.n_nodes)
    except _input_errors() as exc:
        fail(str(exc))
    _warn_high_pressure(pressure)
    if choice is not None:
        _print_auto_choice(choice, tolerance_mm)
    est = None
    if plan.method in ("fe", "hybrid") or check:
        est = _solve_budget(mesh_path, lv, plan.fidelity, inverse=plan.method in ("fe", "hybrid"))
    with _progress_of(est if plan.method in ("fe", "hybrid") else None, str(mesh_path)):
        result = _unload_mesh(lv, params, plan)
    _write_unloaded(out, lv, result, units.value)
    _print_unloaded(result, lv, params, plan, out)
    if check and plan.method != "fe":
        _print_check(lv, result["unloaded_nodes"], params, plan.fidelity, plan.base, plan.fibres)


@app.command()
def verify(problem: Problem = typer.Option(Problem.all, "--problem", help="Land et al. 2015 problem."),
           fidelity: FidelityName = FidelityOpt,
           as_json: bool = typer.Option(False, "--json", help="One JSON object per problem on stdout."),
           threads: int = ThreadsOpt):
    """Run the Land et al. (2015) verification problems and compare with the published values."""
    _solver_threads(threads)
    from solver.benchmarks import land1, land2

    if fidelity is FidelityName.reference:
        fail("verify solves the Land et al. problems on their own meshes; choose --fidelity fast or accurate "
             "(bench convergence measures refinement)")
    names = ["land1", "land2"] if problem is Problem.all else [problem.value]
    for name in names:
        result = (land1 if name == "land1" else land2)(fidelity.value)
        if as_json:
            typer.echo(json_line(result))
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
    _solver_threads(threads)
    from solver.benchmark_solver import run_solver_benchmark

    presets = [f.value for f in fidelity] if fidelity else ["fast", "accurate"]
    try:
        rows = run_solver_benchmark(presets, nodes, shape)
    except _input_errors() as exc:
        fail(str(exc))
    if as_json:
        for row in rows:
            typer.echo(json_line(row))
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
    Console(width=200).print(table)


@bench_app.command("corners")
def bench_corners(fidelity: list[FidelityName] = typer.Option(None, "--fidelity", help="Presets, repeatable (default fast and accurate)."),
                  extended: bool = typer.Option(False, "--extended", help="The extended box too: P 2–30 mmHg, C 20–2,000 Pa, "
                                                "θendo 40–80°, θepi −40…−80°."),
                  nodes: int = typer.Option(None, "--nodes", help="Target mesh node count (default 800; with --extended 350)."),
                  base: Base = typer.Option(Base.sliding, "--base", help="Base condition: sliding (default) | clamped | spring | heartfem."),
                  fibres: str = typer.Option("laplace", "--fibres", help="Fibre rule: laplace (default) | heartfem."),
                  out: Path = typer.Option(None, "--out", help="Report folder: stability.md (the region table) and stability.json."),
                  as_json: bool = typer.Option(False, "--json")):
    """Pairs (inverse, then forward from zero load) at the 16 corners of the paper's box, and with
    --extended of a wider one, on the 3 extreme shapes: converged or why, cutbacks, Newton iterations,
    inverse updates, min det F, max Fung exponent Q (headroom before e^Q overflows), round trip, time."""
    from solver.stability import EXTENDED_BOX, PAPER_BOX, format_row, region_table, run_stability

    presets = [f.value for f in fidelity] if fidelity else ["fast", "accurate"]
    try:
        _check_fibres(fibres)
        if "reference" in presets:
            raise ValueError("--fidelity reference is not a stability target (it is accurate on a refined mesh)")
        nodes = nodes or (350 if extended else 800)
        echo = (lambda r: typer.echo(json_line(r))) if as_json else (lambda r: typer.echo(format_row(r)))
        rows = []
        for box in (PAPER_BOX, EXTENDED_BOX) if extended else (PAPER_BOX,):
            rows += run_stability(presets, box, nodes, base.value, fibres, progress=echo)
    except _input_errors() as exc:
        fail(str(exc))
    for box in sorted({r["box"] for r in rows}):
        for preset in presets:
            rs = [r for r in rows if r["box"] == box and r["preset"] == preset]
            ok = [r for r in rs if r["ok"]]
            bad = sum(1 for r in rs if "finite" in r and not r["finite"])
            typer.echo(f"{box} box, {preset}: {len(ok)}/{len(rs)} converged, worst round trip "
                       f"{max((r['roundtrip_mm'] for r in ok), default=float('nan')):.1e} mm, min J "
                       f"{min((r['min_jacobian'] for r in ok), default=float('nan')):.3f}, max Q "
                       f"{max((r['q_max'] for r in ok), default=float('nan')):.1f}, {bad} non-finite answers, "
                       f"{sum(r['wall_s'] for r in rs):.0f} s")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        header = (f"# heartctl bench corners\n\n{_machine_line(1)}; {base.value} base, {fibres} fibres, ~{nodes}-node "
                  f"meshes.\n\nCommand: `heartctl {' '.join(sys.argv[1:])}`\n\n")
        (out / "stability.md").write_text(header + region_table(rows))
        (out / "stability.json").write_text(json.dumps(rows, indent=1))
        typer.echo(f"report: {out / 'stability.md'}")


def _machine_line(threads: int) -> str:
    """Date, machine and solver threads, for a report's header."""
    import datetime
    import platform

    return (f"{datetime.date.today().isoformat()}, {platform.machine()} {os.cpu_count()}-core machine, "
            f"{threads} solver thread(s)")


@bench_app.command("convergence")
def bench_convergence(shapes: str = typer.Option("mean,minus2,plus2", "--shapes", help="Comma-separated: mean | minus2 | plus2 (every shape mode at 0, −2 or +2 SD)."),
                      cases: str = typer.Option("mid,hard", "--cases", help="Comma-separated: mid (8 mmHg, 150 Pa) | hard (14 mmHg, 50 Pa)."),
                      meshes: str = typer.Option("150:2,350:1,800:1", "--meshes", help="NODES:LEVELS,… : gmsh meshes of about NODES nodes, each refined uniformly LEVELS times (≥ 2 levels give observed orders)."),
                      base: Base = BaseOpt, fibres: str = FibresOpt,
                      out: Path = typer.Option(Path("reports/convergence"), "--out", help="Report folder: convergence.md, .png, .json, and solves/ (kept: a rerun resumes)."),
                      threads: int = typer.Option(1, "--threads", help="Threads for the sparse solver."),
                      quadrature: str = typer.Option("2,4,5,7", "--quadrature", help="Cell quadrature degrees (1–8) of the "
                                                     "quadrature study on levels 0 and 1 of every mesh; '' skips it.")):
    """Mesh convergence of unloading: fast and accurate on a coarse and a default mesh and their uniform
    refinements, each answer's nodal error against the finest accurate answer, observed orders and the
    finest answer's estimated own error (Richardson); and convergence in quadrature (each preset at
    several cell and facet degrees). Writes a Markdown table and a log-log PNG."""
    _solver_threads(threads)
    from solver.convergence import (ConvergenceSpec, parse_hierarchies, parse_quad_degrees, run_convergence,
                                    write_report)

    try:
        _check_fibres(fibres)
        spec = ConvergenceSpec(tuple(s.strip() for s in shapes.split(",") if s.strip()),
                               tuple(c.strip() for c in cases.split(",") if c.strip()), parse_hierarchies(meshes),
                               base=base.value, fibres=fibres,
                               quad_degrees=parse_quad_degrees(quadrature)).validate()
        result = run_convergence(spec, out / "solves", progress=typer.echo)
    except _input_errors() as exc:
        fail(str(exc))
    header = (f"# heartctl bench convergence\n\n{_machine_line(threads)}, solver sha256:{result['solver']}; "
              f"base {base.value}, {fibres} fibres.\n\nCommand: `heartctl {' '.join(sys.argv[1:])}`\n")
    paths = write_report(result, out, header)
    for o in result["orders"]:
        diffs = ", ".join(f"{d:.4f}" for d in o["level_diffs_mean_mm"])
        order = (f"order {o['order_mean']:.2f} (max-norm {o['order_max']:.2f})" if len(o["level_diffs_mean_mm"]) >= 2
                 else f"with the deepest mesh's order {o['order_used']:.2f}")
        typer.echo(f"{o['shape']:>6} {o['case']:>4} {o['hierarchy']:>9} {o['preset']:>8}: mean differences of levels "
                   f"{diffs} mm; {order}: finest level's error ≈ {o['finest_error_mean_mm']:.4f} mm mean")
    for r in result["quadrature"]:
        if not r["failed"]:
            typer.echo(f"{r['shape']:>6} {r['case']:>4} {r['hierarchy']:>9} {r['preset']:>8} q{r['quad_degree']} "
                       f"f{r['facet_quad_degree']} level {r['level']}: quadrature error "
                       f"{r['quadrature']['mean_mm']:.4f} mm mean, {r['wall_s']:.1f} s")
    typer.echo(f"report: {paths['markdown']}, {paths['plot']}")


@bench_app.command("trade")
def bench_trade(run: list[Path] = typer.Option(..., "--run", help="Run directory of a trained network; repeat it to add "
                                                                    "their ensemble as a method."),
                shapes: int = typer.Option(2, "--shapes", help="Held-out shapes (the shape model's ids after the run's last, or from --first-shape)."),
                cases: int = typer.Option(3, "--cases", help="Cases per mesh: the mid of the run's box, then its corners, hardest first (1–5)."),
                user_nodes: int = typer.Option(800, "--user-nodes", help="Second mesh size, as users bring (0: the training resolution only)."),
                out: Path = typer.Option(None, "--out", help="Report folder (default RUN/trade: where unload --method auto looks); "
                                                             "solves/ there keeps the reference solves, so a rerun resumes."),
                threads: int = typer.Option(1, "--threads", help="Threads for the sparse solver."),
                network_only: bool = typer.Option(False, "--network-only", help="Score the network (and the ensemble) "
                                                  "alone: no FE or hybrid methods."),
                first_shape: int = typer.Option(None, "--first-shape", help="First held-out shape id (default: the one "
                                                "after the run's last); the same for runs trained on different stores."),
                seed: int = typer.Option(None, "--seed", help="Shape-model seed of the held-out shapes (default: the "
                                         "run's store's); another seed's shapes are all unseen, from --first-shape 0.")):
    """The speed–accuracy trade: held-out ED meshes unloaded by FE (fast, accurate), the network, and the
    network's guess refined by 1, 2, 4 inverse updates or to tolerance, each against the converged
    solution (the reference preset). Writes trade.md, trade.png and trade.json (read by --method auto)."""
    _solver_threads(threads)
    from trainer.trade import TradeSpec, run_trade, write_report

    out = out or run[0] / "trade"
    try:
        spec = TradeSpec(tuple(str(r) for r in run), shapes, cases, user_nodes, network_only=network_only,
                         first_shape=first_shape, seed=seed).validate()
        result = run_trade(spec, out / "solves", progress=typer.echo)
    except _trainer_errors() as exc:
        fail(str(exc))
    header = (f"# heartctl bench trade\n\n{_machine_line(threads)}\n\n"
              f"Command: `heartctl {' '.join(sys.argv[1:])}`\n")
    paths = write_report(result, out, header)
    for srow in result["summary"]:
        err = (f"mean {srow['mean_mm']:.3f} / p95 {srow['p95_mm']:.3f} / max {srow['max_mm']:.3f} mm"
               if "mean_mm" in srow else "no answer")
        typer.echo(f"{srow['resolution']:>8} ({srow['nodes']:>4} nodes) {srow['method']:<22} {srow['ok']}/{srow['cases']} "
                   f"{err}, {srow['time_mean_s']:.2f} s per case")
    goal = result["hybrid_goal"]
    if goal.get("cases"):
        typer.echo(f"hybrid accurate to tolerance: {goal['time_ratio']:.2f} × the cold accurate time (goal ≤ 0.30), "
                   f"answers within {goal['max_distance_mm']:.1e} mm (goal ≤ 0.01)")
    track = result["check"]["gnn"]
    if track.get("answers"):
        typer.echo(f"--check on the network's answers: Spearman {track['spearman_max']:.2f} with the true max error "
                   f"(goal ≥ 0.8); true ≈ {track['true_over_estimate_median']:.2f} × the check")
    typer.echo(f"report: {paths['markdown']}, {paths['plot']}, {paths['json']}")


# --- the original paper's dataset ---


@app.command("import-l2u")
def import_l2u_cmd(folder: Path = typer.Argument(..., metavar="DIR", help="Folder with the Loaded2UnNet dataset (searched at any depth)."),
                   store: str = typer.Option(..., "--store", help="New Zarr store to write.")):
    """Import the original paper's public FE pairs (VTU, cm) as done cases of a new store (mm)."""
    from storage.l2u import import_l2u
    from storage.store import StoreError

    try:
        with _warnings_as_lines():
            report = import_l2u(folder, store)
    except (StoreError, ValueError, FileNotFoundError) as exc:
        fail(str(exc))
    typer.echo(f"{store}: imported {report.imported} pairs of {report.shapes} shapes "
               f"({report.found_files} files, {report.pairs} matched pairs, {report.n_skipped} skipped)")
    for name, reason in report.skipped_files():
        typer.echo(f"  skipped {name}: {reason}")


@bench_app.command("l2u")
def bench_l2u(store: str = typer.Option(..., "--store", help="A store written by import-l2u."),
              fidelity: FidelityName = FidelityOpt,
              base: Base = typer.Option(Base.heartfem, "--base", help="heartfem (default) follows their pipeline: base z fixed, epicardial spring, rigid motions removed by ∫u = 0 and ∫X×u = 0; spring: the same with our base gauge."),
              limit: int = typer.Option(None, "--limit", help="Check only the first N pairs (N ≥ 1; default all)."),
              stiffness_factor: float = typer.Option(2.0, "--stiffness-factor", help="Multiply their C: 2 (default) because heartFEM writes W = C (e^Q − 1), we W = C/2 (e^Q − 1); 1 takes C as named."),
              fibres: str = typer.Option("heartfem", "--fibres", help="Fibre rule: heartfem (theirs, default) | laplace (ours)."),
              quad_degree: int = typer.Option(4, "--quad-degree", help="Cell quadrature degree (heartFEM: 4; 0 = the preset's own)."),
              direction: Direction = typer.Option(Direction.forward, "--direction", help="forward: inflate their unloaded meshes, compare with their ED meshes; inverse: unload their ED meshes (inverse FE), compare with their unloaded meshes."),
              as_json: bool = typer.Option(False, "--json")):
    """Forward-solve their unloaded meshes with their parameters; mismatch to their ED meshes
    (--direction inverse: unload their ED meshes; mismatch to their unloaded meshes).
    The defaults follow their pipeline (heartFEM's base, their C convention and fibre rule, degree 4)."""
    from orchestrator.l2u_check import run_l2u_check
    from storage.store import StoreError

    try:
        result = run_l2u_check(store, fidelity.value, base.value, limit, stiffness_factor, fibres, quad_degree,
                               direction.value)
    except (StoreError, ValueError) as exc:
        fail(str(exc))
    _print_l2u_check(result, direction, as_json)


def _print_l2u_check(result: dict, direction: Direction, as_json: bool) -> None:
    """bench l2u's comparison: JSON without the rows, or a line per pair, per parameter value, overall."""
    if as_json:
        typer.echo(json_line({k: v for k, v in result.items() if k != "rows"}))
        return
    o = result["overall"]
    what = "ED meshes unloaded" if direction is Direction.inverse else "unloaded meshes inflated"
    typer.echo(f"{result['solved']}/{result['cases']} of their {what} ({result['fidelity']}, base {result['base']}, "
               f"C × {result['stiffness_factor']:g}, {result['fibres']} fibres, quadrature degree {result['quad_degree']})")
    for r in result["rows"]:
        if r["ok"]:
            typer.echo(f"  shape {r['shape']} case {r['case']}: P={r['pressure_mmhg']:g} C={r['stiffness_pa']:g} "
                       f"θ={r['helix_endo_deg']:g}/{r['helix_epi_deg']:g}: mismatch mean {r['mismatch_mean_mm']:.3f} / "
                       f"max {r['mismatch_max_mm']:.3f} mm; their loading {r['loading_mean_mm']:.2f} mm, ours "
                       f"{r['ours_loading_mean_mm']:.2f} mm → {100 * r['relative']:.1f} %, {100 * r['aligned_relative']:.1f} % "
                       f"after in-plane rigid alignment ({r['wall_s']:.1f} s)")
        else:
            typer.echo(f"  shape {r['shape']} case {r['case']}: FAILED {r['reason']}")
    for name, groups in result["by_parameter"].items():
        parts = ", ".join(f"{v:g}: {100 * g['relative']:.1f} % ({100 * g['aligned_relative']:.1f} % aligned)"
                          for v, g in groups.items())
        typer.echo(f"  by {name}: {parts}")
    if o["n"]:
        typer.echo(f"overall: mean mismatch {o['mismatch_mean_mm']:.3f} mm (max {o['mismatch_max_mm']:.3f} mm) = "
                   f"{100 * o['relative']:.1f} % of the mean loading displacement {o['loading_mean_mm']:.2f} mm "
                   f"(ours {o['ours_loading_mean_mm']:.2f} mm); after in-plane rigid alignment {o['aligned_mean_mm']:.3f} mm "
                   f"= {100 * o['aligned_relative']:.1f} %; goal ≤ 10 %")


# --- training and evaluation ---


def _trainer_errors():
    from storage.store import StoreError
    from trainer.config import TrainerError

    return (TrainerError, StoreError, ValueError, FileNotFoundError, NotADirectoryError)


def _unload_mesh(lv, params, plan) -> dict:
    """trainer.unload.unload_mesh: an inverse FE that fails exits 1, a network's refusal 2; the
    network's warnings as lines on stderr."""
    from solver.forward import SolveError
    from trainer.unload import unload_mesh

    try:
        result = unload_mesh(lv, params, plan)
    except SolveError as exc:
        fail(f"inverse solve did not converge: {exc}", code=1)
    except _trainer_errors() as exc:
        fail(str(exc))
    for w in result.get("warnings", ()):
        typer.echo(f"heartctl: warning: {w}", err=True)
    return result


def _write_unloaded(out: Path, lv, result: dict, units: str) -> None:
    """The unloaded mesh with point data `displacement` (ED − unloaded) and, for an ensemble of
    networks, `ensemble_spread` (a hybrid's answer is the FE's: no network spread to show)."""
    shift = lv.nodes - result["unloaded_nodes"]
    point_data, lengths = {"displacement": shift}, ["displacement"]
    if result["method"] == "gnn" and result["members"] > 1:
        point_data["ensemble_spread"] = result["spread_mm"]
        lengths.append("ensemble_spread")
    _write_mesh(out, lv, result["unloaded_nodes"], point_data=point_data, units=units, length_fields=tuple(lengths))


def _print_unloaded(result: dict, lv, params, plan, out: Path) -> None:
    """One line: how the mesh was unloaded (FE's updates and mismatch, the network's time, or the
    hybrid's both) and the ED − unloaded displacement."""
    d = np.linalg.norm(lv.nodes - result["unloaded_nodes"], axis=1)
    moved = f"ED − unloaded mean {d.mean():.3f} / max {d.max():.3f} mm → {out}"
    inv = result.get("inverse")
    if result["method"] == "fe":
        typer.echo(f"unloaded at {params.label()} ({plan.fidelity}, {plan.base} base): {inv.updates} updates, "
                   f"{inv.stats.newton_iterations} Newton iterations, {inv.stats.wall_s:.2f} s, "
                   f"mismatch {inv.mismatch_mm:.2e} mm; {moved}")
    elif result["method"] == "gnn":
        spread = (f"; the {result['members']} networks disagree by {result['spread_mm'].mean():.3f} mm mean / "
                  f"{result['spread_mm'].max():.3f} mm max (RMS about their mean, point data ensemble_spread)"
                  if result["members"] > 1 else "")
        typer.echo(f"unloaded at {params.label()} by the network {result['run']} in {result['network_ms']:.1f} ms "
                   f"(first call with graph building{' and the linear FE response' if result['with_response'] else ''} "
                   f"{result['first_call_ms']:.0f} ms); "
                   f"ED − unloaded mean {d.mean():.3f} / max {d.max():.3f} mm{spread} → {out}")
    else:
        dropped = ""
        if result["fallback"]:
            lost = result.get("guess_attempt_s")
            dropped = ", guess unusable" + (f" after {lost:.1f} s of inverse FE from it" if lost is not None else "")
        budget = f", at most {plan.max_updates} updates" if plan.max_updates is not None else ""
        typer.echo(f"unloaded at {params.label()} (hybrid: network {result['network_ms']:.1f} ms{dropped}"
                   f", then {plan.fidelity} inverse FE{budget}): {inv.updates} updates, "
                   f"{inv.stats.newton_iterations} Newton iterations, {inv.stats.wall_s:.2f} s, mismatch {inv.mismatch_mm:.2e} mm; "
                   f"network guess was {result['guess_error_mm']:.3f} mm (max) from the FE answer; {moved}")


@app.command()
def train(store: str = typer.Option(..., "--store", help="Zarr store of FE pairs (heartctl generate)."),
          run_dir: Path = typer.Option(..., "--run-dir", help="Run directory: checkpoint.pt, metrics.csv, Ray storage; "
                                                               "reusing it resumes the run."),
          gpus: int = typer.Option(0, "--gpus", help="GPU workers (DDP over NCCL); 0 = CPU workers with gloo."),
          config: str = typer.Option("paper", "--config", help=CONFIG_HELP),
          node_input: str = NodeInputOpt, ema: float = EmaOpt, dropout: float = DropoutOpt,
          output_scale: str = OutputScaleOpt, layer: str = LayerOpt, settings: list[str] = SetOpt,
          epochs: int = typer.Option(None, "--epochs", help="Max epochs (default 500; --local 5)."),
          batch_size: int = typer.Option(16, "--batch-size", help="Graphs per batch per worker."),
          sr: float = typer.Option(1.0, "--sr", help="Supervision ratio: fraction of training cases with labels (e.g. 0.03)."),
          labelled_share: float = typer.Option(0.25, "--labelled-share",
                                               help="SR < 1: share of each batch drawn from the labelled cases."),
          split: str = typer.Option("shape", "--split", help="shape (70/30 of shapes) | lovo:P=10 (C=, endo=, epi=) | source."),
          train_fraction: float = typer.Option(1.0, "--train-fraction",
                                               help="Train on this fraction of the training shapes (seeded; "
                                                    "validation and test unchanged)."),
          seed: int = typer.Option(0, "--seed", help="Seed of initialisation and shuffling, and of split and SR subset unless --split-seed is given."),
          split_seed: int = typer.Option(None, "--split-seed", help="Seed of split, SR subset and training-shape subset (default: --seed); "
                                         "runs with one split seed and several --seed values form a seed ensemble."),
          label_seed: int = typer.Option(None, "--label-seed", help="With --sr < 1: seed of the labelled subset only "
                                         "(default: the split seed); the same test cases, other labelled pairs."),
          rotate_deg: float = RotateDegOpt,
          scale_pct: float = PresetScalePctOpt,
          lr_schedule: str = PresetLrScheduleOpt,
          local: bool = typer.Option(False, "--local", help="Two CPU workers (Ray Train, gloo), a few epochs: minutes."),
          no_ray: bool = typer.Option(False, "--no-ray", help="Run the plain PyTorch loop in this process (no Ray)."),
          device: str = typer.Option(None, "--device", help="With --no-ray: cpu | cuda (default cuda when available)."),
          workers: int = typer.Option(2, "--workers", help="CPU workers when --gpus 0."),
          address: str = typer.Option(None, "--address", help="Join a Ray cluster: auto | HOST:PORT (default: a local Ray)."),
          connect_timeout: float = typer.Option(None, "--connect-timeout", help="With --address: seconds to wait for the cluster before giving up (default 30)."),
          max_failures: int = typer.Option(2, "--max-failures", help="Restarts from the last checkpoint after a worker dies."),
          lr: float = typer.Option(1e-3, "--lr", help="AdamW learning rate."),
          patience: int = typer.Option(50, "--patience", help="Early stopping: epochs without a better validation loss."),
          init_from: Path = typer.Option(None, "--init-from", help="Fine-tune: start from this run directory's (or "
                                         "checkpoint's) weights and normalisation, with a fresh optimiser and schedule; "
                                         "give the configuration it was trained with."),
          bf16: bool = typer.Option(False, "--bf16", help="bf16 autocast (GPU only)."),
          compile_model: bool = typer.Option(False, "--compile", help="torch.compile the training step (GPU; "
                                             "a few minutes to compile, then faster steps)."),
          as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON (the last line of stdout).")):
    """Train HeartUnloadNet (or an ablation / baseline) on a store; Ray Train DDP, or --no-ray."""
    from orchestrator.ray_session import RayAddress
    from trainer.launch import Placement, prepare_training

    try:
        where = RayAddress(address, connect_timeout)
        placement = Placement(gpus=gpus, workers=workers, local=local, no_ray=no_ray, device=device, address=address,
                              max_failures=max_failures)
        cfg = prepare_training(store, run_dir, placement, config,
                               dict(node_input=node_input, ema=ema, dropout=dropout, output_scale=output_scale,
                                    layer=layer, settings=settings or ()),
                               dict(scale_pct=scale_pct, lr_schedule=lr_schedule, split=split, sr=sr,
                                    train_fraction=train_fraction, labelled_share=labelled_share, seed=seed,
                                    split_seed=split_seed, label_seed=label_seed, rotate_deg=rotate_deg, epochs=epochs,
                                    batch_size=batch_size, lr=lr, patience=patience, bf16=bf16, compile=compile_model,
                                    init_from=None if init_from is None else str(init_from)))
    except _trainer_errors() as exc:
        fail(str(exc))
    if placement.in_process(cfg):
        summary = _train_in_process(cfg, run_dir.resolve(), placement)
    else:
        summary = _train_on_ray(cfg, run_dir.resolve(), placement, where)
    _print_training(summary, config, cfg.model.kind, run_dir, as_json)


def _train_in_process(cfg, run_dir: Path, placement) -> dict:
    """trainer.launch.train_in_process, its refusals and Ctrl-C (or SIGTERM) as one line."""
    from trainer.launch import train_in_process

    from trainer.checkpoint import DiskFullError

    stop_on_sigterm()
    try:
        return train_in_process(cfg, run_dir, placement, log=lambda line: typer.echo(line, err=True))
    except _trainer_errors() as exc:
        fail(str(exc))
    except DiskFullError as exc:  # a failure, not bad input: exit 1
        fail(str(exc), code=1)
    except KeyboardInterrupt:
        fail("interrupted; rerun the same command to resume from the last checkpoint", code=130)


def _train_on_ray(cfg, run_dir: Path, placement, where) -> dict:
    """Ray Train within a ray_session (a local Ray, or the cluster joined): refusals, Ray that will not
    start and Ctrl-C exit 2 (130) in one line, a training that fails exits 1."""
    from orchestrator.ray_session import RayConnectError, RayStartError, ray_session
    from trainer.checkpoint import DiskFullError
    from trainer.ray_local import local_ray_options
    from trainer.ray_train import check_ray_resources, train_with_ray

    gpus, workers = placement.gpus, placement.workers
    try:
        with ray_session(where, **local_ray_options(workers if placement.local else None)):
            check_ray_resources(gpus, workers, where.address)
            stop_on_sigterm()  # after ray.init, whose driver installs its own handler
            summary = train_with_ray(cfg, run_dir, gpus=gpus, cpu_workers=workers, max_failures=placement.max_failures)
    except (RayConnectError, RayStartError) as exc:
        fail(str(exc))
    except _trainer_errors() as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        fail("interrupted; rerun the same command to resume from the last checkpoint", code=130)
    except DiskFullError as exc:
        fail(str(exc), code=1)
    except Exception as exc:  # Ray's TrainingFailedError and the like: not bad input
        text = str(exc).strip()
        fail(f"training failed: {text.splitlines()[0] if text else type(exc).__name__}", code=1)
    summary["mode"] = f"Ray Train, {summary['workers']} {'GPU' if gpus else 'CPU'} worker(s), {summary['backend']}"
    return summary


def _print_training(summary: dict, config: str, kind: str, run_dir: Path, as_json: bool) -> None:
    """The run's summary: strict JSON, or one line (epochs, best validation MD, parameters, where)."""
    if as_json:
        typer.echo(json_line(summary))
        return
    best = summary.get("best_val_md_mm")
    if kind == "pca":
        typer.echo(f"{config}: fitted; "
                   + (f"validation MD {best:.3f} mm" if best is not None else "no validation cases")
                   + f"; {summary.get('n_parameters') or 0:,} parameters → {run_dir / 'checkpoint.pt'}")
        return
    typer.echo(f"{config}: {summary['epoch']} epochs ({summary['mode']}); "
               + (f"best validation MD {best:.3f} mm at epoch {summary['best_epoch']}" if best is not None
                  else f"no validation cases, kept epoch {summary['best_epoch']} (lowest training loss)")
               + (", stopped early" if summary.get("stopped_early") else "")
               + f"; {summary.get('n_parameters') or 0:,} parameters → {run_dir / 'checkpoint.pt'}")


@app.command()
def evaluate(run: list[Path] = typer.Option(..., "--run", help="Run directory (heartctl train --run-dir); repeat "
                                                            "it to average several runs' networks (an ensemble: same "
                                                            "store and split, K× the inference time)."),
             store: str = typer.Option(..., "--store", help="The store the run was trained on."),
             split: str = typer.Option("test", "--split", help="test | val | train (the run's split) | all (every done case of --store, which may be a store the run never saw)."),
             device: str = typer.Option("cpu", "--device", help="cpu | cuda."),
             out: Path = typer.Option(None, "--out", help="Output folder (default RUN/eval_SPLIT)."),
             plots: bool = typer.Option(True, "--plots/--no-plots", help="PNG plots (needs matplotlib)."),
             rotations: int = typer.Option(1, "--rotations", help="Average the network over K turns about the long "
                                                                  "axis (K× the time; best with runs trained with --rotate-deg 180)."),
             reference: str = typer.Option(None, "--reference", help="A store of the same ED meshes at converged fidelity (heartctl generate --fidelity reference, same --seed and --nodes): the cases it has are scored against it too, the network's answers and the store's own labels."),
             as_json: bool = typer.Option(False, "--json", help='One JSON object: {"dsc_1mm": …, "hd_mm": …, "cases": N}.')):
    """Metrics of a trained run on its store: DSC@1 mm / 0.1 mm, HD, MD, SD (mm, mean ± SD), time per case;
    against the store's own labels and, with --reference, against the converged solution."""
    from trainer.evaluate import evaluate_run

    try:
        report = evaluate_run(run[0], store, split, device, out, plots, rotations=rotations, members=run[1:],
                              reference=reference)
    except _trainer_errors() as exc:
        fail(str(exc))
    _print_evaluation(report, split, store, as_json)


def _print_evaluation(report: dict, split: str, store: str, as_json: bool) -> None:
    """An evaluation: one strict JSON object, or the metrics table (against the labels, and the
    converged solution when there is a reference), the configuration, timings and files written."""
    if as_json:
        typer.echo(json_line({**report["summary"], "nn_md_mm": report["nn_md_mm"],
                               "ms_per_case_batched": report["ms_per_case_batched"],
                               "response_ms_per_mesh": report["response_ms_per_mesh"], "split": split,
                               "config": report["config"], "configuration": report["configuration"],
                               "rotations": report["rotations"],
                               "members": report["members"], "labels_fidelity": report["labels_fidelity"],
                               "unfinished_runs": report["unfinished_runs"],
                               **({"reference": report["reference"]} if "reference" in report else {})}))
        return
    from rich.console import Console
    from rich.table import Table

    for u in report["unfinished_runs"]:
        typer.echo(f"warning: run {u['run']} is unfinished: it stopped at epoch {u['epoch']} of {u['epochs']} (killed, "
                   f"or still training); `heartctl train` with the same --run-dir finishes it", err=True)
    agg = report["aggregate"]
    ref = report.get("reference")
    table = Table(title=f"{report['config']} on {report['summary']['cases']} {split} cases of {store}")
    table.add_column("metric")
    table.add_column(f"vs its labels ({report['labels_fidelity']}), mean ± SD", justify="right")
    table.add_column("cm", justify="right")
    if ref:
        table.add_column(f"vs converged ({ref['fidelity']}, {ref['cases']} cases)", justify="right")
        table.add_column(f"labels vs converged", justify="right")
    for key, name, cm in (("dsc_1mm", "DSC @ 1 mm", False), ("dsc_01mm", "DSC @ 0.1 mm", False),
                          ("hd_mm", "HD (mm)", True), ("md_mm", "MD (mm)", True), ("sd_mm", "SD (mm)", True),
                          ("nn_md_mm", "MD, nearest node (mm)", True), ("max_mm", "max node error (mm)", True)):
        m, s = agg[key]
        cells = [name, f"{m:.4f} ± {s:.4f}", f"{m / 10:.4f}" if cm else ""]
        if ref:
            cells += [f"{ref[who][key][0]:.4f} ± {ref[who][key][1]:.4f}" if key in ref[who] else ""
                      for who in ("network", "labels")]
        table.add_row(*cells)
    con = Console(width=200)
    con.print(table)
    configurations = report["configuration"]
    for i, line in enumerate(configurations):
        con.print(f"configuration{f' of member {i + 1}' if len(configurations) > 1 else ''}: {line}", markup=False)
    con.print(f"inference: {report['summary']['ms_per_case']:.2f} ms per case at batch 1, "
              f"{report['ms_per_case_batched']:.3f} ms per case at batch {report['batch_size']} ({report['device']})"
              + (f", each the mean of {report['rotations']} turns about the long axis" if report["rotations"] > 1 else ""))
    if report["response_ms_per_mesh"] is not None:
        con.print(f"  + the linear FE response (node input): {report['response_ms_per_mesh']:.0f} ms per mesh on the CPU, "
                  f"once for all the parameter sets a mesh is unloaded at")
    worst = max(report["by_parameter"], key=lambda r: r["md_mm_mean"])
    con.print(f"per parameter value: worst MD {worst['md_mm_mean']:.3f} mm at {worst['parameter']} = {worst['value']:g} "
              f"({worst['cases']} cases); see by_parameter.csv")
    con.print(f"wrote {', '.join(report['files'])} to {report['out_dir']}")


@bench_app.command("model")
def bench_model_cmd(device: str = typer.Option("cpu", "--device", help="cpu | cuda."),
                    nodes: int = typer.Option(650, "--nodes", help="Target mesh node count."),
                    config: str = typer.Option("paper", "--config", help="Model configuration (a gnn one)."),
                    batches: str = typer.Option("1,32,128", "--batches", help="Inference batch sizes."),
                    train_batch: int = typer.Option(None, "--train-batch", help="Training batch (default 32 CPU, 128 GPU)."),
                    bf16: bool = typer.Option(False, "--bf16", help="bf16 autocast (GPU only)."),
                    threads: int = typer.Option(None, "--threads", help="torch CPU threads (default: torch's)."),
                    gat_kernel: str = typer.Option("sparse", "--gat-kernel",
                                                   help="sparse (one SpMM per GAT layer) | pyg (GATConv)."),
                    mesh: Path = typer.Option(None, "--mesh", help="Time on this LV mesh instead of meshing one with gmsh."),
                    units: Units = typer.Option(Units.mm, "--units", help="Length unit of the --mesh file."),
                    compile_model: bool = typer.Option(False, "--compile", help="torch.compile the model (dynamic shapes)."),
                    profile: bool = typer.Option(False, "--profile", help="Also print torch.profiler's top operators "
                                                 "of a training step and of the largest inference batch."),
                    min_seconds: float = typer.Option(1.0, "--min-seconds", help="Time each figure over at least this long."),
                    as_json: bool = typer.Option(False, "--json")):
    """Inference ms per case at batch 1, 32, 128 and training graphs/s (plain PyTorch, no Ray)."""
    from trainer.bench import ModelBench

    try:
        with _warnings_as_lines():
            r = ModelBench(device=device, nodes=nodes, config=config, batches=batches, train_batch=train_batch, bf16=bf16,
                           threads=threads, gat_kernel=gat_kernel, mesh=mesh, mesh_units=units.value,
                           compile_model=compile_model, profile=profile, min_seconds=min_seconds).run()
    except _trainer_errors() as exc:
        fail(str(exc))
    _print_model_bench(r, as_json)


def _print_model_bench(r: dict, as_json: bool) -> None:
    """bench model's figures: strict JSON, or lines for the model, each inference batch, the prepared
    single case, the linear FE response, training steps, batch building and any profiles."""
    if as_json:
        typer.echo(json_line(r))
        return
    typer.echo(f"{r['config']} model, {r['parameters']:,} parameters; mesh {r['nodes']} nodes, {r['edges']} directed edges; "
               f"{r['device_name']} ({r['threads']} threads){', bf16' if r['bf16'] else ', fp32'}, "
               f"{'torch.compile (%.0f s to compile)' % r['compile_s'] if r['compiled'] else 'eager PyTorch'}, "
               f"{r['gat_kernel']} GAT kernel")
    for row in r["inference"]:
        table = (f"; {row['table_ms_per_case']:.3f} ms with the batch built from a graph table (attention graph "
                 f"assembled from the mesh's)") if "table_ms_per_case" in row else ""
        typer.echo(f"inference batch {row['batch']:>4}: {row['ms_per_case']:8.3f} ms per case ({row['ms_per_batch']:.1f} "
                   f"ms per batch){table}")
    pr = r["prepared_single"]
    how = "CUDA graph replay" if pr["cuda_graph"] else ("eager; capture failed: " + pr["capture_error"]
                                                       if pr["capture_error"] else "eager")
    typer.echo(f"inference batch    1, mesh prepared once ({how}): {pr['ms_per_case']:8.3f} ms per case")
    if r["response_ms_per_mesh"] is not None:
        typer.echo(f"linear FE response (node input of {r['config']}; CPU, once per mesh, shared by every case "
                   f"of it): {r['response_ms_per_mesh']:.1f} ms")
    typer.echo(f"training batch {r['train_batch']} (with cycle: {r['cycle']}): {r['train_step_ms']:.0f} ms per step, "
               f"{r['train_graphs_per_s']:.1f} graphs/s")
    bb = r["batch_building"]
    typer.echo(f"building a batch of {r['train_batch']}: {bb['table_ms']:.2f} ms from the training loop's graph table "
               f"(on {bb['table_device']}), {bb['pyg_ms']:.2f} ms by PyG's collation and copy; a step with its batch "
               f"built, steps back to back as in the training loop: {bb['loop_step_ms']:.0f} ms, "
               f"{r['loop_graphs_per_s']:.1f} graphs/s")
    for key, what in (("profile_train", "three training steps"), ("profile_inference", "three inferences of the largest batch")):
        if key in r:
            typer.echo(f"torch.profiler, {what}:\n{r[key]}")


@bench_app.command("ablation")
def bench_ablation_cmd(store: str = typer.Option(..., "--store", help="Zarr store of FE pairs."),
                       root: Path = typer.Option(..., "--root", help="Folder for one run directory per configuration."),
                       configs: str = typer.Option("paper,A1,A4,pca", "--configs", help="Comma-separated configurations."),
                       epochs: int = typer.Option(40, "--epochs", help="Max epochs per configuration."),
                       batch_size: int = typer.Option(8, "--batch-size", help="Graphs per batch."),
                       sr: float = typer.Option(1.0, "--sr", help="Supervision ratio for every configuration."),
                       split: str = typer.Option("shape", "--split", help="shape | lovo:P=10 | source."),
                       seed: int = typer.Option(0, "--seed", help="Seed of split, SR subset and training."),
                       seeds: str = typer.Option("", "--seeds", help="Comma-separated seeds (replaces --seed): the "
                                                 "ablation once per seed under ROOT/seed<N>, then mean ± SD and "
                                                 "seed-paired comparisons."),
                       device: str = typer.Option("cpu", "--device", help="cpu | cuda."),
                       rotate_deg: float = RotateDegOpt,
                       scale_pct: float = ScalePctOpt,
                       lr_schedule: str = LrScheduleOpt,
                       as_json: bool = typer.Option(False, "--json", help="Print the table as JSON.")):
    """Train each configuration on the same split (plain PyTorch, in turn) and tabulate test metrics."""
    from trainer.ablation import ablation_study

    try:
        result = ablation_study(store, root, configs, seeds, device, lambda line: typer.echo(line, err=True),
                                split=split, sr=sr, seed=seed, epochs=epochs, batch_size=batch_size,
                                rotate_deg=rotate_deg, scale_pct=scale_pct, lr_schedule=lr_schedule)
    except _trainer_errors() as exc:
        fail(str(exc))
    if as_json:
        typer.echo(json_line(result))
    elif "seeds" in result:
        _print_ablation_seeds(result, root)
    else:
        _print_ablation(result, store, root, split, sr, epochs, seed)


def _print_ablation(result: dict, store: str, root: Path, split: str, sr: float, epochs: int, seed: int) -> None:
    """The ablation table (the best value per metric in bold), then the comparisons that matter."""
    from rich.console import Console
    from rich.table import Table

    from trainer.ablation import KEY_COMPARISONS, TABLE_METRICS, beats

    rows = result["rows"]
    table = Table(title=f"test split of {store} (split {split}, SR {sr:g}, ≤ {epochs} epochs, seed {seed}; "
                        f"{rows[0]['cases']} cases)")
    for col in ("config", *[label for _, label, _ in TABLE_METRICS], "ms/case", "epochs"):
        table.add_column(col, justify="left" if col == "config" else "right")
    for r in rows:
        cells = [f"[bold]{r[k]:.3f}[/bold]" if result["best"][k] == r["config"] else f"{r[k]:.3f}"
                 for k, _, _ in TABLE_METRICS]
        table.add_row(r["config"], *cells, f"{r['ms_per_case']:.1f}", f"{r['best_epoch']}/{r['epochs']}")
    con = Console(width=160)
    con.print(table)
    for name, rivals in KEY_COMPARISONS:
        won = beats(rows, name, list(rivals))
        present = [o for o in rivals if o in {r["config"] for r in rows}]
        if won and present:
            wins = [label for k, label, _ in TABLE_METRICS if won[k]]
            con.print(f"{name} vs {', '.join(present)}: better on {len(wins)}/{len(TABLE_METRICS)} metrics"
                      + (f" ({', '.join(wins)})" if wins else ""))
    con.print(f"wrote ablation.csv and ablation.json to {root}")


def _print_ablation_seeds(result: dict, root: Path) -> None:
    """Mean ± SD per configuration over the seeds, then the seed-paired comparisons that matter."""
    from rich.console import Console
    from rich.table import Table

    from trainer.ablation import KEY_COMPARISONS, TABLE_METRICS

    seeds = ", ".join(str(s) for s in result["seeds"])
    table = Table(title=f"test split of {result['store']} (split {result['split']}, SR {result['sr']:g}, "
                        f"≤ {result['epochs']} epochs; seeds {seeds}): mean ± SD over seeds")
    for col in ("config", *[label for _, label, _ in TABLE_METRICS]):
        table.add_column(col, justify="left" if col == "config" else "right")
    for name, stats in result["configs"].items():
        table.add_row(name, *[f"{stats[k]['mean']:.3f} ± {stats[k]['sd']:.3f}" for k, _, _ in TABLE_METRICS])
    con = Console(width=160)
    con.print(table)
    n = len(result["seeds"])
    for name, rival in ((name, rival) for name, rivals in KEY_COMPARISONS for rival in rivals):
        pair = result["pairs"].get(f"{name} vs {rival}")
        if pair is None:
            continue
        md = pair["md_mm"]
        wins = sum(pair[k]["better_seeds"] == n for k, _, _ in TABLE_METRICS)
        con.print(f"{name} vs {rival}: MD better on {md['better_seeds']}/{n} seeds, paired difference "
                  f"{md['mean_diff']:+.3f} ± {md['sd_diff']:.3f} mm; better on every seed for {wins}/"
                  f"{len(TABLE_METRICS)} metrics")
    con.print(f"wrote ablation_seeds.json to {root} (per-seed tables under {root}/seed<N>/)")


@bench_app.command("learning-curve")
def bench_learning_curve_cmd(store: str = typer.Option(..., "--store", help="Zarr store of FE pairs."),
                             root: Path = typer.Option(..., "--root", help="Folder for one run directory per fraction."),
                             config: str = typer.Option("paper", "--config", help=CONFIG_HELP),
                             fractions: str = typer.Option("0.25,0.5,1", "--fractions",
                                                           help="Comma-separated fractions of the training shapes."),
                             epochs: int = typer.Option(30, "--epochs", help="Max epochs per fraction."),
                             batch_size: int = typer.Option(8, "--batch-size", help="Graphs per batch."),
                             sr: float = typer.Option(1.0, "--sr", help="Supervision ratio."),
                             split: str = typer.Option("shape", "--split", help="shape | lovo:P=10 | source."),
                             seed: int = typer.Option(0, "--seed", help="Seed of split, subsets and training."),
                             target_md: float = typer.Option(0.15, "--target-md", help="MD target, mm."),
                             target_hd: float = typer.Option(0.6, "--target-hd", help="HD target, mm."),
                             target_dsc: float = typer.Option(0.99, "--target-dsc", help="DSC@1mm target."),
                             device: str = typer.Option("cpu", "--device", help="cpu | cuda."),
                             rotate_deg: float = RotateDegOpt,
                             scale_pct: float = PresetScalePctOpt,
                             lr_schedule: str = PresetLrScheduleOpt,
                             as_json: bool = typer.Option(False, "--json", help="Print the result as JSON.")):
    """Train one configuration on growing fractions of the training shapes, evaluate each on the same
    test shapes, fit error ∝ pairs^(−b) and extrapolate the pairs a target would take."""
    from trainer.ablation import check_study
    from trainer.config import TrainConfig, TrainerError, compose
    from trainer.learning_curve import parse_fractions, run_learning_curve

    try:
        values = parse_fractions(fractions)
        model, training = compose(config)  # a preset brings its training options
        training.update({k: v for k, v in (("scale_pct", scale_pct), ("lr_schedule", lr_schedule)) if v is not None})
        if not (target_md > 0 and target_hd > 0 and 0 < target_dsc < 1):
            raise TrainerError("--target-md and --target-hd must be > 0 mm and --target-dsc in (0, 1)")
        check_study(store, root, split, device)
        base = TrainConfig(store=store, config_name=config, model=model, split=split, sr=sr, seed=seed, epochs=epochs,
                           batch_size=batch_size, rotate_deg=rotate_deg, **training)
        targets = {"md_mm": target_md, "hd_mm": target_hd, "dsc_1mm": target_dsc}
        result = run_learning_curve(base, values, root, targets, device, lambda line: typer.echo(line, err=True))
    except _trainer_errors() as exc:
        fail(str(exc))
    if as_json:
        typer.echo(json_line(result))
        return
    _print_learning_curve(result, root)


def _print_learning_curve(result: dict, root: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"{result['config']} on {result['store']}: test split ({result['test_cases']} cases), "
                        f"split {result['split']}, SR {result['sr']:g}, ≤ {result['epochs']} epochs, seed {result['seed']}")
    for col in ("fraction", "train pairs", "MD mm", "HD mm", "SD mm", "DSC@1mm", "epochs"):
        table.add_column(col, justify="right")
    for r in result["rows"]:
        table.add_row(f"{r['fraction']:g}", str(r["train_cases"]), f"{r['md_mm']:.3f}", f"{r['hd_mm']:.3f}",
                      f"{r['sd_mm']:.3f}", f"{r['dsc_1mm']:.3f}", f"{r['best_epoch']}/{r['epochs']}")
    con = Console(width=160)
    con.print(table)
    labels = {"md_mm": ("MD", "mm"), "hd_mm": ("HD", "mm"), "dsc_1mm": ("1 − DSC@1mm", "")}
    for key, law in result["laws"].items():
        name, unit = labels[key]
        target = result["targets"][key]
        goal = f"DSC@1mm {target:g}" if key == "dsc_1mm" else f"{name} {target:g} {unit}"
        need = result["pairs_needed"].get(key)
        reach = (f"~{need:,.0f} training pairs for {goal}" if need is not None
                 else f"{goal} is not reached: the error does not fall with more data")
        con.print(f"{name} ≈ {law['a']:.3g} · pairs^(−{law['b']:.2f}) (R² {law['r2']:.2f}): {reach}")
    con.print("(an extrapolation from these points at this epoch budget, an order of magnitude at best)")
    con.print(f"wrote learning_curve.csv and learning_curve.json to {root}")


# --- end of training and evaluation ---


# --- data generation ---


def _store_errors():
    from storage.store import StoreError

    return (StoreError, ValueError, FileNotFoundError, NotADirectoryError)


@app.command()
def generate(shapes: int = typer.Option(None, "--shapes", help="Number of shapes (default 60, the paper's; or the store's). More than an existing store's grows it by the shape model's next shapes, its done cases kept; fewer is refused."),
             store: str = typer.Option(..., "--store", help="Zarr store: a path or an fsspec URL (s3://…)."),
             pressures: str = typer.Option(None, "--pressures", help="ED pressures, mmHg, comma-separated (default 4,6,…,14)."),
             stiffness: str = typer.Option(None, "--stiffness", help="Stiffness C, Pa, comma-separated (default 50,100,…,300)."),
             endo: str = typer.Option(None, "--endo", help="Endocardial helix angles, degrees (default 60,65,70)."),
             epi: str = typer.Option(None, "--epi", help="Epicardial helix angles, degrees (default −60,−65,−70; write --epi=-60,-65)."),
             fidelity: str = typer.Option(None, "--fidelity", help="Solver preset: fast | accurate (default) | reference (accurate on each mesh refined once: pairs near the converged solution, for evaluate --reference)."),
             base: str = typer.Option(None, "--base", help="Base condition: sliding (default) | clamped | spring | heartfem."),
             fibres: str = typer.Option(None, "--fibres", help="Fibre rule: laplace (default) | heartfem (the original pipeline's)."),
             seed: int = typer.Option(None, "--seed", help="Shape-model seed (default 0)."),
             nodes: int = typer.Option(None, "--nodes", help="Target mesh node count (default 800; --local 350)."),
             meshes: str = typer.Option(None, "--meshes", help="Use your ED meshes as the shape set: a folder or a glob of mesh files (any meshio format; readable by every worker)."),
             units: Units = typer.Option(None, "--units", help="Length unit of the --meshes files (default mm)."),
             address: str = typer.Option(None, "--address", help="Join a Ray cluster: auto | HOST:PORT (default: start a local Ray on all cores)."),
             connect_timeout: float = typer.Option(None, "--connect-timeout", help="With --address: seconds to wait for the cluster before giving up (default 30)."),
             num_cpus: int = typer.Option(None, "--num-cpus", help="CPUs of the local Ray (default: all cores; --local 2)."),
             local: bool = typer.Option(False, "--local", help="Two-core test mode: 3 shapes × 2 P × 2 C, coarse meshes, fast preset."),
             dry_run: bool = typer.Option(False, "--dry-run", help="Print the plan (cases, core-hours from a calibration solve) and exit."),
             retry_failed: bool = typer.Option(False, "--retry-failed", help="Also rerun cases recorded as failed."),
             retry_damaged: bool = typer.Option(False, "--retry-damaged", help="First read every done case back; recompute the damaged ones (data missing, short, unreadable or not finite; status codes out of range; a shape whose arrays are not as the schema says is meshed again)."),
             max_in_flight: int = typer.Option(None, "--max-in-flight", help="Tasks in flight (default 2 × the cluster's CPUs, re-read as nodes join); a task is one pressure chain."),
             warm_start: bool = typer.Option(True, "--warm-start/--no-warm-start", help="Start each inverse from the unloaded geometry of its chain's lower pressures (default) or from the ED mesh."),
             as_json: bool = typer.Option(False, "--json", help="Print the plan / final report as JSON.")):
    """Generate FE pairs (inverse + forward) over shapes × P × C × θendo × θepi into a Zarr store, on Ray.
    Rerunning on the same store resumes it; a larger --shapes grows it."""
    from orchestrator.ray_session import RayAddress
    from orchestrator.sweep_request import SweepRequest, resolve_sweep
    from solver.mesh import MeshError

    try:
        request = SweepRequest(store=store, shapes=shapes, pressures=pressures, stiffness=stiffness, endo=endo, epi=epi,
                               fidelity=fidelity, base=base, fibres=fibres, seed=seed, nodes=nodes, meshes=meshes,
                               mesh_units=None if units is None else units.value, local=local, address=address,
                               num_cpus=num_cpus, max_in_flight=max_in_flight, retry_failed=retry_failed,
                               retry_damaged=retry_damaged, dry_run=dry_run)
        where = RayAddress(address, connect_timeout)
        with _warnings_as_lines():
            sweep = resolve_sweep(request)
    except (*_store_errors(), MeshError) as exc:
        fail(str(exc))
    _warn_high_pressures(sweep.high_pressures())
    if not dry_run and address is None:
        _sweep_budget(sweep)
    if dry_run:
        _print_plan(sweep.plan(warm_start), as_json)
    elif sweep.nothing_to_run(retry_damaged):
        _print_nothing_to_run(sweep, as_json)
    else:
        report = _run_sweep(sweep, where, warm_start, retry_damaged, progress=not as_json)
        _print_sweep_report(report, store, retry_damaged, as_json)


def _sweep_budget(sweep) -> None:
    """A local sweep whose workers' solves (solver.budget's estimate of one pair of a ~--nodes mesh at the
    sweep's preset, times the workers) need more memory than this machine has available: refused in one
    line (exit 2), naming how many workers would fit. User meshes (--meshes) are not estimated."""
    from solver.budget import estimate_for_nodes

    spec = sweep.spec
    if spec.meshes:
        return
    est = estimate_for_nodes(spec.fidelity, spec.nodes, inverse=True)
    workers = sweep.request.local_cpus or os.cpu_count() or 1
    available = _available_memory()
    if est.peak_bytes * workers > available:
        fit = int(available // est.peak_bytes)
        instead = f"--num-cpus {fit}" if fit >= 1 else "a coarser --nodes or a cheaper --fidelity"
        fail(f"{workers} workers solving {spec.fidelity} pairs of ~{spec.nodes:,}-node meshes need about "
             f"{_size(est.peak_bytes)} each, {_size(est.peak_bytes * workers)} in all; {_size(available)} are "
             f"available: use {instead}")


def _warn_high_pressures(high: list[float], flag: str = "--pressures") -> None:
    """One warning line for pressures above end-diastolic ones (allowed: the solver decides)."""
    from solver.parameters import HIGHEST_ED_PRESSURE_MMHG

    if high:
        typer.echo(f"warning: {flag} {', '.join(f'{p:g}' for p in high)} mmHg: end-diastolic pressures are "
                   f"0–{HIGHEST_ED_PRESSURE_MMHG:g} mmHg; such cases may take long and fail", err=True)


def _warn_high_pressure(pressure: float) -> None:
    """_warn_high_pressures for the one --pressure of solve and unload."""
    from solver.parameters import HIGHEST_ED_PRESSURE_MMHG

    _warn_high_pressures([pressure] if pressure > HIGHEST_ED_PRESSURE_MMHG else [], "--pressure")


def _run_sweep(sweep, where, warm_start: bool, retry_damaged: bool, progress: bool):
    """orchestrator.sweep.run_sweep within a ray_session: Ray that will not start and store errors
    exit 2, a full disk or a lost object store exits 1, Ctrl-C (or SIGTERM) 130, each in one line;
    done cases are kept."""
    from orchestrator.ray_session import RayConnectError, RayStartError, ray_session, sweep_ray_options
    from orchestrator.sweep import StoreFullError, StoreLostError, run_sweep

    req = sweep.request
    try:
        with ray_session(where, **sweep_ray_options(req.num_cpus, req.local)):
            stop_on_sigterm()  # after ray.init, whose driver installs its own handler
            return run_sweep(sweep.spec, req.store, max_in_flight=req.max_in_flight, retry_failed=req.retry_failed,
                             progress=progress, warm_start=warm_start, retry_damaged=retry_damaged)
    except (RayConnectError, RayStartError) as exc:
        fail(str(exc))
    except _store_errors() as exc:
        fail(str(exc))
    except (StoreFullError, StoreLostError) as exc:  # not bad input: exit 1, like a solve that fails
        fail(str(exc), code=1)
    except KeyboardInterrupt:
        fail("interrupted; done cases are kept, rerun the same command to resume", code=130)


def _print_nothing_to_run(sweep, as_json: bool) -> None:
    """A store that holds every case: the keys of a run's report with nothing submitted, or one line."""
    left, total = sweep.left, sweep.spec.n_cases
    if as_json:
        from orchestrator.sweep import SweepReport

        typer.echo(json_line(SweepReport(total=total, done_before=left["done"], failed_before=left["failed"]).as_dict()))
        return
    typer.echo(f"{sweep.request.store}: nothing to run — {left['done']} done, {left['failed']} failed of {total}"
               + (" (--retry-failed reruns the failed ones)" if left["failed"] else ""))


def _print_sweep_report(report, store: str, retry_damaged: bool, as_json: bool) -> None:
    """The run's report: strict JSON, or the damaged cases recomputed and one summary line."""
    if as_json:
        typer.echo(json_line(report.as_dict()))
        return
    rate = report.throughput
    if retry_damaged:
        typer.echo(f"{len(report.damaged_reset)} damaged case(s) or shape(s) recomputed"
                   + (": " + ", ".join(f"shape {a} case {b}" if b is not None else f"shape {a} (meshed again, every case)"
                                       for a, b in report.damaged_reset[:10]) if report.damaged_reset else "")
                   + (" …" if len(report.damaged_reset) > 10 else ""))
    typer.echo(f"{store}: {report.done_before + report.done} done, {report.failed_now} failed "
               f"of {report.total} ({report.done} done and {report.failed} failed in this run, "
               f"{report.submitted} submitted); meshing {report.phase1_s:.1f} s, pairs {report.phase2_s:.1f} s "
               f"on {_cpus_line(report)} ({rate:.2f} cases/s)"
               + (f"; {report.lost} cases lost with their workers are still pending (rerun to solve them)"
                  if report.lost else "") if report.submitted else
               f"{store}: nothing to run — {report.done_before} done, {report.failed_before} failed of {report.total}")


def _cpus_line(report) -> str:
    """Where the pairs were solved: the CPUs whose workers solved them (and their nodes, if several),
    and the cluster's CPUs when it had more."""
    where = f"{report.cpus:g} CPU{'s' if report.cpus != 1 else ''}"
    if report.nodes > 1:
        where += f" of {report.nodes} nodes"
    if report.cluster_cpus > report.cpus:
        where += f" (the cluster had {report.cluster_cpus:g})"
    return where


def _run_state(writer: dict | None, object_store: bool) -> str:
    """How an unfinished run stands: a local store's writer lock tells a running driver from a dead one."""
    if writer is not None:
        return f", running: pid {writer.get('pid')} on {writer.get('host')}"
    return ", running or interrupted" if object_store else ", interrupted"


def _print_plan(plan: dict, as_json: bool) -> None:
    """A dry run's plan: strict JSON, or the grid, counts, calibration, estimates and the paper's sweep."""
    if as_json:
        typer.echo(json_line(plan))
        return
    g = plan["grid"]
    axes = " × ".join(f"{len(g[a])} {n}" for a, n in (("pressure_mmhg", "P"), ("stiffness_pa", "C"),
                                                      ("helix_endo_deg", "θendo"), ("helix_epi_deg", "θepi")))
    how = ("new store" if not plan["resume"] else "resume" if plan.get("grows_from") is None else
           f"resume, growing the store from {plan['grows_from']} shapes")
    typer.echo(f"plan for {plan['store']} ({how}): {plan['shapes']} shapes × "
               f"{axes} = {plan['cases']} cases; {plan['done']} done, {plan['failed']} failed, {plan['to_run']} to run")
    typer.echo(f"fidelity {plan['fidelity']}, seed {plan['seed']}, ~{plan['mesh_nodes']} nodes per mesh")
    cal = plan.get("calibration")
    if cal:
        p = cal["params"]
        status = "ok" if cal["ok"] else f"FAILED: {cal['reason']}"
        typer.echo(f"calibration: shape 0 ({cal['nodes']} nodes) meshed in {cal['mesh_s']:.1f} s; one pair at "
                   f"P={p[0]:g} mmHg, C={p[1]:g} Pa, θ={p[2]:g}/{p[3]:g}° took {cal['cold_pair_s']:.2f} s on 1 core ({status})"
                   + (f", the next pressure warm-started from it {cal['warm_pair_s']:.2f} s: "
                      f"{cal['pair_s']:.2f} s a pair over a pressure chain" if "warm_pair_s" in cal else ""))
        typer.echo(f"estimate: {plan['core_hours']:.2f} core-hours"
                   + (f", {plan['wall_hours_at_cores'] * 60:.1f} min wall on {plan['cores']} cores" if plan.get("cores") else "")
                   + f"; store ≈ {plan['store_bytes_estimate'] / 1e6:.0f} MB ({cal['case_bytes'] / 1e3:.1f} kB per case), "
                   f"{plan['store_objects']:,} objects")
        typer.echo(f"to finish in one hour: {plan['cores_for_one_hour']:,} cores, e.g. "
                   f"{plan['worker_nodes_for_one_hour']:,} worker nodes of 32 vCPUs (cluster.yaml's c7i.8xlarge)")
        full = plan["paper_full_sweep_core_hours"]
        line = (f"full paper sweep (19,440 pairs) at this fidelity and mesh size: {full:.1f} core-hours, "
                f"{full * 60 / 64:.0f} min on 64 cores, store ≈ {plan['paper_full_sweep_store_bytes'] / 1e9:.2f} GB")
        if "fast_goal" in plan:
            line += (f"; goal ≤ 8 core-hours (≤ 1.5 s a pair): "
                     f"{'met' if plan['fast_goal']['meets'] else 'NOT met'} ({cal['pair_s']:.2f} s a pair)")
        typer.echo(line)


def _fmt_s(x) -> str:
    if x is None:
        return "—"
    if x >= 3600:
        return f"{x / 3600:.1f} h"
    if x >= 60:
        return f"{x / 60:.1f} min"
    return f"{x:.2f} s"


@app.command()
def status(store: str = typer.Option(..., "--store", help="Zarr store: a path or an fsspec URL."),
           verify: bool = typer.Option(False, "--verify", help="Also read every done case and list those whose stored chunks are damaged (exit 1 if any)."),
           as_json: bool = typer.Option(False, "--json", help='One JSON object: {"done": N, "failed": N, "pending": N, …}.')):
    """Progress of a store: counts by status, failure reasons, throughput, per-phase times, ETA."""
    from storage.status import store_status

    try:
        s = store_status(store, verify)
    except _store_errors() as exc:
        fail(str(exc))
    if as_json:
        typer.echo(json_line(s))
    else:
        _print_status(s, store, verify)
    if s.get("damaged") or s["table_damage"]:
        raise typer.Exit(1)


def _print_status(s: dict, store: str, verify: bool) -> None:
    """A store's status as lines and tables: counts, throughput and ETA, per-phase times, failure
    reasons, shapes that did not mesh, hosts, and with --verify the damaged cases."""
    from rich.console import Console
    from rich.table import Table

    from storage.store import is_url

    con = Console(width=160)
    made = ", ".join(part for part in (s["fidelity"], None if s["seed"] is None else f"seed {s['seed']}",
                                       None if s["mesh_nodes"] is None else f"~{s['mesh_nodes']} nodes") if part)
    con.print(f"[bold]{store}[/bold]: {s['shapes']} shapes × {s['cases_per_shape']} cases = {s['total']} "
              f"({made}{'; ' if made else ''}{s['shapes_ready']} shapes meshed)")
    pct = lambda n: f"{100 * n / s['total']:.1f} %" if s["total"] else "—"  # noqa: E731
    con.print(f"done {s['done']} ({pct(s['done'])}), failed {s['failed']} ({pct(s['failed'])}), "
              f"pending {s['pending']} ({pct(s['pending'])})"
              + (f", status unknown {s['unknown']} ({pct(s['unknown'])})" if s["unknown"] else ""))
    thr = s["throughput_cases_per_s"]
    lr = s["last_run"] or {}
    con.print(f"throughput (run {lr.get('index', '—')}, {lr.get('done_in_run', 0)} done"
              f"{'' if not lr else ', finished' if lr.get('ended') else _run_state(s['writer'], is_url(store))}"
              f"{'; over its whole wall time, meshing included' if lr else ''}): "
              + (f"{thr:.3f} cases/s ({thr * 3600:.0f}/h)" if thr else "—")
              + f"; ETA {_fmt_s(s['eta_s'])}"
              + (f"; store {s['store_bytes'] / 1e6:.1f} MB" if s.get("store_bytes") is not None else ""))
    table = Table(title="per-case times, done cases (s)")
    for col in ("phase", "p50", "p90", "p99", "max", "mean"):
        table.add_column(col, justify="right")
    for name, p in s["phase_percentiles_s"].items():
        if p is None:
            table.add_row(name, *["—"] * 5)
        else:
            table.add_row(name, *(f"{p[k]:.3f}" for k in ("p50", "p90", "p99", "max", "mean")))
    con.print(table)
    if s["failure_reasons"]:
        ft = Table(title="failure reasons")
        ft.add_column("cases", justify="right")
        ft.add_column("reason (numbers as #)")
        ft.add_column("e.g. (shape, case)")
        for f in s["failure_reasons"]:
            ft.add_row(str(f["count"]), f["reason"], ", ".join(f"({a}, {b})" for a, b in f["cases"]))
        con.print(ft)
    if s["mesh_failures"]:
        con.print(f"shapes that did not mesh: {s['mesh_failures']}")
    if s["hosts"]:
        con.print("done by host: " + ", ".join(f"{h} {n}" for h, n in sorted(s["hosts"].items())))
    damaged = s["damaged"] if verify else s["table_damage"]
    if verify and not damaged:
        con.print(f"verified: all {s['done']} done cases read back intact (checksums match, data present and "
                  f"finite, arrays as the schema says)")
    for d in damaged:
        where = "every case" if d["case"] is None else f"case {d['case']}"
        typer.echo(f"damaged: shape {d['shape']} {where}: {d['reason']}")
    if damaged:
        typer.echo(f"{_damage_count(damaged, s['cases_per_shape'])}; `heartctl generate --store {store} "
                   f"--retry-damaged` recomputes them" + ("" if verify else "; `--verify` reads every done case"))


def _damage_count(damaged: list, cases_per_shape: int) -> str:
    """"2 damaged cases", "1 damaged shape (4 cases)", or both: the damage status found, in words."""
    cases = sum(d["case"] is not None for d in damaged)
    shapes = len(damaged) - cases
    parts = ([f"{cases} damaged case{'s' if cases != 1 else ''}"] if cases else []) + \
            ([f"{shapes} damaged shape{'s' if shapes != 1 else ''} ({shapes * cases_per_shape} cases)"] if shapes else [])
    return " and ".join(parts)


@app.command()
def export(store: str = typer.Option(..., "--store", help="Zarr store: a path or an fsspec URL."),
           shape: int = typer.Option(..., "--shape", help="Shape id."),
           case: int = typer.Option(..., "--case", help="Case index k within the shape (see the store's case_params)."),
           out: Path = typer.Option(..., "-o", "--out", help="Output mesh file, e.g. case.vtu (ParaView)."),
           geometry: str = typer.Option("unloaded", "--geometry", help="Points of the mesh: unloaded | loaded.")):
    """Write one done case as a mesh (points = unloaded geometry, point data `displacement` = loaded − unloaded)."""
    from storage.store import export_case

    try:
        _check_output(out)
        params = export_case(store, shape, case, out, geometry)
    except _store_errors() as exc:
        fail(str(exc))
    typer.echo(f"shape {shape}, case {case} (P={params['pressure_mmhg']:g} mmHg, C={params['stiffness_pa']:g} Pa, "
               f"θ={params['helix_endo_deg']:g}/{params['helix_epi_deg']:g}°) → {out}")


@bench_app.command("sweep")
def bench_sweep(cases: int = typer.Option(8, "--cases", help="Pairs per run (one shape)."),
                nodes: int = typer.Option(200, "--nodes", help="Target mesh node count (coarse keeps it short)."),
                cpus: str = typer.Option("1,2", "--cpus", help="CPU counts to compare, comma-separated."),
                as_json: bool = typer.Option(False, "--json")):
    """Sweep throughput on 1 and 2 (…) CPUs, parallel efficiency, Ray overhead per task vs a fast pair's solve."""
    from orchestrator.bench import parse_cpu_counts, run_sweep_benchmark

    try:
        result = run_sweep_benchmark(cases, nodes, parse_cpu_counts(cpus))
    except ValueError as exc:
        fail(str(exc))
    if as_json:
        typer.echo(json_line(result))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"heartctl bench sweep — {result['cases']} fast pairs, {result['nodes']} nodes; "
                        f"plain serial {result['plain_serial_s_per_case']:.2f} s/pair cold, "
                        f"{result['chained_serial_s_per_case']:.2f} s/pair in warm-started pressure chains")
    for col in ("CPUs", "pairs/s", "speedup", "efficiency", "solve s (p50)", "idle core s/task", "submit→start s",
                "result→stored s", "no-op round trip s", "overhead % of solve (idle / stored / no-op)"):
        table.add_column(col, justify="right")
    for r in result["rows"]:
        table.add_row(str(r["cpus"]), f"{r['throughput_cases_per_s']:.3f}", f"{r['speedup_vs_1']:.2f}",
                      f"{100 * r['parallel_efficiency']:.0f} %", f"{r['solve_s_median']:.2f}",
                      f"{r['idle_core_s_per_task']:.3f}", f"{r['submit_to_start_s_median']:.3f}",
                      f"{r['result_to_stored_s_median']:.4f}", f"{r['noop_roundtrip_s_median']:.4f}",
                      f"{r['overhead_idle_core_pct']:.1f} / {r['overhead_result_to_stored_pct']:.2f} / "
                      f"{r['overhead_noop_pct']:.2f}")
    Console(width=200).print(table)
    typer.echo("Ray rows: one cold pair per task. submit→start includes queueing (2 tasks in flight per CPU); "
               "idle core s/task = (CPUs × wall − Σ solve) / pairs, everything that is not solving.")


# --- end of data generation ---


import numpy as np  # noqa: E402  (after the app so `heartctl --help` stays light)


def _usage_exception_types() -> tuple:
    """(usage errors, other click errors, aborts) of click and of the click typer vendors (≥ 0.16)."""
    import importlib

    mods = []
    for name in ("typer._click.exceptions", "click.exceptions"):
        try:
            mods.append(importlib.import_module(name))
        except ImportError:
            pass
    aborts = {typer.Abort, *(m.Abort for m in mods if hasattr(m, "Abort"))}
    return tuple(m.UsageError for m in mods), tuple(m.ClickException for m in mods), tuple(aborts)


def main() -> None:
    """The `heartctl` entry point: the typer app, with usage errors (an unknown option, preset or
    command, a value that is not a number, a missing option) as one line and exit code 2 like
    every other bad input, instead of click's framed usage box."""
    usage_errors, click_errors, aborts = _usage_exception_types()
    try:
        code = app(standalone_mode=False)
    except usage_errors as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":  # `heartctl` alone: the help is the answer
            typer.echo(exc.format_message(), err=True)
            sys.exit(2)
        where = exc.ctx.command_path if exc.ctx is not None else "heartctl"
        typer.echo(f"heartctl: error: {' '.join(exc.format_message().split())} (see {where} --help)", err=True)
        sys.exit(2)
    except click_errors as exc:
        typer.echo(f"heartctl: error: {' '.join(exc.format_message().split())}", err=True)
        sys.exit(exc.exit_code)
    except aborts:
        typer.echo("heartctl: error: interrupted", err=True)
        sys.exit(130)
    sys.exit(code if isinstance(code, int) else 0)


if __name__ == "__main__":  # pragma: no cover
    main()
