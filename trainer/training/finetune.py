"""Fine-tuning (`heartctl train --init-from`): a run that starts from a trained network's weights and
keeps its normalisation, with a fresh optimiser and schedule; the parent checkpoint and its checks."""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

from trainer.training.checkpoint import CHECKPOINT_NAME, DIGEST_KEY, check_finite_weights, load_checkpoint, tensors_digest
from trainer.config import TrainConfig, describe_model
from trainer.errors import TrainerError
from trainer.data.normalisation import Normalisation


@dataclass(frozen=True)
class Parent:
    """The checkpoint a run starts from: its file, tensors digest, network, the normalisation the new
    run keeps, and the weights it was evaluated with (the best model; the weight average's with EMA)."""

    path: Path
    digest: str
    config_name: str
    norm: Normalisation
    epoch: int
    best_val_md_mm: float | None
    weights: dict = field(repr=False)
    train_descriptors: dict = field(repr=False, default_factory=dict)  # the parent's training shapes'

    def describe(self) -> str:
        md = f", validation MD {self.best_val_md_mm:.3f} mm on its own labels" if self.best_val_md_mm is not None else ""
        return f"{self.path} ({self.config_name}, its best epoch {self.epoch}{md})"


def parent_checkpoint_path(location) -> Path:
    """A run directory's checkpoint.pt, or the checkpoint file itself (absolute)."""
    path = Path(location).expanduser().resolve()
    return path / CHECKPOINT_NAME if path.is_dir() else path


def _network(model) -> dict:
    """The fields that make two networks the same (the GAT kernel computes the same maths either way)."""
    return {k: v for k, v in model.as_dict().items() if k != "gat_kernel"}


def load_parent(cfg: TrainConfig) -> Parent:
    """The parent checkpoint of a fine-tuning TrainConfig, checked: readable and undamaged (digest), a
    network (not the PCA baseline) whose configuration is the run's, finite weights, and, once the run
    has recorded it, the same digest. TrainerError (one line) otherwise."""
    if cfg.init_from is None:
        raise TrainerError("this run has no `init_from`")
    path = parent_checkpoint_path(cfg.init_from)
    if not path.is_file():
        raise TrainerError(f"init_from={cfg.init_from}: no checkpoint at {path} (give a run directory or its {CHECKPOINT_NAME})")
    state = load_checkpoint(path)
    if state.get("kind") != "gnn":
        raise TrainerError(f"init_from={path} holds a {state.get('kind')} run; fine-tuning starts from a network")
    saved = TrainConfig.from_dict(state["train_config"])
    if _network(saved.model) != _network(cfg.model):
        raise TrainerError(f"init_from={path} holds the network {describe_model(saved.model)}; this command trains "
                           f"{describe_model(cfg.model)}: give the configuration options it was trained with")
    weights = state.get("best_model") or state.get("model")
    if not isinstance(weights, dict) or not weights:
        raise TrainerError(f"checkpoint {path} is damaged: it holds no model weights to start from")
    check_finite_weights(weights, saved.config_name)
    digest = state.get(DIGEST_KEY) or tensors_digest(state)
    if cfg.init_from_sha256 is not None and digest != cfg.init_from_sha256:
        raise TrainerError(f"init_from={path} changed since this run started from it (digest {digest[:12]}…, "
                           f"recorded {cfg.init_from_sha256[:12]}…); use a new `run_dir`")
    history = state.get("history") or []
    md = next((r.get("val_md_mm") for r in history if r.get("epoch") == state.get("best_epoch")), None)
    return Parent(path, digest, saved.config_name, Normalisation.from_dict(state["normalisation"]),
                  int(state.get("best_epoch") or state["epoch"]),
                  float(md) if md is not None and math.isfinite(md) else None, weights,
                  dict(state.get("train_descriptors") or {}))


def with_parent(cfg: TrainConfig) -> TrainConfig:
    """cfg with its parent checked and recorded: init_from the checkpoint file's absolute path,
    init_from_sha256 its digest (what config.json and the checkpoint keep, and a resumed run checks)."""
    parent = load_parent(cfg)
    return replace(cfg, init_from=str(parent.path), init_from_sha256=parent.digest)
