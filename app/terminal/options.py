"""The command line's choices and options: each choice type built from the lower layers' own names,
and the options that several commands share or that one command has many of (its Options class)."""
from __future__ import annotations

from enum import Enum

import typer

from app.unload import ADAPTIVE, METHODS
from solver.fidelity import PRESETS
from solver.parameters import BASE_CONDITIONS, SOLVE_DIRECTIONS
from storage.meshfiles import UNIT_TO_MM
from trainer.config import CONFIG_HELP  # the trainer's one light module (no torch): --help stays fast

from .console import flags_in


def _choices(name: str, values) -> type[Enum]:
    """A typer choice type whose members are the lower layers' own names (member name = value)."""
    return Enum(name, {v: v for v in values}, type=str)


Units = _choices("Units", UNIT_TO_MM)


FidelityName = _choices("FidelityName", PRESETS)


UnloadFidelity = _choices("UnloadFidelity", (*PRESETS, ADAPTIVE))


Direction = _choices("Direction", SOLVE_DIRECTIONS)


Base = _choices("Base", BASE_CONDITIONS)


UnloadMethod = _choices("UnloadMethod", METHODS)


class Problem(str, Enum):
    land1 = "land1"
    land2 = "land2"
    all = "all"


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


class UnloadOptions:
    """The options of `heartctl unload`."""

    mesh_path = typer.Argument(..., metavar="MESH", help="End-diastolic mesh.")
    out = typer.Option(..., "-o", "--out", help="Output: unloaded mesh with `displacement` (ED − unloaded).")
    method = typer.Option(UnloadMethod.fe, "--method", help="fe: inverse finite elements; "
                          "gnn: the trained network; hybrid: network guess refined by inverse FE; "
                          "auto: the cheapest that met --tolerance-mm on the run's trade table.")
    fidelity = typer.Option(UnloadFidelity.accurate, "--fidelity", help="Solver preset: fast (P1/P1) | accurate "
                            "(P2/P1) | reference (accurate on the mesh refined once: near the converged solution, "
                            "~10× accurate's time) | adaptive (accurate, refined where the error indicator is "
                            "largest until the estimated p95 nodal error is ≤ --tolerance-mm).")
    tol_mm = typer.Option(None, "--tol-mm", help="Max nodal mismatch to stop at, mm (default: the preset's 1e-4; hybrid 2e-3).")
    run = typer.Option(None, "--run", help="Run directory of a trained network (--method gnn|hybrid|auto; "
                       "default: the network shipped with heartctl); "
                       "repeat it to average several (an ensemble; the output "
                       "gets their per-node spread).")
    rotations = typer.Option(1, "--rotations", help="--method gnn|hybrid: average the network over K turns "
                             "about the long axis (K× the time; best with --rotate-deg 180 runs).")
    tolerance_mm = typer.Option(None, "--tolerance-mm", help="--method auto or --fidelity adaptive: the p95 nodal "
                                "error against the converged solution you accept, mm (auto: as bench trade measured "
                                "it; adaptive: as its error estimate puts it).")
    check = typer.Option(False, "--check", help="--method gnn|hybrid|auto: inflate the answer again (one "
                         "forward solve at --fidelity) and print how far it lands from the ED mesh.")


class TrainOptions:
    """The options of `heartctl train`."""

    store = typer.Option(..., "--store", help="Zarr store of FE pairs (heartctl generate).")
    run_dir = typer.Option(..., "--run-dir", help="Run directory: checkpoint.pt, metrics.csv, Ray storage; "
                           "reusing it resumes the run.")
    gpus = typer.Option(0, "--gpus", help="GPU workers (DDP over NCCL); 0 = CPU workers with gloo.")
    config = typer.Option("paper", "--config", help=flags_in(CONFIG_HELP))
    epochs = typer.Option(None, "--epochs", help="Max epochs (default 500; --local 5).")
    batch_size = typer.Option(16, "--batch-size", help="Graphs per batch per worker.")
    sr = typer.Option(1.0, "--sr", help="Supervision ratio: fraction of training cases with labels (e.g. 0.03).")
    labelled_share = typer.Option(0.25, "--labelled-share",
                                  help="SR < 1: share of each batch drawn from the labelled cases.")
    split = typer.Option("shape", "--split", help="shape (70/30 of shapes; shape:0.1 tests on 10 %) | "
                                                  "lovo:P=10 (C=, endo=, epi=) | source.")
    train_fraction = typer.Option(1.0, "--train-fraction",
                                  help="Train on this fraction of the training shapes (seeded; "
                                  "validation and test unchanged).")
    seed = typer.Option(0, "--seed", help="Seed of initialisation and shuffling, and of split and SR subset unless --split-seed is given.")
    split_seed = typer.Option(None, "--split-seed", help="Seed of split, SR subset and training-shape subset (default: --seed); "
                              "runs with one split seed and several --seed values form a seed ensemble.")
    label_seed = typer.Option(None, "--label-seed", help="With --sr < 1: seed of the labelled subset only "
                              "(default: the split seed); the same test cases, other labelled pairs.")
    local = typer.Option(False, "--local", help="Two CPU workers (Ray Train, gloo), a few epochs: minutes.")
    no_ray = typer.Option(False, "--no-ray", help="Run the plain PyTorch loop in this process (no Ray).")
    device = typer.Option(None, "--device", help="With --no-ray: cpu | cuda (default cuda when available).")
    workers = typer.Option(2, "--workers", help="CPU workers when --gpus 0.")
    address = typer.Option(None, "--address", help="Join a Ray cluster: auto | HOST:PORT (default: a local Ray).")
    connect_timeout = typer.Option(None, "--connect-timeout", help="With --address: seconds to wait for the cluster before giving up (default 30).")
    max_failures = typer.Option(2, "--max-failures", help="Restarts from the last checkpoint after a worker dies.")
    lr = typer.Option(1e-3, "--lr", help="AdamW learning rate.")
    patience = typer.Option(50, "--patience", help="Early stopping: epochs without a better validation loss.")
    init_from = typer.Option(None, "--init-from", help="Fine-tune: start from this run directory's (or "
                             "checkpoint's) weights and normalisation, with a fresh optimiser and schedule; "
                             "give the configuration it was trained with.")
    bf16 = typer.Option(False, "--bf16", help="bf16 autocast (GPU only).")
    compile_model = typer.Option(False, "--compile", help="torch.compile the training step (GPU; "
                                 "a few minutes to compile, then faster steps).")
    as_json = typer.Option(False, "--json", help="Print the summary as JSON (the last line of stdout).")


class LearningCurveOptions:
    """The options of `heartctl bench learning-curve`."""

    store = typer.Option(..., "--store", help="Zarr store of FE pairs.")
    root = typer.Option(..., "--root", help="Folder for one run directory per fraction.")
    config = typer.Option("paper", "--config", help=flags_in(CONFIG_HELP))
    fractions = typer.Option("0.25,0.5,1", "--fractions",
                             help="Comma-separated fractions of the training shapes.")
    epochs = typer.Option(30, "--epochs", help="Max epochs per fraction.")
    batch_size = typer.Option(8, "--batch-size", help="Graphs per batch.")
    sr = typer.Option(1.0, "--sr", help="Supervision ratio.")
    split = typer.Option("shape", "--split", help="shape | lovo:P=10 | source.")
    seed = typer.Option(0, "--seed", help="Seed of split, subsets and training.")
    target_md = typer.Option(0.15, "--target-md", help="MD target, mm.")
    target_hd = typer.Option(0.6, "--target-hd", help="HD target, mm.")
    target_dsc = typer.Option(0.99, "--target-dsc", help="DSC@1mm target.")
    device = typer.Option("cpu", "--device", help="cpu | cuda.")
    as_json = typer.Option(False, "--json", help="Print the result as JSON.")


class GenerateOptions:
    """The options of `heartctl generate`."""

    shapes = typer.Option(None, "--shapes", help="Number of shapes (default 60, the paper's; or the store's). More than an existing store's grows it by the shape model's next shapes, its done cases kept; fewer is refused.")
    store = typer.Option(..., "--store", help="Zarr store: a path or an fsspec URL (s3://…).")
    pressures = typer.Option(None, "--pressures", help="ED pressures, mmHg, comma-separated (default 4,6,…,14).")
    stiffness = typer.Option(None, "--stiffness", help="Stiffness C, Pa, comma-separated (default 50,100,…,300).")
    endo = typer.Option(None, "--endo", help="Endocardial helix angles, degrees (default 60,65,70).")
    epi = typer.Option(None, "--epi", help="Epicardial helix angles, degrees (default −60,−65,−70; write --epi=-60,-65).")
    fidelity = typer.Option(None, "--fidelity", help="Solver preset: fast | accurate (default) | reference (accurate on each mesh refined once: pairs near the converged solution, for evaluate --reference).")
    base = typer.Option(None, "--base", help="Base condition: sliding (default) | clamped | spring | heartfem.")
    fibres = typer.Option(None, "--fibres", help="Fibre rule: laplace (default) | heartfem (the original pipeline's).")
    seed = typer.Option(None, "--seed", help="Shape-model seed (default 0).")
    shape_model = typer.Option(None, "--shape-model", help="Shape model version of a new store: 2 (default: each mode N(0,1) within ±2 SD) | 3 (the same modes drawn uniformly within ±2 SD: the tails as often as the centre, for training sets) | 1. A store keeps its own.")
    nodes = typer.Option(None, "--nodes", help="Target mesh node count (default 800; --local 350).")
    meshes = typer.Option(None, "--meshes", help="Use your ED meshes as the shape set: a folder or a glob of mesh files (any meshio format; readable by every worker).")
    units = typer.Option(None, "--units", help="Length unit of the --meshes files (default mm).")
    address = typer.Option(None, "--address", help="Join a Ray cluster: auto | HOST:PORT (default: start a local Ray on all cores).")
    connect_timeout = typer.Option(None, "--connect-timeout", help="With --address: seconds to wait for the cluster before giving up (default 30).")
    num_cpus = typer.Option(None, "--num-cpus", help="CPUs of the local Ray (default: all cores; --local 2).")
    local = typer.Option(False, "--local", help="Two-core test mode: 3 shapes × 2 P × 2 C, coarse meshes, fast preset.")
    dry_run = typer.Option(False, "--dry-run", help="Print the plan (cases, core-hours from a calibration solve) and exit.")
    retry_failed = typer.Option(False, "--retry-failed", help="Also rerun cases recorded as failed.")
    retry_damaged = typer.Option(False, "--retry-damaged", help="First read every done case back; recompute the damaged ones (data missing, short, unreadable or not finite; status codes out of range; a shape whose arrays are not as the schema says is meshed again).")
    max_in_flight = typer.Option(None, "--max-in-flight", help="Tasks in flight (default 2 × the cluster's CPUs, re-read as nodes join); a task is one pressure chain.")
    warm_start = typer.Option(True, "--warm-start/--no-warm-start", help="Start each inverse from the unloaded geometry of its chain's lower pressures (default) or from the ED mesh.")
    as_json = typer.Option(False, "--json", help="Print the plan / final report as JSON.")
