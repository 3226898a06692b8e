"""The network shipped with heartctl (docs/model-card.md): a run directory in this package, `network/`,
holding `checkpoint.pt` (the best weights in half precision with the run's configuration, normalisation,
store fingerprint, split and training-shape descriptors) and `trade/trade.json` (its speed–accuracy
table, read by `unload --method auto`), and `manifest.json`: the SHA-256 of each file, checked before
the network is used, and what the network was trained and scored on.

`package_run` makes that folder from a trained run; `shipped_run` returns it, checked."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

from storage.disk import file_sha256

from trainer.training.checkpoint import CHECKPOINT_NAME, load_run, save_checkpoint
from trainer.errors import TrainerError

HERE = Path(__file__).resolve().parent
NETWORK = HERE / "network"
MANIFEST = HERE / "manifest.json"
SHIPPED_PARTS = ("kind", "train_config", "normalisation", "fingerprint", "split", "labelled", "train_descriptors",
                 "epoch", "best_val", "best_epoch", "history", "stopped_early", "finished", "n_parameters")
MAX_BYTES = 10 * 2**20


def shipped_run(folder: Path | None = None, manifest: Path | None = None) -> Path:
    """The shipped network's run directory (default: this package's), after checking every file's
    SHA-256 against the manifest; TrainerError (one line) when it is missing or any byte differs."""
    folder, manifest = folder or NETWORK, manifest or MANIFEST
    if not manifest.is_file() or not (folder / CHECKPOINT_NAME).is_file():
        raise TrainerError("this heartctl has no shipped network (its package data is missing): give `run` DIR of a "
                           "network you trained, or rebuild the shipped one with scripts/build_network.sh")
    try:
        files = json.loads(manifest.read_text())["files"]
    except (json.JSONDecodeError, KeyError, TypeError, UnicodeDecodeError):
        raise TrainerError(f"the shipped network's manifest {manifest} is damaged: reinstall heartctl") from None
    for name, digest in files.items():
        path = folder / name
        if not path.is_file() or file_sha256(path) != digest:
            raise TrainerError(f"the shipped network's {name} does not match its digest in {manifest.name} (a changed "
                               f"or missing file): reinstall heartctl, or give `run` DIR")
    return folder


def package_run(run_dir: Path, trade_dir: Path | None, card: dict, folder: Path | None = None,
                manifest: Path | None = None) -> dict:
    """Write the shipped network from a trained run: its best weights (the weight average's under EMA)
    in half precision, the parts prediction reads, the run's trade table, and the manifest with
    `card` (what it was trained and scored on). Returns the manifest. Refuses a package over 10 MB.
    folder, manifest: default this package's."""
    folder, manifest = folder or NETWORK, manifest or MANIFEST
    state = load_run(run_dir)
    weights = state.get("best_model") or state["model"]
    shipped = {k: state[k] for k in SHIPPED_PARTS if k in state}
    shipped["shipped"] = True
    shipped["best_model"] = {k: (v.half() if v.is_floating_point() else v) for k, v in weights.items()}
    if folder.exists():
        shutil.rmtree(folder)
    save_checkpoint(folder / CHECKPOINT_NAME, shipped)
    files = [CHECKPOINT_NAME]
    if trade_dir is not None:
        (folder / "trade").mkdir(parents=True)
        shutil.copyfile(Path(trade_dir) / "trade.json", folder / "trade" / "trade.json")
        files.append("trade/trade.json")
    size = sum((folder / f).stat().st_size for f in files)
    if size > MAX_BYTES:
        raise TrainerError(f"the packaged network is {size / 2**20:.1f} MB, over the {MAX_BYTES / 2**20:.0f} MB limit")
    out = {"files": {f: file_sha256(folder / f) for f in files}, "bytes": size,
           "weights": "float16", "parameters": int(sum(v.numel() for v in weights.values())), **card}
    manifest.write_text(json.dumps(out, indent=1) + "\n")
    return out


def record(fields: dict, manifest: Path | None = None) -> dict:
    """Add `fields` (measurements of the packaged network) to the manifest; returns it."""
    manifest = manifest or MANIFEST
    out = {**json.loads(manifest.read_text()), **fields}
    manifest.write_text(json.dumps(out, indent=1) + "\n")
    return out


def half_precision_error_mm(run_dir: Path, folder: Path, items: list) -> float:
    """Largest nodal difference (mm) between the run's full-precision network and the packaged
    half-precision one on `items` ((MeshFeatures, params, key) as Predictor.predict_many takes)."""
    from trainer.evaluation.predict import Predictor

    full = Predictor.from_run(run_dir).predict_many(items)
    half = Predictor.from_run(folder).predict_many(items)
    return float(max(torch.linalg.vector_norm(torch.as_tensor(a - b), dim=1).max() for a, b in zip(full, half)))
