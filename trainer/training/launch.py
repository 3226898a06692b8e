"""Starting a training run as `heartctl train` asks: where it runs (this process, or Ray Train
workers), the checks made before anything starts, and the run in this process.

Every refusal is a TrainerError (or StoreError) of one line, raised before a worker or Ray starts:
workers would retry a refusal --max-failures times.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, replace
from pathlib import Path

from trainer.config import TrainConfig
from trainer.errors import TrainerError
from trainer.training.summary import TrainingSummary


@dataclass(frozen=True)
class Placement:
    """Where a run trains: in this process (`no_ray`, on `device`: cpu | cuda, default cuda when
    available), or as Ray Train workers: `gpus` GPU workers (NCCL), or `workers` CPU workers (gloo)
    when gpus is 0, on a local Ray (`local`: two CPU workers, a few epochs) or on the cluster at
    `address`; `max_failures` restarts from the last checkpoint after a worker dies."""

    gpus: int = 0
    workers: int = 2
    local: bool = False
    no_ray: bool = False
    device: str | None = None
    address: str | None = None
    max_failures: int = 2

    def __post_init__(self):
        if self.local and (self.gpus or self.address):
            raise TrainerError("`local` runs two CPU workers on a local Ray; it takes no `gpus` or `address`")
        if self.no_ray and (self.local or self.address or self.gpus):
            raise TrainerError("`no_ray` trains in this process; drop `local`, `address` and `gpus` (use `device`)")
        if self.gpus < 0 or self.workers < 1 or self.max_failures < 0:
            raise TrainerError("`gpus` ≥ 0, `workers` ≥ 1 and `max_failures` ≥ 0 are required")
        if self.device not in (None, "cpu", "cuda"):
            raise TrainerError(f"`device` must be cpu or cuda, got {self.device!r}")

    def in_process(self, cfg: TrainConfig) -> bool:
        """Whether the run trains in this process: --no-ray, or a PCA fit (no workers to spread)."""
        return self.no_ray or cfg.model.kind == "pca"

    @property
    def default_epochs(self) -> int:
        return 5 if self.local else 500


def prepare_training(store: str, run_dir: Path, placement: Placement, config: str, model_options: dict,
                     run_options: dict) -> TrainConfig:
    """The run's TrainConfig, composed from the `config` name changed by `model_options` (compose's
    keywords) and `run_options` (TrainConfig's fields; scale_pct, lr_schedule and epochs None for the
    preset's or the default), after every check that can be made before training starts: the split,
    the store, a writable run directory, a checkpoint there of the same run that can be resumed, and
    the CUDA devices asked for; with `init_from` (fine-tuning), the parent checkpoint checked and
    recorded (trainer.training.finetune.with_parent)."""
    from storage.location import StoreError, is_url
    from storage.schema import inspect_store

    from trainer.training.checkpoint import load_checkpoint, run_checkpoint_path
    from trainer.config import compose, describe_model
    from trainer.data.store_cases import check_split, training_data
    from trainer.training.finetune import with_parent
    from trainer.training.loop import check_resumable, check_same_run
    from trainer.data.splits import parse_split

    model, preset_options = compose(config, **model_options)
    options = dict(run_options)
    for key in ("scale_pct", "lr_schedule"):
        if options.get(key) is None:
            options.pop(key, None)
    preset_options.update({k: options.pop(k) for k in list(options) if k in preset_options})
    if options.get("epochs") is None:
        options["epochs"] = placement.default_epochs
    parse_split(options.get("split", "shape"))
    if not is_url(store):  # Ray Train workers run in their own working directory
        store = str(Path(store).resolve())
    run_dir = run_dir.resolve()
    cfg = TrainConfig(store=store, config_name=describe_model(model), model=model, **options, **preset_options)
    if inspect_store(store) is None:
        raise StoreError(f"no heartctl store at {store}")
    if cfg.init_from is not None:
        cfg = with_parent(cfg)
    nearest = next(p for p in (run_dir, *run_dir.parents) if p.exists())  # made with its parents when training starts
    if not nearest.is_dir():
        raise TrainerError(f"run_dir={run_dir}: {nearest} is a file")
    if not os.access(nearest, os.W_OK | os.X_OK):
        raise TrainerError(f"run_dir={run_dir}: the folder {nearest} is not writable")
    ckpt = run_checkpoint_path(run_dir)
    in_process = placement.in_process(cfg)
    if ckpt.is_file():  # refused here, before Ray starts (whose workers would retry a refusal)
        state = load_checkpoint(ckpt)
        check_same_run(state, cfg, run_dir)
        if not in_process:  # the plain loop checks the store itself
            check_resumable(state, cfg, training_data(cfg), run_dir)
    elif not in_process:
        check_split(cfg)
    _check_cuda(placement)
    return cfg


def _check_cuda(placement: Placement) -> None:
    """TrainerError when this machine lacks the CUDA devices asked for (a joined cluster has its own)."""
    import torch

    gpus = placement.gpus
    if gpus and not placement.address and torch.cuda.device_count() < gpus:
        raise TrainerError(f"gpus={gpus}: this machine has {torch.cuda.device_count()} CUDA device(s); "
                           f"use `gpus` 0 for CPU workers")
    if placement.device == "cuda" and not torch.cuda.is_available():
        raise TrainerError("`device` cuda: no CUDA device is available here")


def train_in_process(cfg: TrainConfig, run_dir: Path, placement: Placement, log) -> TrainingSummary:
    """The plain PyTorch loop in this process (no Ray); the loop's summary with its `mode`."""
    import torch

    from trainer.training.loop import Dist, fit

    device = torch.device(placement.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    summary = fit(cfg, Path(run_dir).resolve(), Dist(device=device, log=log))
    return replace(summary, mode="in-process" if cfg.model.kind != "pca" else "in-process (PCA fit, no Ray needed)")
