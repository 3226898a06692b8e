"""`heartctl train`, `evaluate` and the network benchmarks in the terminal: training in this process
or on Ray with its refusals as one line, and the summaries and tables they print."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from .console import failures, json_line, say, stop_on_sigterm

if TYPE_CHECKING:
    from bench.ablation import AblationResult, AblationSeedsResult
    from bench.learning_curve import LearningCurveResult
    from bench.network_speed import ModelBenchResult
    from trainer.evaluation.evaluate import Evaluation
    from trainer.training.summary import TrainingSummary

RESUME_TRAINING = "interrupted; rerun the same command to resume from the last checkpoint"


def run_training_here(cfg, run_dir: Path, placement) -> TrainingSummary:
    """trainer.training.launch.train_in_process, its refusals and Ctrl-C (or SIGTERM) as one line."""
    from trainer.training.launch import train_in_process

    stop_on_sigterm()
    with failures(interrupted=RESUME_TRAINING):
        return train_in_process(cfg, run_dir, placement, log=lambda line: say(line, err=True))


def run_training_on_ray(cfg, run_dir: Path, placement, where) -> TrainingSummary:
    """Ray Train within a ray_session (a local Ray, or the cluster joined): refusals, Ray that will not
    start and Ctrl-C exit 2 (130) in one line, a training that fails exits 1."""
    from orchestrator.ray_session import ray_session
    from trainer.training.ray_local import local_ray_options
    from trainer.training.ray_train import check_ray_resources, train_with_ray

    gpus, workers = placement.gpus, placement.workers
    # Ray's TrainingFailedError and the like are not bad input: "training failed: …", exit 1
    with failures(interrupted=RESUME_TRAINING, other="training failed"):
        with ray_session(where, **local_ray_options(workers if placement.local else None)):
            check_ray_resources(gpus, workers, where.address)
            stop_on_sigterm()  # after ray.init, whose driver installs its own handler
            return train_with_ray(cfg, run_dir, gpus=gpus, cpu_workers=workers, max_failures=placement.max_failures)


def print_training(summary: TrainingSummary, config: str, kind: str, run_dir: Path, as_json: bool) -> None:
    """The run's summary: strict JSON, or one line (epochs, best validation MD, parameters, where)."""
    if as_json:
        typer.echo(json_line(summary.as_dict()))
        return
    best = summary.best_val_md_mm
    if kind == "pca":
        typer.echo(f"{config}: fitted; "
                   + (f"validation MD {best:.3f} mm" if best is not None else "no validation cases")
                   + f"; {summary.n_parameters or 0:,} parameters → {run_dir / 'checkpoint.pt'}")
        return
    typer.echo(f"{config}: {summary.epoch} epochs ({summary.mode}); "
               + (f"best validation MD {best:.3f} mm at epoch {summary.best_epoch}" if best is not None
                  else f"no validation cases, kept epoch {summary.best_epoch} (lowest training loss)")
               + (", stopped early" if summary.stopped_early else "")
               + f"; {summary.n_parameters or 0:,} parameters → {run_dir / 'checkpoint.pt'}")


def print_evaluation(report: Evaluation, store: str, as_json: bool) -> None:
    """An evaluation: one strict JSON object, or the metrics table (against the labels, and the
    converged solution when there is a reference), the configuration, timings and files written."""
    if as_json:
        typer.echo(json_line(report.as_dict()))
        return
    from rich.console import Console
    from rich.table import Table

    for u in report.unfinished_runs:
        typer.echo(f"warning: run {u['run']} is unfinished: it stopped at epoch {u['epoch']} of {u['epochs']} (killed, "
                   f"or still training); `heartctl train` with the same --run-dir finishes it", err=True)
    ref, net = report.reference, report.network
    table = Table(title=f"{net.config} on {report.cases} {report.split} cases of {store}")
    table.add_column("metric")
    table.add_column(f"vs its labels ({report.labels_fidelity}), mean ± SD", justify="right")
    table.add_column("cm", justify="right")
    if ref:
        table.add_column(f"vs converged ({ref['fidelity']}, {ref['cases']} cases)", justify="right")
        table.add_column("labels vs converged", justify="right")
    for key, name, cm in (("dsc_1mm", "DSC @ 1 mm", False), ("dsc_01mm", "DSC @ 0.1 mm", False),
                          ("hd_mm", "HD (mm)", True), ("md_mm", "MD (mm)", True), ("sd_mm", "SD (mm)", True),
                          ("nn_md_mm", "MD, nearest node (mm)", True), ("max_mm", "max node error (mm)", True)):
        m, s = report.aggregate[key]
        cells = [name, f"{m:.4f} ± {s:.4f}", f"{m / 10:.4f}" if cm else ""]
        if ref:
            cells += [f"{ref[who][key][0]:.4f} ± {ref[who][key][1]:.4f}" if key in ref[who] else ""
                      for who in ("network", "labels")]
        table.add_row(*cells)
    con = Console(width=200)
    con.print(table)
    for i, line in enumerate(net.configuration):
        con.print(f"configuration{f' of member {i + 1}' if net.members > 1 else ''}: {line}", markup=False)
    con.print(f"inference: {report.ms_per_case:.2f} ms per case at batch 1, "
              f"{report.ms_per_case_batched:.3f} ms per case at batch {report.batch_size} ({net.device})"
              + (f", each the mean of {net.rotations} turns about the long axis" if net.rotations > 1 else ""))
    if report.response_ms_per_mesh is not None:
        con.print(f"  + the linear FE response (node input): {report.response_ms_per_mesh:.0f} ms per mesh on the CPU, "
                  f"once for all the parameter sets a mesh is unloaded at")
    worst = report.worst_parameter
    con.print(f"per parameter value: worst MD {worst['md_mm_mean']:.3f} mm at {worst['parameter']} = {worst['value']:g} "
              f"({worst['cases']} cases); see by_parameter.csv")
    con.print(f"wrote {', '.join(report.files)} to {report.out_dir}")


def print_model_bench(r: "ModelBenchResult", as_json: bool) -> None:
    """bench model's figures: strict JSON, or lines for the model, each inference batch, the prepared
    single case, the linear FE response, training steps, batch building and any profiles."""
    if as_json:
        typer.echo(json_line(r.as_dict()))
        return
    typer.echo(f"{r.config} model, {r.parameters:,} parameters; mesh {r.nodes} nodes, {r.edges} directed edges; "
               f"{r.device_name} ({r.threads} threads){', bf16' if r.bf16 else ', fp32'}, "
               f"{'torch.compile (%.0f s to compile)' % r.compile_s if r.compiled else 'eager PyTorch'}, "
               f"{r.gat_kernel} GAT kernel")
    for row in r.inference:
        table = (f"; {row.table_ms_per_case:.3f} ms with the batch built from a graph table (attention graph "
                 f"assembled from the mesh's)") if row.table_ms_per_case is not None else ""
        typer.echo(f"inference batch {row.batch:>4}: {row.ms_per_case:8.3f} ms per case ({row.ms_per_batch:.1f} "
                   f"ms per batch){table}")
    pr = r.prepared_single
    how = "CUDA graph replay" if pr.cuda_graph else ("eager; capture failed: " + pr.capture_error
                                                     if pr.capture_error else "eager")
    typer.echo(f"inference batch    1, mesh prepared once ({how}): {pr.ms_per_case:8.3f} ms per case")
    if r.response_ms_per_mesh is not None:
        typer.echo(f"linear FE response (node input of {r.config}; CPU, once per mesh, shared by every case "
                   f"of it): {r.response_ms_per_mesh:.1f} ms")
    typer.echo(f"training batch {r.train_batch} (with cycle: {r.cycle}): {r.train_step_ms:.0f} ms per step, "
               f"{r.train_graphs_per_s:.1f} graphs/s")
    bb = r.batch_building
    typer.echo(f"building a batch of {r.train_batch}: {bb.table_ms:.2f} ms from the training loop's graph table "
               f"(on {bb.table_device}), {bb.pyg_ms:.2f} ms by PyG's collation and copy; a step with its batch "
               f"built, steps back to back as in the training loop: {bb.loop_step_ms:.0f} ms, "
               f"{r.loop_graphs_per_s:.1f} graphs/s")
    for table, what in ((r.profile_train, "three training steps"), (r.profile_inference, "three inferences of the largest batch")):
        if table is not None:
            typer.echo(f"torch.profiler, {what}:\n{table}")


def print_ablation(result: "AblationResult", store: str, root: Path, split: str, sr: float, epochs: int,
                   seed: int) -> None:
    """The ablation table (the best value per metric in bold), then the comparisons that matter."""
    from rich.console import Console
    from rich.table import Table

    from bench.ablation import KEY_COMPARISONS, TABLE_METRICS, beats

    rows = result.rows
    table = Table(title=f"test split of {store} (split {split}, SR {sr:g}, ≤ {epochs} epochs, seed {seed}; "
                        f"{rows[0].score.cases} cases)")
    for col in ("config", *[label for _, label, _ in TABLE_METRICS], "ms/case", "epochs"):
        table.add_column(col, justify="left" if col == "config" else "right")
    for r in rows:
        cells = [f"[bold]{r.score.metric(k):.3f}[/bold]" if result.best[k] == r.config else f"{r.score.metric(k):.3f}"
                 for k, _, _ in TABLE_METRICS]
        label = f"{r.config} ({r.code})" if r.code else r.config
        table.add_row(label, *cells, f"{r.score.ms_per_case:.1f}", f"{r.score.best_epoch}/{r.score.epochs}")
    con = Console(width=160)
    con.print(table)
    for name, rivals in KEY_COMPARISONS:
        won = beats(rows, name, list(rivals))
        present = [o for o in rivals if o in {r.config for r in rows}]
        if won and present:
            wins = [label for k, label, _ in TABLE_METRICS if won[k]]
            con.print(f"{name} vs {', '.join(present)}: better on {len(wins)}/{len(TABLE_METRICS)} metrics"
                      + (f" ({', '.join(wins)})" if wins else ""))
    con.print(f"wrote ablation.csv and ablation.json to {root}")


def print_ablation_seeds(result: "AblationSeedsResult", root: Path) -> None:
    """Mean ± SD per configuration over the seeds, then the seed-paired comparisons that matter."""
    from rich.console import Console
    from rich.table import Table

    from bench.ablation import KEY_COMPARISONS, TABLE_METRICS

    seeds = ", ".join(str(s) for s in result.seeds)
    table = Table(title=f"test split of {result.store} (split {result.split}, SR {result.sr:g}, "
                        f"≤ {result.epochs} epochs; seeds {seeds}): mean ± SD over seeds")
    for col in ("config", *[label for _, label, _ in TABLE_METRICS]):
        table.add_column(col, justify="left" if col == "config" else "right")
    for name, spreads in result.configs.items():
        table.add_row(name, *[f"{spreads[k].mean:.3f} ± {spreads[k].sd:.3f}" for k, _, _ in TABLE_METRICS])
    con = Console(width=160)
    con.print(table)
    n = len(result.seeds)
    for name, rival in ((name, rival) for name, rivals in KEY_COMPARISONS for rival in rivals):
        pair = result.pairs.get(f"{name} vs {rival}")
        if pair is None:
            continue
        md = pair["md_mm"]
        wins = sum(pair[k].better_seeds == n for k, _, _ in TABLE_METRICS)
        con.print(f"{name} vs {rival}: MD better on {md.better_seeds}/{n} seeds, paired difference "
                  f"{md.mean_diff:+.3f} ± {md.sd_diff:.3f} mm; better on every seed for {wins}/"
                  f"{len(TABLE_METRICS)} metrics")
    con.print(f"wrote ablation_seeds.json to {root} (per-seed tables under {root}/seed<N>/)")


def print_learning_curve(result: "LearningCurveResult", root: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"{result.config} on {result.store}: test split ({result.test_cases} cases), "
                        f"split {result.split}, SR {result.sr:g}, ≤ {result.epochs} epochs, seed {result.seed}")
    for col in ("fraction", "train pairs", "MD mm", "HD mm", "SD mm", "DSC@1mm", "epochs"):
        table.add_column(col, justify="right")
    for point in result.rows:
        r = point.score
        table.add_row(f"{point.fraction:g}", str(r.train_cases), f"{r.md_mm:.3f}", f"{r.hd_mm:.3f}",
                      f"{r.sd_mm:.3f}", f"{r.dsc_1mm:.3f}", f"{r.best_epoch}/{r.epochs}")
    con = Console(width=160)
    con.print(table)
    labels = {"md_mm": ("MD", "mm"), "hd_mm": ("HD", "mm"), "dsc_1mm": ("1 − DSC@1mm", "")}
    for key, law in result.laws.items():
        name, unit = labels[key]
        target = result.targets[key]
        goal = f"DSC@1mm {target:g}" if key == "dsc_1mm" else f"{name} {target:g} {unit}"
        need = result.pairs_needed.get(key)
        reach = (f"~{need:,.0f} training pairs for {goal}" if need is not None
                 else f"{goal} is not reached: the error does not fall with more data")
        con.print(f"{name} ≈ {law.a:.3g} · pairs^(−{law.b:.2f}) (R² {law.r2:.2f}): {reach}")
    con.print("(an extrapolation from these points at this epoch budget, an order of magnitude at best)")
    con.print(f"wrote learning_curve.csv and learning_curve.json to {root}")
