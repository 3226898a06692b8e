"""Checkpoints of a run: plain dicts of tensors, numbers, strings and lists, written atomically with
torch.save and read back with torch.load(weights_only=True), so no arbitrary object is unpickled.
A SHA-256 of every tensor is recorded when saving and checked when loading: torch stores tensors
uncompressed and does not check them, so a flipped bit would otherwise load as a different network."""
from __future__ import annotations

import hashlib
import io
import math
import os
from pathlib import Path

import torch

from storage.disk import DISK_FULL_ERRNOS
from storage.meshfiles import atomic_write

from trainer.errors import TrainerError

FORMAT = "heartctl.trainer.checkpoint"
VERSION = 1
CHECKPOINT_NAME = "checkpoint.pt"
REQUIRED = ("format", "version", "kind", "train_config", "normalisation", "fingerprint", "split", "epoch")
DIGEST_KEY = "tensors_sha256"


class DiskFullError(RuntimeError):
    """No space (or quota) left where a checkpoint is saved: a failure of the run, not bad input; the
    checkpoint saved before it is intact. The message is one line."""


def disk_full_error(folder, exc: BaseException | None = None) -> DiskFullError:
    why = f" ({os.strerror(exc.errno)})" if isinstance(exc, OSError) and exc.errno else ""
    return DiskFullError(f"disk full saving a checkpoint in {folder}{why}; the run keeps its last checkpoint: free "
                         f"space and rerun the same command to resume from it")


def _tensors(value, path: str = ""):
    """(path, tensor) for every tensor inside nested dicts, lists and tuples, in a fixed order."""
    if isinstance(value, torch.Tensor):
        yield path, value
    elif isinstance(value, dict):
        for k in sorted(value, key=str):
            yield from _tensors(value[k], f"{path}/{k}")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            yield from _tensors(v, f"{path}/{i}")


def tensors_digest(state: dict) -> str:
    """SHA-256 over the name, dtype, shape and bytes of every tensor of a checkpoint (its digest entry
    left out)."""
    h = hashlib.sha256()
    for name, t in _tensors({k: v for k, v in state.items() if k != DIGEST_KEY}):
        t = t.detach().to("cpu")
        dense = torch.empty(t.shape, dtype=t.dtype).copy_(t)  # fresh strides (an expanded 1-element tensor has stride 0)
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(dense.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def save_checkpoint(path: str | os.PathLike, state: dict) -> None:
    """Write `state` (with format/version and the tensors' digest added) to `path` via a temporary
    file and a rename. torch.save serialises into memory and Python writes the bytes, so that a full
    disk is an OSError with its errno (torch's own file writer says "unexpected pos"): DiskFullError
    (one line), the temporary file removed and the checkpoint before it intact."""
    path = Path(path)
    full = {"format": FORMAT, "version": VERSION, **state}
    full[DIGEST_KEY] = tensors_digest(full)
    buffer = io.BytesIO()
    torch.save(full, buffer)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, lambda tmp: _write_bytes(tmp, buffer.getbuffer()))
    except OSError as exc:
        if exc.errno not in DISK_FULL_ERRNOS:
            raise
        raise disk_full_error(path.parent, exc) from None


def _write_bytes(path, data) -> None:
    with open(path, "wb") as f:
        f.write(data)


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
    if DIGEST_KEY in state and state[DIGEST_KEY] != tensors_digest(state):
        raise TrainerError(f"checkpoint {path} is damaged: its tensors do not match the digest recorded when it was "
                           f"saved (a changed byte); use another copy or train again")
    check_contents(state, path)
    return state


def check_contents(state: dict, path) -> None:
    """TrainerError (one line) unless the checkpoint's parts read back as what training wrote: a
    configuration, a usable normalisation (finite centre, positive scales), a store fingerprint, the
    split's case keys and the per-epoch history."""
    from trainer.config import TrainConfig
    from trainer.data.normalisation import Normalisation

    def bad(part: str, why: str):
        return TrainerError(f"checkpoint {path} is damaged: its {part} {why}")

    for part, kind in (("train_config", dict), ("normalisation", dict), ("fingerprint", dict), ("split", dict),
                       ("kind", str), ("history", list)):
        if part in state and not isinstance(state[part], kind):
            raise bad(part, f"is a {type(state[part]).__name__}, not a {kind.__name__}")
    try:
        TrainConfig.from_dict(state["train_config"])
    except TrainerError as exc:  # a configuration this heartctl cannot resolve, or a bad value
        raise TrainerError(f"checkpoint {path}: its configuration does not resolve: {exc}") from None
    except Exception as exc:  # KeyError, TypeError of a damaged dict
        raise bad("train_config", f"does not read back ({type(exc).__name__}: {str(exc)[:80]})") from None
    try:
        norm = Normalisation.from_dict(state["normalisation"])
        values = [*norm.centre_mm, norm.scale_mm, norm.disp_scale_mm, *norm.param_lo, *norm.param_hi, *norm.load_coef]
        usable = len(norm.centre_mm) == 3 and all(map(math.isfinite, values)) and norm.scale_mm > 0 and norm.disp_scale_mm > 0
    except Exception as exc:
        raise bad("normalisation", f"does not read back ({type(exc).__name__}: {str(exc)[:80]})") from None
    if not usable:
        raise bad("normalisation", "holds a non-finite value or a scale ≤ 0")
    for name, keys in state["split"].items():
        if not isinstance(keys, (list, tuple)) or any(not isinstance(k, (list, tuple)) or len(k) != 2 for k in keys):
            raise bad("split", f"{name!r} is not a list of (shape, case) keys")
    if any(not isinstance(h, dict) or "epoch" not in h for h in state.get("history", [])):
        raise bad("history", "has an entry without its epoch")


RESUME_PARTS = ("model", "optimizer", "scheduler", "best_val", "best_epoch", "bad_epochs", "history")


def check_finite_weights(weights: dict, label: str) -> None:
    """TrainerError unless every floating-point tensor of a state dict is finite."""
    if not all(bool(torch.isfinite(v).all()) for v in weights.values()
               if isinstance(v, torch.Tensor) and v.is_floating_point()):
        raise TrainerError(f"the {label} run's weights are not finite: its training diverged "
                           f"(train again into a new `run_dir` with a lower `lr`)")


def check_resume_parts(state: dict, path, weight_average: bool) -> None:
    """TrainerError (one line) unless a network checkpoint holds what resuming reads, with finite weights."""
    missing = [k for k in RESUME_PARTS + (("weight_average",) if weight_average else ()) if k not in state]
    if missing:
        raise TrainerError(f"checkpoint {path} is damaged: it lacks {', '.join(missing)}, which resuming needs")
    if not isinstance(state["model"], dict):
        raise TrainerError(f"checkpoint {path} is damaged: its model weights are not a dict of tensors")
    from trainer.config import TrainConfig

    check_finite_weights(state["model"], TrainConfig.from_dict(state["train_config"]).config_name)


def run_checkpoint_path(run_dir: str | os.PathLike) -> Path:
    return Path(run_dir) / CHECKPOINT_NAME


def remove_stale_temporaries(run_dir: str | os.PathLike) -> list[Path]:
    """Delete the temporary files (`.checkpoint.*.pt`, save_checkpoint's) that a run killed while
    saving left in run_dir; returns them. Call it when a run starts or resumes there, before it saves:
    the run directory has one writer, so no temporary of a live save is taken."""
    name = Path(CHECKPOINT_NAME)
    removed = []
    for tmp in Path(run_dir).glob(f".{name.stem}.*{name.suffix}"):
        try:
            tmp.unlink()
            removed.append(tmp)
        except OSError:
            pass
    return removed


def load_run(run_dir: str | os.PathLike) -> dict:
    """The checkpoint of a finished or running run directory."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise TrainerError(f"{run_dir} is a file, not a run directory (the folder given to heartctl train `run_dir`)")
    if not run_dir.is_dir():
        raise TrainerError(f"run directory {run_dir} does not exist")
    path = run_checkpoint_path(run_dir)
    if not path.is_file():
        raise TrainerError(f"run directory {run_dir} has no {CHECKPOINT_NAME}; train into it first (heartctl train)")
    return load_checkpoint(path)


def cpu_state(module: torch.nn.Module) -> dict:
    return {k: v.detach().to("cpu", copy=True) for k, v in module.state_dict().items()}
