"""heartctl: the command-line interface. Parses arguments, calls the packages, formats output;
bad input → one line on stderr and exit code 2; a solve that fails → its reason and exit code 1."""
from __future__ import annotations

import sys
from pathlib import Path

import typer

from app.terminal.console import (fail, failures, json_line, mesh_progress, progress_of, say, usage_exception_types,
                                  warnings_as_lines)
from app.terminal.generation import (check_sweep_memory, print_nothing_to_run, print_plan, print_sweep_bench,
                                     print_sweep_report, sweep_or_fail, warn_high_pressure, warn_high_pressures)
from app.terminal.inputs import (case_parameters, check_fibres, check_output, read_mesh_file, set_solver_threads,
                                 solve_budget, split_names, write_mesh_file)
from app.terminal.l2u import print_l2u_check
from app.terminal.options import (Base, BaseOpt, Direction, DropoutOpt, EmaOpt, EndoOpt, EpiOpt, FibresOpt,
                                  FidelityName, FidelityOpt, GenerateOptions, LayerOpt, LearningCurveOptions,
                                  LrScheduleOpt, NodeInputOpt, OutputScaleOpt, PresetLrScheduleOpt, PresetScalePctOpt,
                                  PressureOpt, Problem, RotateDegOpt, ScalePctOpt, SetOpt, StiffnessOpt, ThreadsOpt,
                                  TrainOptions, Units, UnitsOpt, UnloadFidelity, UnloadMethod, UnloadOptions)
from app.terminal.solving import (print_adaptive_bench, print_convergence, print_corners, print_inflated, print_land,
                                  print_shape_mesh, print_solver_bench, print_trade, report_header)
from app.terminal.status import print_exported, print_status
from app.terminal.training import (print_ablation, print_ablation_seeds, print_evaluation, print_learning_curve,
                                   print_model_bench, print_training, run_training_here, run_training_on_ray)
from app.terminal.unloading import unload_and_report

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
    from app.meshing import shape_mesh

    with failures():
        check_output(out)
        result = shape_mesh(shape, seed, shape_model, nodes, endo, epi, fidelity.value, progress=mesh_progress)
        write_mesh_file(out, result.lv, point_data=result.point_data, cell_data=result.cell_data, units=units.value)
    print_shape_mesh(result, out)


@app.command()
def solve(mesh_path: Path = typer.Argument(..., metavar="MESH", help="Unloaded (stress-free) mesh."),
          pressure: float = PressureOpt, stiffness: float = StiffnessOpt, endo: float = EndoOpt, epi: float = EpiOpt,
          out: Path = typer.Option(..., "-o", "--out", help="Output: deformed mesh with `displacement`."),
          fidelity: FidelityName = FidelityOpt, base: Base = BaseOpt, units: Units = UnitsOpt,
          fibres: str = FibresOpt, threads: int = ThreadsOpt):
    """Forward inflation of an unloaded mesh to the ED pressure."""
    set_solver_threads(threads)
    from solver.lv import forward_solve

    with failures():
        params = case_parameters(pressure, stiffness, endo, epi)
        check_fibres(fibres)
        check_output(out, mesh_path)
        lv = read_mesh_file(mesh_path, units.value)
    warn_high_pressure(pressure)
    est = solve_budget(mesh_path, lv, fidelity.value, inverse=False)
    with failures(solve="forward solve did not converge"):
        with progress_of(est, str(mesh_path)):
            result = forward_solve(lv, params, fidelity.value, base.value, fibres=fibres)
    write_mesh_file(out, lv, result.loaded_nodes, point_data={"displacement": result.displacement},
                    units=units.value, length_fields=("displacement",))
    print_inflated(result, params, fidelity.value, base.value, out)


def _given(ctx: typer.Context, name: str) -> bool:
    """Whether the user named option `name` on the command line (not left at its default). By the
    source's name: typer vendors its own click, whose ParameterSource is not click.core's."""
    source = ctx.get_parameter_source(name)
    return source is not None and source.name not in ("DEFAULT", "DEFAULT_MAP")


@app.command()
def unload(ctx: typer.Context, mesh_path: Path = UnloadOptions.mesh_path, pressure: float = PressureOpt,
           stiffness: float = StiffnessOpt, endo: float = EndoOpt, epi: float = EpiOpt,
           out: Path = UnloadOptions.out, method: UnloadMethod = UnloadOptions.method,
           fidelity: UnloadFidelity = UnloadOptions.fidelity, base: Base = BaseOpt, units: Units = UnitsOpt,
           tol_mm: float = UnloadOptions.tol_mm, run: list[Path] = UnloadOptions.run,
           rotations: int = UnloadOptions.rotations, fibres: str = FibresOpt,
           tolerance_mm: float = UnloadOptions.tolerance_mm, check: bool = UnloadOptions.check,
           threads: int = ThreadsOpt):
    """Unload a user's ED mesh: the stress-free geometry that inflates back onto it."""
    set_solver_threads(threads)
    from app.unload import UnloadRequest

    with failures():
        params = case_parameters(pressure, stiffness, endo, epi)
        check_output(out, mesh_path)
        given = frozenset(n for n in ("fidelity", "tol_mm", "base", "fibres") if _given(ctx, n))
        request = UnloadRequest(method=method.value, fidelity=fidelity.value, base=base.value, fibres=fibres, tol_mm=tol_mm,
                                runs=tuple(run or ()), rotations=rotations, tolerance_mm=tolerance_mm, check=check,
                                given=given)
        lv = read_mesh_file(mesh_path, units.value)
        plan, choice = request.plan(lv.n_nodes)
    warn_high_pressure(pressure)
    unload_and_report(mesh_path, lv, params, plan, choice, request, out, units.value)


@app.command()
def verify(problem: Problem = typer.Option(Problem.all, "--problem", help="Land et al. 2015 problem."),
           fidelity: FidelityName = FidelityOpt,
           as_json: bool = typer.Option(False, "--json", help="One JSON object per problem on stdout."),
           threads: int = ThreadsOpt):
    """Run the Land et al. (2015) verification problems and compare with the published values."""
    set_solver_threads(threads)
    from solver.land_problems import land1, land2

    if fidelity is FidelityName.reference:
        fail("verify solves the Land et al. problems on their own meshes; choose --fidelity fast or accurate "
             "(bench convergence measures refinement)")
    names = ["land1", "land2"] if problem is Problem.all else [problem.value]
    for name in names:
        print_land((land1 if name == "land1" else land2)(fidelity.value), as_json)


@bench_app.command("solver")
def bench_solver(fidelity: list[FidelityName] = typer.Option(None, "--fidelity", help="Presets (default: all)."),
                 nodes: int = typer.Option(1000, "--nodes", help="Target mesh node count."),
                 shape: int = typer.Option(0, "--shape"),
                 threads: int = typer.Option(1, "--threads", help="Threads for the sparse solver (goals are for 1 core)."),
                 as_json: bool = typer.Option(False, "--json")):
    """Wall time of forward and pair per preset at a mid case (8 mmHg, 150 Pa) and the extreme (14, 50)."""
    set_solver_threads(threads)
    from bench.solver_speed import run_solver_benchmark

    presets = [f.value for f in fidelity] if fidelity else ["fast", "accurate"]
    with failures():
        rows = run_solver_benchmark(presets, nodes, shape)
    print_solver_bench(rows, shape, nodes, threads, as_json)


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
    from bench.stability import EXTENDED_BOX, PAPER_BOX, format_row, run_stability

    presets = [f.value for f in fidelity] if fidelity else ["fast", "accurate"]
    with failures():
        check_fibres(fibres)
        if "reference" in presets:
            raise ValueError("--fidelity reference is not a stability target (it is accurate on a refined mesh)")
        nodes = nodes or (350 if extended else 800)
        echo = (lambda r: typer.echo(json_line(r.as_dict()))) if as_json else (lambda r: typer.echo(format_row(r)))
        rows = [row for box in ((PAPER_BOX, EXTENDED_BOX) if extended else (PAPER_BOX,))
                for row in run_stability(presets, box, nodes, base.value, fibres, progress=echo)]
    print_corners(rows, presets, out, report_header("corners", f"; {base.value} base, {fibres} fibres, ~{nodes}-node meshes."))


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
    set_solver_threads(threads)
    from bench.convergence import ConvergenceSpec, parse_hierarchies, parse_quad_degrees, run_convergence
    from bench.convergence_report import write_report

    with failures():
        check_fibres(fibres)
        spec = ConvergenceSpec(split_names(shapes), split_names(cases), parse_hierarchies(meshes),
                               base=base.value, fibres=fibres,
                               quad_degrees=parse_quad_degrees(quadrature)).validate()
        result = run_convergence(spec, out / "solves", progress=typer.echo)
    details = f", solver sha256:{result.solver}; base {base.value}, {fibres} fibres."
    print_convergence(result, write_report(result, out, report_header("convergence", details, threads)))


@bench_app.command("adaptive")
def bench_adaptive(shapes: str = typer.Option("mean", "--shapes", help="Comma-separated: mean | minus2 | plus2 (every shape mode at 0, −2 or +2 SD)."),
                   cases: str = typer.Option("mid,hard", "--cases", help="Comma-separated: mid (8 mmHg, 150 Pa) | hard (14 mmHg, 50 Pa)."),
                   nodes: int = typer.Option(350, "--nodes", help="The gmsh mesh's size (150–2000 nodes)."),
                   tolerance: str = typer.Option("0.05", "--tolerance", help="Comma-separated targets of the adaptive unload (p95, mm)."),
                   base: Base = BaseOpt, fibres: str = FibresOpt,
                   out: Path = typer.Option(Path("reports/adaptive"), "--out", help="Report folder: adaptive.md, adaptive.json."),
                   threads: int = typer.Option(1, "--threads", help="Threads for the sparse solver.")):
    """Adaptive unloading against the converged solution: the error indicator's ranking of the true
    local error, and the adaptive answer's error, estimate and time against `reference`'s."""
    set_solver_threads(threads)
    from bench.adaptive import AdaptiveSpec, parse_tolerances, run_adaptive, write_report

    with failures():
        check_fibres(fibres)
        spec = AdaptiveSpec(split_names(shapes), split_names(cases), nodes,
                            parse_tolerances(split_names(tolerance)), base.value, fibres).validate()
        result = run_adaptive(spec, progress=typer.echo)
    print_adaptive_bench(result, write_report(result, out, report_header("adaptive", f", solver sha256:{result.solver}; "
                                                                   f"base {base.value}, {fibres} fibres.", threads)))


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
                                         "run's store's); another seed's shapes are all unseen, from --first-shape 0."),
                shape_model: int = typer.Option(None, "--shape-model", help="Shape model version of the held-out "
                                                "shapes (default: the run's store's); another version's are all unseen.")):
    """The speed–accuracy trade: held-out ED meshes unloaded by FE (fast, accurate), the network, and the
    network's guess refined by 1, 2, 4 inverse updates or to tolerance, each against the converged
    solution (the reference preset). Writes trade.md, trade.png and trade.json (read by --method auto)."""
    set_solver_threads(threads)
    from bench.trade import TradeSpec, run_trade
    from bench.trade_table import write_report

    out = out or run[0] / "trade"
    with failures():
        spec = TradeSpec(tuple(str(r) for r in run), shapes, cases, user_nodes, network_only=network_only,
                         first_shape=first_shape, seed=seed, shape_model=shape_model).validate()
        result = run_trade(spec, out / "solves", progress=typer.echo)
    print_trade(result, write_report(result, out, report_header("trade", "", threads)))


# --- the original paper's dataset ---


@app.command("import-l2u")
def import_l2u_cmd(folder: Path = typer.Argument(..., metavar="DIR", help="Folder with the Loaded2UnNet dataset (searched at any depth)."),
                   store: str = typer.Option(..., "--store", help="New Zarr store to write.")):
    """Import the original paper's public FE pairs (VTU, cm) as done cases of a new store (mm)."""
    from storage.l2u import import_l2u

    with failures():
        with warnings_as_lines():
            report = import_l2u(folder, store)
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

    with failures():
        result = run_l2u_check(store, fidelity.value, base.value, limit, stiffness_factor, fibres, quad_degree,
                               direction.value)
    print_l2u_check(result, direction, as_json)


# --- training and evaluation ---


@app.command()
def train(store: str = TrainOptions.store, run_dir: Path = TrainOptions.run_dir, gpus: int = TrainOptions.gpus,
          config: str = TrainOptions.config, node_input: str = NodeInputOpt, ema: float = EmaOpt,
          dropout: float = DropoutOpt, output_scale: str = OutputScaleOpt, layer: str = LayerOpt,
          settings: list[str] = SetOpt, epochs: int = TrainOptions.epochs, batch_size: int = TrainOptions.batch_size,
          sr: float = TrainOptions.sr, labelled_share: float = TrainOptions.labelled_share,
          split: str = TrainOptions.split, train_fraction: float = TrainOptions.train_fraction,
          seed: int = TrainOptions.seed, split_seed: int = TrainOptions.split_seed,
          label_seed: int = TrainOptions.label_seed, rotate_deg: float = RotateDegOpt,
          scale_pct: float = PresetScalePctOpt, lr_schedule: str = PresetLrScheduleOpt,
          local: bool = TrainOptions.local, no_ray: bool = TrainOptions.no_ray, device: str = TrainOptions.device,
          workers: int = TrainOptions.workers, address: str = TrainOptions.address,
          connect_timeout: float = TrainOptions.connect_timeout, max_failures: int = TrainOptions.max_failures,
          lr: float = TrainOptions.lr, patience: int = TrainOptions.patience,
          init_from: Path = TrainOptions.init_from, bf16: bool = TrainOptions.bf16,
          compile_model: bool = TrainOptions.compile_model, as_json: bool = TrainOptions.as_json):
    """Train HeartUnloadNet (or an ablation / baseline) on a store; Ray Train DDP, or --no-ray."""
    from orchestrator.ray_session import RayAddress
    from trainer.training.launch import Placement, prepare_training

    with failures():
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
    if placement.in_process(cfg):
        summary = run_training_here(cfg, run_dir.resolve(), placement)
    else:
        summary = run_training_on_ray(cfg, run_dir.resolve(), placement, where)
    print_training(summary, config, cfg.model.kind, run_dir, as_json)


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
    from trainer.evaluation.evaluate import evaluate_run

    with failures():
        report = evaluate_run(run[0], store, split, device, out, plots, rotations=rotations, members=run[1:],
                              reference=reference)
    print_evaluation(report, store, as_json)


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
    from bench.network_speed import ModelBench

    with failures():
        with warnings_as_lines():
            r = ModelBench(device=device, nodes=nodes, config=config, batches=batches, train_batch=train_batch, bf16=bf16,
                           threads=threads, gat_kernel=gat_kernel, mesh=mesh, mesh_units=units.value,
                           compile_model=compile_model, profile=profile, min_seconds=min_seconds).run()
    print_model_bench(r, as_json)


@bench_app.command("ablation")
def bench_ablation_cmd(store: str = typer.Option(..., "--store", help="Zarr store of FE pairs."),
                       root: Path = typer.Option(..., "--root", help="Folder for one run directory per configuration."),
                       configs: str = typer.Option("paper,no-cycle,gcn,pca", "--configs", help="Comma-separated configurations."),
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
    from bench.ablation import AblationSeedsResult, ablation_study

    with failures():
        result = ablation_study(store, root, configs, seeds, device, lambda line: say(line, err=True),
                                split=split, sr=sr, seed=seed, epochs=epochs, batch_size=batch_size,
                                rotate_deg=rotate_deg, scale_pct=scale_pct, lr_schedule=lr_schedule)
    if as_json:
        typer.echo(json_line(result.as_dict()))
    elif isinstance(result, AblationSeedsResult):
        print_ablation_seeds(result, root)
    else:
        print_ablation(result, store, root, split, sr, epochs, seed)


@bench_app.command("learning-curve")
def bench_learning_curve_cmd(store: str = LearningCurveOptions.store, root: Path = LearningCurveOptions.root,
                             config: str = LearningCurveOptions.config,
                             fractions: str = LearningCurveOptions.fractions,
                             epochs: int = LearningCurveOptions.epochs,
                             batch_size: int = LearningCurveOptions.batch_size, sr: float = LearningCurveOptions.sr,
                             split: str = LearningCurveOptions.split, seed: int = LearningCurveOptions.seed,
                             target_md: float = LearningCurveOptions.target_md,
                             target_hd: float = LearningCurveOptions.target_hd,
                             target_dsc: float = LearningCurveOptions.target_dsc,
                             device: str = LearningCurveOptions.device, rotate_deg: float = RotateDegOpt,
                             scale_pct: float = PresetScalePctOpt, lr_schedule: str = PresetLrScheduleOpt,
                             as_json: bool = LearningCurveOptions.as_json):
    """Train one configuration on growing fractions of the training shapes, evaluate each on the same
    test shapes, fit error ∝ pairs^(−b) and extrapolate the pairs a target would take."""
    from bench.learning_curve import learning_curve_config, parse_fractions, run_learning_curve

    with failures():
        values = parse_fractions(fractions)
        base, targets = learning_curve_config(store, root, config, split, device, dict(
            sr=sr, seed=seed, epochs=epochs, batch_size=batch_size, rotate_deg=rotate_deg, scale_pct=scale_pct,
            lr_schedule=lr_schedule), {"md_mm": target_md, "hd_mm": target_hd, "dsc_1mm": target_dsc})
        result = run_learning_curve(base, values, root, targets, device, lambda line: say(line, err=True))
    if as_json:
        typer.echo(json_line(result.as_dict()))
        return
    print_learning_curve(result, root)


# --- end of training and evaluation ---


# --- data generation ---


@app.command()
def generate(shapes: int = GenerateOptions.shapes, store: str = GenerateOptions.store,
             pressures: str = GenerateOptions.pressures, stiffness: str = GenerateOptions.stiffness,
             endo: str = GenerateOptions.endo, epi: str = GenerateOptions.epi,
             fidelity: str = GenerateOptions.fidelity, base: str = GenerateOptions.base,
             fibres: str = GenerateOptions.fibres, seed: int = GenerateOptions.seed,
             shape_model: int = GenerateOptions.shape_model,
             nodes: int = GenerateOptions.nodes, meshes: str = GenerateOptions.meshes,
             units: Units = GenerateOptions.units, address: str = GenerateOptions.address,
             connect_timeout: float = GenerateOptions.connect_timeout, num_cpus: int = GenerateOptions.num_cpus,
             local: bool = GenerateOptions.local, dry_run: bool = GenerateOptions.dry_run,
             retry_failed: bool = GenerateOptions.retry_failed, retry_damaged: bool = GenerateOptions.retry_damaged,
             max_in_flight: int = GenerateOptions.max_in_flight, warm_start: bool = GenerateOptions.warm_start,
             as_json: bool = GenerateOptions.as_json):
    """Generate FE pairs (inverse + forward) over shapes × P × C × θendo × θepi into a Zarr store, on Ray.
    Rerunning on the same store resumes it; a larger --shapes grows it."""
    from orchestrator.ray_session import RayAddress
    from orchestrator.sweep_request import SweepRequest, resolve_sweep

    with failures():
        request = SweepRequest(store=store, shapes=shapes, pressures=pressures, stiffness=stiffness, endo=endo, epi=epi,
                               fidelity=fidelity, base=base, fibres=fibres, seed=seed, nodes=nodes, meshes=meshes,
                               shape_model=shape_model,
                               mesh_units=None if units is None else units.value, local=local, address=address,
                               num_cpus=num_cpus, max_in_flight=max_in_flight, retry_failed=retry_failed,
                               retry_damaged=retry_damaged, dry_run=dry_run)
        where = RayAddress(address, connect_timeout)
        with warnings_as_lines():
            sweep = resolve_sweep(request)
    warn_high_pressures(sweep.high_pressures())
    if not dry_run and address is None:
        check_sweep_memory(sweep)
    if dry_run:
        print_plan(sweep.plan(warm_start), as_json)
    elif sweep.nothing_to_run(retry_damaged):
        print_nothing_to_run(sweep, as_json)
    else:
        report = sweep_or_fail(sweep, where, warm_start, retry_damaged, progress=not as_json)
        print_sweep_report(report, store, retry_damaged, as_json)


@app.command()
def status(store: str = typer.Option(..., "--store", help="Zarr store: a path or an fsspec URL."),
           verify: bool = typer.Option(False, "--verify", help="Also read every done case and list those whose stored chunks are damaged (exit 1 if any)."),
           as_json: bool = typer.Option(False, "--json", help='One JSON object: {"done": N, "failed": N, "pending": N, …}.')):
    """Progress of a store: counts by status, failure reasons, throughput, per-phase times, ETA."""
    from storage.status import store_status

    with failures():
        s = store_status(store, verify)
    if as_json:
        typer.echo(json_line(s.as_dict()))
    else:
        print_status(s, store, verify)
    if s.damaged or s.table_damage:
        raise typer.Exit(1)


@app.command()
def export(store: str = typer.Option(..., "--store", help="Zarr store: a path or an fsspec URL."),
           shape: int = typer.Option(..., "--shape", help="Shape id."),
           case: int = typer.Option(..., "--case", help="Case index k within the shape (see the store's case_params)."),
           out: Path = typer.Option(..., "-o", "--out", help="Output mesh file, e.g. case.vtu (ParaView)."),
           geometry: str = typer.Option("unloaded", "--geometry", help="Points of the mesh: unloaded | loaded.")):
    """Write one done case as a mesh (points = unloaded geometry, point data `displacement` = loaded − unloaded)."""
    from storage.export import export_case

    with failures():
        check_output(out)
        params = export_case(store, shape, case, out, geometry)
    print_exported(shape, case, params, out)


@bench_app.command("sweep")
def bench_sweep(cases: int = typer.Option(8, "--cases", help="Pairs per run (one shape)."),
                nodes: int = typer.Option(200, "--nodes", help="Target mesh node count (coarse keeps it short)."),
                cpus: str = typer.Option("1,2", "--cpus", help="CPU counts to compare, comma-separated."),
                as_json: bool = typer.Option(False, "--json")):
    """Sweep throughput on 1 and 2 (…) CPUs, parallel efficiency, Ray overhead per task vs a fast pair's solve."""
    from bench.sweep_speed import parse_cpu_counts, run_sweep_benchmark

    with failures():
        result = run_sweep_benchmark(cases, nodes, parse_cpu_counts(cpus))
    print_sweep_bench(result, as_json)


# --- end of data generation ---


def main() -> None:
    """The `heartctl` entry point: the typer app, with usage errors (an unknown option, preset or
    command, a value that is not a number, a missing option) as one line and exit code 2 like
    every other bad input, instead of click's framed usage box."""
    usage_errors, click_errors, aborts = usage_exception_types()
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
