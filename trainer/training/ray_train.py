"""Ray Train wrapper around the plain loop: TorchTrainer (DDP; NCCL on GPUs, gloo on CPU workers),
rank-0 checkpoints reported to Ray storage in the run directory, resume and worker-failure restarts."""
from __future__ import annotations

import logging
import os
import shutil
import sys
import tempfile
import uuid
from pathlib import Path

from storage.disk import is_disk_full

from trainer.training.checkpoint import (CHECKPOINT_NAME, DiskFullError, check_resume_parts, disk_full_error,
                         load_checkpoint, remove_stale_temporaries, run_checkpoint_path, save_checkpoint)
from trainer.config import TrainConfig
from trainer.errors import TrainerError, TrainingDiverged
from trainer.training.summary import TrainingSummary

# A refusal that every rank reaches alike (the training loss diverged in the same epoch; the store
# cannot be read or split on some worker) is told to the driver by a reported marker checkpoint (one
# file, the message; Ray keeps metrics only with checkpoints), not by an error that Ray would retry
# --max-failures times, each time refusing again.
REFUSED = "heartctl_refused"
REFUSED_FILE = "refused.txt"
RAY_RUN_NAME = "ray"  # Ray storage: <run_dir>/ray/ (the same name resumes the run)
def check_ray_resources(gpus: int, workers: int, address: str | None) -> None:
    """TrainerError unless the running Ray has the GPUs asked for, or, for CPU workers on a local
    Ray, one CPU per worker (Ray Train would wait for them for ever)."""
    import ray

    where = f"cannot start or join Ray ({address or 'local'})"
    if gpus and ray.cluster_resources().get("GPU", 0) < gpus:
        raise TrainerError(f"{where}: gpus={gpus}: the Ray cluster has {ray.cluster_resources().get('GPU', 0):g} GPUs")
    cpus = ray.cluster_resources().get("CPU", 0)
    if not gpus and not address and cpus < workers:
        raise TrainerError(f"{where}: workers={workers}: the local Ray has {cpus:g} CPUs; use workers={int(cpus)} "
                           f"or fewer (one CPU each), or join a larger cluster with `address`")


def worker_trainer_error(exc: BaseException) -> TrainerError | None:
    """The TrainerError a Ray Train worker raised (bad input found on the worker), looked up by type
    in Ray's failure (_failure_chain). None when there is none."""
    return next((e for e in _failure_chain(exc) if isinstance(e, TrainerError)), None)


def worker_disk_full(exc: BaseException, run_dir) -> DiskFullError | None:
    """A full disk (ENOSPC, EDQUOT) anywhere in Ray's failure, as the DiskFullError a worker raised or
    one naming run_dir (Ray Train's own copy of a reported checkpoint); None when there is none."""
    for e in _failure_chain(exc):
        if isinstance(e, DiskFullError):
            return e
        if is_disk_full(e):
            return disk_full_error(run_dir, e)
    return None


def _failure_chain(exc: BaseException):
    """Every exception in Ray's failure, breadth first: a WorkerGroupError's worker_failures (lowest
    rank first), each wrapping the worker's own exception, and the exceptions they were raised from."""
    seen, todo = set(), [exc]
    while todo:
        e = todo.pop(0)
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        yield e
        failures = getattr(e, "worker_failures", None) or {}
        todo += [failures[rank] for rank in sorted(failures)]
        todo += [getattr(e, name, None) for name in ("_base_exc", "cause", "controller_failure")]
        todo += [e.__cause__, e.__context__]


def serves_state_api() -> bool:
    """Whether the Ray this process is connected to runs a dashboard, which serves the State API.
    Ray Train's placement-group cleaner (an actor that removes the run's placement group if the
    controller dies) asks the State API whether the controller lives; without it each question waits
    10 s and fails, and the controller waits 12 s for the cleaner to stop at the end of every run.
    Assumed served when Ray does not say."""
    try:
        from ray._private.worker import get_dashboard_url

        return bool(get_dashboard_url())
    except Exception:  # noqa: BLE001 - an older or newer Ray: keep Ray Train's defaults
        return True


def without_pg_cleaner(trainer) -> None:
    """Drop the placement-group cleaner from a Ray Train trainer's controller callbacks (for a Ray
    without the State API, where it cannot work: Ray removes a local cluster's placement groups when
    the cluster stops). Leaves the trainer as it is when this Ray version builds its callbacks
    otherwise."""
    try:
        from ray.train.v2._internal.callbacks.placement_group_callback import PlacementGroupCleanerCallback
    except ImportError:
        return
    make = getattr(trainer, "_create_default_callbacks", None)
    if make is None:
        return
    trainer._create_default_callbacks = lambda: [c for c in make() if not isinstance(c, PlacementGroupCleanerCallback)]


# The INFO lines of every ray.train.report in a worker ("Checkpoint successfully created at: …" once an
# epoch): the run's own log line says the epoch, and the run directory holds the checkpoints.
# Ray Train v2 names one of the two loggers after its module, the other (context.py) after its file path.
RAY_REPORT_LOGGERS = ("ray.train.v2._internal.execution.storage",)


def warnings_and_up(record: logging.LogRecord) -> bool:
    return record.levelno >= logging.WARNING


def quieten_checkpoint_reports() -> None:
    names = list(RAY_REPORT_LOGGERS)
    try:
        from ray.train.v2._internal.execution import context as _ray_ctx

        names.append(_ray_ctx.__file__)
    except ImportError:
        pass
    for name in names:
        logger = logging.getLogger(name)
        if warnings_and_up not in logger.filters:
            logger.addFilter(warnings_and_up)


def worker_data(cfg: TrainConfig, rank: int, host: str, same_host: bool):
    """(the worker's DataBundle, None), or (None, a one-line refusal) when it cannot read or split the
    store. The driver checked the store before the workers started; a worker on another machine can
    still miss it (a path on the driver's own disk)."""
    from storage.location import StoreError, is_url

    from trainer.data.store_cases import training_data

    try:
        return training_data(cfg), None
    except (TrainerError, StoreError, OSError) as exc:  # OSError: a folder this worker's user cannot list
        where = f"Ray worker {rank} on {host}"
        if not isinstance(exc, TrainerError) and not same_host and not is_url(cfg.store):
            where += ", not the driver's machine: every worker must reach the store at the same path (a shared " \
                     "filesystem) or read it from s3://"
        return None, f"{exc} ({where})"


def agreed_refusal(refusal: str | None, world: int, device) -> str | None:
    """The lowest refusing rank's message on every rank, or None when no rank refuses (a collective:
    every rank calls it, so they all stop together or all train)."""
    if world <= 1:
        return refusal
    import torch
    import torch.distributed as tdist

    if device.type == "cuda":  # NCCL gathers objects through the current device
        torch.cuda.set_device(device)
    gathered = [None] * world
    tdist.all_gather_object(gathered, refusal)
    return next((m for m in gathered if m), None)


def _train_worker(config: dict) -> None:
    """Runs in every Ray Train worker."""
    import ray
    import ray.train
    import ray.train.torch
    import torch

    from trainer.training.loop import Dist, fit, pick_resume_state  # here, not at the top: Ray Train's controller imports
    # this module to unpickle the function, and needs neither the loop nor PyG (~1.7 s on a busy core)

    ctx = ray.train.get_context()
    rank, world = ctx.get_world_rank(), ctx.get_world_size()
    device = ray.train.torch.get_device()
    cfg = TrainConfig.from_dict(config["train_config"])
    if device.type == "cpu" and cfg.num_threads == 0:
        torch.set_num_threads(max(1, int(config.get("threads_per_worker", 1))))
    run_dir = Path(config["run_dir"])
    same_host = ray.util.get_node_ip_address() == config.get("driver_ip")

    def restore():
        candidates = []
        ckpt = ray.train.get_checkpoint()
        if ckpt is not None:
            with ckpt.as_directory() as d:
                if (Path(d) / CHECKPOINT_NAME).is_file():  # not a refusal marker
                    candidates.append(load_checkpoint(Path(d) / CHECKPOINT_NAME))
        if config.get("driver_state") is not None:  # the run directory's own checkpoint, via the object store
            path = Path(tempfile.mkdtemp()) / CHECKPOINT_NAME
            path.write_bytes(ray.get(config["driver_state"]))
            candidates.append(load_checkpoint(path))
            shutil.rmtree(path.parent, ignore_errors=True)
        return pick_resume_state(candidates)

    def report_with(metrics: dict, write=None) -> None:  # write(folder) fills the reported checkpoint
        if write is None:
            ray.train.report(metrics)
            return
        with tempfile.TemporaryDirectory() as tmp:
            write(Path(tmp))
            ray.train.report(metrics, checkpoint=ray.train.Checkpoint.from_directory(tmp))

    def report(metrics: dict, state: dict | None) -> None:
        report_with(metrics, None if state is None else lambda d: save_checkpoint(d / CHECKPOINT_NAME, state))

    def log(line: str) -> None:  # once (Ray Train's patched print would also echo it through logging)
        sys.__stdout__.write(line + "\n")
        sys.__stdout__.flush()

    quieten_checkpoint_reports()

    def refuse(message: str) -> None:  # on every rank at once; rank 0 reports the marker checkpoint
        report_with({REFUSED: message, "heartctl_call": config["call"]},
                    (lambda d: (d / REFUSED_FILE).write_text(message)) if rank == 0 else None)

    dist = Dist(rank=rank, world=world, device=device, wrap_model=ray.train.torch.prepare_model, restore=restore,
                report=report, log=log, write_local=same_host)
    bundle, refusal = worker_data(cfg, rank, ray.util.get_node_ip_address(), same_host)
    refusal = agreed_refusal(refusal, world, device)
    if refusal is not None:
        refuse(refusal)
        return
    try:
        fit(cfg, run_dir, dist, bundle=bundle)
    except TrainingDiverged as exc:  # on every rank at once (reduced losses)
        refuse(str(exc))


def _check_local_checkpoint(local: Path) -> None:
    """A damaged checkpoint in the run directory is an input error, found before any worker starts."""
    if local.is_file():
        saved = load_checkpoint(local)
        if saved.get("kind") == "gnn":
            check_resume_parts(saved, local, TrainConfig.from_dict(saved["train_config"]).model.ema_decay > 0)


def _latest_checkpoint(result) -> dict | None:
    """The newest checkpoint Ray Train kept for this run (its checkpoint.pt), or None."""
    for checkpoint, _ in reversed(result.best_checkpoints or [(result.checkpoint, None)]):  # latest first
        if checkpoint is None:
            continue
        with checkpoint.as_directory() as d:
            if (Path(d) / CHECKPOINT_NAME).is_file():
                return load_checkpoint(Path(d) / CHECKPOINT_NAME)
    return None


def train_with_ray(cfg: TrainConfig, run_dir: str | os.PathLike, gpus: int = 0, cpu_workers: int = 2,
                   max_failures: int = 2, threads_per_worker: int = 1) -> TrainingSummary:
    """Train on `gpus` GPU workers (NCCL), or `cpu_workers` CPU workers (gloo) when gpus == 0.
    Ray must be initialised by the caller. Re-running with the same run_dir resumes from the latest
    checkpoint (Ray's storage under run_dir/ray, or run_dir/checkpoint.pt, whichever is further).
    Returns the loop's summary (from the final checkpoint). A TrainerError raised on a worker is
    raised here as itself; other worker failures as Ray's TrainingFailedError."""
    import ray
    from ray.train import CheckpointConfig, FailureConfig, RunConfig, ScalingConfig, TrainingFailedError
    from ray.train.torch import TorchConfig, TorchTrainer

    from trainer.training.loop import best_val_md, pick_resume_state, write_metrics_csv

    if gpus < 0 or cpu_workers < 1:
        raise TrainerError("`gpus` must be ≥ 0 and the CPU worker count ≥ 1")
    from dataclasses import replace

    from storage.location import is_url

    if not is_url(cfg.store):  # workers run in their own working directory
        cfg = replace(cfg, store=str(Path(cfg.store).resolve()))
    run_dir = Path(run_dir).resolve()
    made_run_dir = not run_dir.exists()
    run_dir.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(run_dir)  # a killed save's; the workers save into Ray's storage, this driver at the end
    local = run_checkpoint_path(run_dir)
    driver_state = ray.put(local.read_bytes()) if local.is_file() else None
    _check_local_checkpoint(local)
    use_gpu = gpus > 0
    call = uuid.uuid4().hex  # tells this call's refusal marker from an earlier call's
    scaling = ScalingConfig(num_workers=gpus if use_gpu else cpu_workers, use_gpu=use_gpu,
                            resources_per_worker=None if use_gpu else {"CPU": threads_per_worker})
    trainer = TorchTrainer(
        _train_worker,
        train_loop_config={"train_config": cfg.as_dict(), "run_dir": str(run_dir), "driver_state": driver_state,
                           "driver_ip": ray.util.get_node_ip_address(), "threads_per_worker": threads_per_worker,
                           "call": call},
        torch_config=TorchConfig(backend="nccl" if use_gpu else "gloo"),
        scaling_config=scaling,
        run_config=RunConfig(name=RAY_RUN_NAME, storage_path=str(run_dir),
                             failure_config=FailureConfig(max_failures=max_failures),
                             checkpoint_config=CheckpointConfig(num_to_keep=2)),
    )
    if not serves_state_api():
        without_pg_cleaner(trainer)
    try:
        result = trainer.fit()
    except TrainingFailedError as exc:  # a worker's bad input or full disk reaches the caller as itself
        cause = worker_trainer_error(exc) or worker_disk_full(exc, run_dir)
        if cause is None:
            raise
        raise cause from None
    if result.error is not None:  # pragma: no cover - surfaced by fit() raising in practice
        raise result.error
    metrics = result.metrics or {}  # Ray restores the latest checkpoint's metrics from an earlier call too
    refused = metrics.get(REFUSED) if metrics.get("heartctl_call") == call else None
    final = pick_resume_state([_latest_checkpoint(result), load_checkpoint(local) if local.is_file() else None])
    if final is None:  # refused or diverged before any checkpoint: Ray's storage holds nothing to resume from
        shutil.rmtree(run_dir / RAY_RUN_NAME, ignore_errors=True)
        if made_run_dir:
            try:
                run_dir.rmdir()
            except OSError:  # not empty
                pass
        raise TrainerError(refused or "Ray Train finished without a checkpoint")
    save_checkpoint(local, {k: v for k, v in final.items() if k not in ("format", "version")})
    write_metrics_csv(run_dir / "metrics.csv", final.get("history", []))
    if refused:  # the run directory keeps the last checkpoint from before
        raise TrainerError(refused)
    hist = final.get("history", [])
    backend = "nccl" if use_gpu else "gloo"
    return TrainingSummary(config=cfg.config_name, run_dir=str(run_dir), epoch=int(final["epoch"]),
                           best_epoch=final.get("best_epoch"), best_val_loss=final.get("best_val"),
                           best_val_md_mm=best_val_md(hist, final.get("best_epoch")),
                           stopped_early=bool(final.get("stopped_early")), n_parameters=final.get("n_parameters"),
                           workers=scaling.num_workers, backend=backend, ray_storage=str(run_dir / RAY_RUN_NAME),
                           mode=f"Ray Train, {scaling.num_workers} {'GPU' if use_gpu else 'CPU'} worker(s), {backend}")
