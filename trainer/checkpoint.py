"""Checkpoints of a run: plain dicts of tensors, numbers, strings and lists, written atomically with
torch.save and read back with torch.load(weights_only=True), so no arbitrary object is unpickled."""
from __future__ import annotations

import os
from pathlib import Path

import torch

from storage.meshfiles import atomic_write

from .config import TrainerError

FORMAT = "heartctl.trainer.checkpoint"
VERSION = 1
CHECKPOINT_NAME = "checkpoint.pt"
REQUIRED = ("format", "version", "kind", "train_config", "normalisation", "fingerprint", "split", "epoch")


def save_checkpoint(path: str | os.PathLike, state: dict) -> None:
    """Write `state` (with format/version added) to `path` via a temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: torch.save({"format": FORMAT, "version": VERSION, **state}, tmp))


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read a checkpoint on the CPU; TrainerError (one line) for a missing, damaged or foreign file."""
    path = Path(path)
    if not path.is_file():
        raise TrainerError(f"no checkpoint at {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # UnpicklingError, RuntimeError (zip), EOFError, …
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise TrainerError(f"cannot read checkpoint {path}: damaged or not a heartctl checkpoint ({reason[:120]})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise TrainerError(f"{path} is not a heartctl training checkpoint")
    if state.get("version") != VERSION:
        raise TrainerError(f"checkpoint {path} has version {state.get('version')!r}; this heartctl reads {VERSION}")
    missing = [k for k in REQUIRED if k not in state]
    if missing:
        raise TrainerError(f"checkpoint {path} lacks {', '.join(missing)}")
    return state


def run_checkpoint_path(run_dir: str | os.PathLike) -> Path:
    return Path(run_dir) / CHECKPOINT_NAME


def load_run(run_dir: str | os.PathLike) -> dict:
    """The checkpoint of a finished or running run directory."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise TrainerError(f"run directory {run_dir} does not exist")
    path = run_checkpoint_path(run_dir)
    if not path.is_file():
        raise TrainerError(f"run directory {run_dir} has no {CHECKPOINT_NAME}; train into it first (heartctl train)")
    return load_checkpoint(path)


def cpu_state(module: torch.nn.Module) -> dict:
    return {k: v.detach().to("cpu", copy=True) for k, v in module.state_dict().items()}
