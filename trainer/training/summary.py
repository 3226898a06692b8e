"""What a training run did, as `heartctl train` prints it and `--json` writes it."""
from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class TrainingSummary:
    """A finished (or stopped) training run.

    epoch: the epochs the run directory holds; best_epoch: the one kept as the best model (lowest
    validation loss, or training loss without validation cases); best_val_md_mm: its validation mean
    node distance, mm (None without validation cases); n_parameters: the network's.
    mode: how it ran ("in-process", "Ray Train, 1 GPU worker(s), nccl", …).
    The plain loop also says epochs_run (this call's), resumed_from, train_cases, labelled_cases and
    wall_s; Ray Train says workers, backend and ray_storage. What a mode does not know is None."""

    config: str
    run_dir: str
    epoch: int
    best_epoch: int | None
    best_val_loss: float | None
    best_val_md_mm: float | None
    stopped_early: bool
    n_parameters: int | None
    mode: str = ""
    epochs_run: int | None = None
    resumed_from: int | None = None
    train_cases: int | None = None
    labelled_cases: int | None = None
    wall_s: float | None = None
    workers: int | None = None
    backend: str | None = None
    ray_storage: str | None = None

    def as_dict(self) -> dict:
        return asdict(self)
